"""Speed levers of the fit (pig.avatar.training) against independent references, each within a stated tolerance:
bf16 and compiled decoders, SSIM's shifted-sum blur, CG's residual checks, the batched render and loss, fused Adam,
the windowed train log; and the learning-rate schedule and time budget."""
import copy
import math
import time
import warnings
from contextlib import nullcontext

import numpy as np
import pytest
import torch
from torch._dynamo.utils import counters

from pig.avatar.batches import Picks, TrainingBatch, ViewBatch
from pig.avatar.build import build_optimizers
from pig.avatar.checkpoint import load_avatar
from pig.avatar.decoders import AnchorDecoder
from pig.avatar.losses import boundary_band, boundary_band_host
from pig.avatar.training import FitConfig, LossTerms, iteration_loss, lr_factor
from pig.body.params import SmplxParams
from pig.config import ConfigError, derive_preset, load_preset, load_section
from pig.field.knn_graph import knn_laplacian
from pig.field.knn_solve import CGNotConverged, CGSystem
from pig.field.optim import Adam
from pig.field.precondition import PrecondConfig
from pig.metrics.ssim import gaussian_window, ssim, ssim_map
from pig.render.api import RenderError, render_gaussians, render_timesteps
from avatar_fixture import small_avatar

HEADS = ("offset", "rotation", "scale", "opacity", "sh")


# ---- 1, 2: decoders in bf16 autocast and compiled ----


def _decode(decoder: AnchorDecoder, y: torch.Tensor, weights: dict[str, torch.Tensor]):
    """Decoded heads, and the gradients of sum(weights * heads) for every parameter and the input."""
    decoder.zero_grad(set_to_none=True)
    y = y.clone().requires_grad_()
    out = decoder(y, log_scale_prior=-3.0)
    sum(((getattr(out, k) * weights[k]).sum() for k in HEADS)).backward()
    return out, [p.grad for p in decoder.parameters()] + [y.grad]


def _decoder_batch(single_mlp: bool, anchors: int = 512, inputs: int = 28):
    torch.manual_seed(0)
    # Output gain 1: every head far from its initial value, as after training (the default 0.01 leaves the
    # rotation and scale heads at the identity and the prior, where any precision agrees).
    decoder = AnchorDecoder(inputs, 64, 2, 1, single_mlp=single_mlp, output_gain=1.0)
    g = torch.Generator().manual_seed(1)
    y = torch.randn(anchors, inputs, generator=g)
    out = decoder(y)
    weights = {k: torch.randn(getattr(out, k).shape, generator=g) for k in HEADS}
    return decoder, y, weights


@pytest.mark.parametrize("single_mlp", [False, True])
def test_bf16_decoder_matches_float32_with_float32_weights(single_mlp):
    """bf16 keeps 8 significant bits: each rounding is off by at most u = 2^-8 = 3.9e-3 relative. Autocast
    rounds every linear layer's input, weights and output (3 roundings a layer, 3 layers, float32 sums), so
    each head is off by about sqrt(9) u / sqrt(3) ~ 7e-3 of its size (rounding errors uniform in +-u, random
    signs), the parameterisations after the MLPs (quaternion norm, exp, sigmoid) being float32 and
    1-Lipschitz at this scale. Measured max |bf16 - float32| / max |float32| over 512 anchors: 3.6e-3
    (offset), 1.9e-3 (rotation), 1.4e-3 (scale), 7.2e-4 (opacity), 5.0e-3 (sh); bound 2e-2 (~5 u).
    Gradients go through the same roundings: cosine to float32's measured >= 0.9958; bound 0.99."""
    decoder, y, weights = _decoder_batch(single_mlp)
    reference, reference_grads = _decode(decoder, y, weights)
    decoder.set_precision("bf16")
    fast, fast_grads = _decode(decoder, y, weights)
    for k in HEADS:
        a, b = getattr(reference, k), getattr(fast, k)
        assert b.dtype == torch.float32, k  # the heads come back in the input's precision
        error = ((b - a).abs().max() / a.abs().max()).item()
        assert error < 2e-2, (k, error)
    # Autocast is on: bf16's rounding shows (float32 alone would agree to ~1e-7).
    assert ((fast.sh - reference.sh).abs().max() / reference.sh.abs().max()).item() > 1e-4
    assert all(p.dtype == torch.float32 for p in decoder.parameters())
    assert all(g.dtype == torch.float32 for g in fast_grads)
    for a, b in zip(reference_grads, fast_grads):
        cosine = torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0).item()
        assert cosine > 0.99, cosine
    decoder.set_precision("float32")  # and back: float32 again, bit for bit
    again, again_grads = _decode(decoder, y, weights)
    assert all(torch.equal(getattr(again, k), getattr(reference, k)) for k in HEADS)
    assert all(torch.equal(a, b) for a, b in zip(again_grads, reference_grads))


def test_compiled_decoder_matches_eager():
    """torch.compile (inductor, CPU) fuses and reorders float32 operations: a difference of float32 rounding,
    ~1e-7 relative per operation. Bound 1e-5 absolute on the heads (size <= 1; measured 0) and 1e-5 of each
    gradient tensor's largest element (sums over 64 anchors; measured <= 3.2e-7)."""
    decoder, y, weights = _decoder_batch(single_mlp=False, anchors=64)
    eager = copy.deepcopy(decoder)
    graphs = counters["stats"]["unique_graphs"]
    decoder.set_precision("float32", compiled=True)
    assert sorted(decoder.state_dict()) == sorted(eager.state_dict())  # the same parameters and state dict
    for _ in range(2):  # the second call runs the compiled code, the first compiles it
        compiled, compiled_grads = _decode(decoder, y, weights)
        reference, reference_grads = _decode(eager, y, weights)
        for k in HEADS:
            torch.testing.assert_close(getattr(compiled, k), getattr(reference, k), rtol=0, atol=1e-5)
        for a, b in zip(compiled_grads, reference_grads):
            assert (a - b).abs().max() <= 1e-5 * b.abs().max()
    # Dynamo captured the MLPs: the compiled code ran (nn.Module.compile() on the nn.Sequential MLPs ran them
    # eagerly, torch 2.13 skipping torch.nn's frames).
    assert counters["stats"]["unique_graphs"] > graphs



def test_compiled_posing_matches_eager(tmp_path):
    """`fit.compile_posing`: body, transport and splats of a training step through torch.compile, sync-free, against
    the eager model with the same weights. float32 reordered by inductor (fused broadcast sums for the 3 x 3 and
    4 x 4 products): bound 1e-5 absolute on the means (size ~1; measured 1.8e-7), 5e-5 on the quaternions, whose
    conversion from the rotation matrix amplifies rounding (measured 1.1e-5), and 5e-5 of each parameter's largest
    gradient (measured <= 7.2e-6). Evaluations (no grad) stay eager: no graph is compiled for them."""
    from pig.body.standin import write_standin

    write_standin(tmp_path / "body_model.npz")
    compiled, eager = (_model((tmp_path / "body_model.npz").read_bytes()) for _ in range(2))
    compiled.compile_posing()
    steps = torch.tensor([0, 2])
    weights = {}

    def step(model):
        g = model(steps, 1)
        if not weights:
            gen = torch.Generator().manual_seed(3)
            weights.update({k: torch.randn(getattr(g, k).shape, generator=gen) for k in ("means", "quats", "scales")})
        loss = sum((getattr(g, k) * w).sum() for k, w in weights.items())
        model.zero_grad(set_to_none=True)
        loss.backward()
        return g, {name: p.grad for name, p in model.named_parameters() if p.grad is not None}

    graphs = counters["stats"]["unique_graphs"]
    for _ in range(2):  # the first call compiles, the second runs the compiled code
        fast, fast_grads = step(compiled)
        reference, reference_grads = step(eager)
        for k, bound in (("means", 1e-5), ("quats", 5e-5), ("scales", 0), ("opacities", 0), ("sh", 0)):
            torch.testing.assert_close(getattr(fast, k), getattr(reference, k), rtol=0, atol=bound)
        assert sorted(fast_grads) == sorted(reference_grads) and len(reference_grads) > 5
        for name, b in reference_grads.items():
            assert (fast_grads[name] - b).abs().max() <= 5e-5 * b.abs().max(), name
    assert counters["stats"]["unique_graphs"] > graphs  # Dynamo captured the posing
    graphs = counters["stats"]["unique_graphs"]
    with torch.no_grad():
        evaluated = compiled(torch.tensor([1]), 0)
        torch.testing.assert_close(evaluated.means, eager(torch.tensor([1]), 0).means, rtol=0, atol=0)
    assert counters["stats"]["unique_graphs"] == graphs


# ---- 3: SSIM's shifted-sum blur ----


@pytest.mark.parametrize("size", [(11, 11), (17, 29), (40, 23)])
def test_ssim_shift_blur_equals_conv_in_float64(size):
    """Both blurs sum the same 121 products in another order: float64 rounding, ~1e-16 per term (bound 1e-12)."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, *size, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    y[1] = 0  # an empty (black) image: SSIM's constants alone keep it finite
    a, b = ssim_map(x, y, blur="shift"), ssim_map(x, y, blur="conv")
    assert a.shape == (2, 3, size[0] - 10, size[1] - 10)
    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    torch.testing.assert_close(ssim(x, y, reduction="none", blur="shift"), ssim(x, y, reduction="none", blur="conv"),
                               rtol=0, atol=1e-12)


def test_ssim_window_is_scipys_gaussian():
    """The window: scipy.ndimage.gaussian_filter1d's weights (sigma 1.5, radius 5), to float64 rounding."""
    offsets = np.arange(-5, 6, dtype=np.float64)
    weights = np.exp(-0.5 * (offsets / 1.5) ** 2)
    window = gaussian_window(torch.float64, "cpu").numpy()
    np.testing.assert_allclose(window, weights / weights.sum(), rtol=1e-15, atol=0)


@pytest.mark.parametrize("blur", ["conv", "shift"])
def test_ssim_with_a_window_passed_equals_the_window_made_inside(blur):
    """A window passed (float32, as the fit makes it) gives the SSIM of the window made inside, in float32 and, cast
    to the images' dtype, in float64 (float32 taps: ~1e-8 relative of each, bound 1e-7); a window of another size or
    device is refused by name."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 17, 21, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    window = gaussian_window(torch.float32, "cpu")
    torch.testing.assert_close(ssim(x.float(), y.float(), reduction="none", blur=blur, window=window),
                               ssim(x.float(), y.float(), reduction="none", blur=blur), rtol=0, atol=0)
    torch.testing.assert_close(ssim(x, y, reduction="none", blur=blur, window=window),
                               ssim(x, y, reduction="none", blur=blur), rtol=0, atol=1e-7)
    with pytest.raises(ValueError, match=r"window must be gaussian_window's \(11,\) taps on cpu, found \(9,\) on cpu"):
        ssim(x, y, blur=blur, window=window[1:-1])
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"taps on cpu, found \(11,\) on cuda"):
            ssim(x, y, blur=blur, window=window.cuda())


def test_compiled_loss_reads_a_window_made_before_compilation(monkeypatch):
    """LossTerms' compiled L1 + SSIM reads SSIM's window as an input of its graph, made once: made inside the graph
    (arange, exp) it cost 17 GiB and 6 ms a step on the GPU, and as Python constants inductor loaded 44 values an
    output in the blur's column pass against 22 (run35-run36). The graphs dynamo hands its backend are inspected."""
    graphs, inputs = [], []

    def inspect(gm, example_inputs):
        graphs.append(gm.graph)
        inputs.extend(example_inputs)
        return gm.forward

    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, mode=None: compile_(fn, backend=inspect))
    background = torch.tensor([0.2, 0.3, 0.4])
    loss = LossTerms(FitConfig(weight_lpips=0.0, band_radius_px=2.0, band_reference_height=16), background, None,
                     compiled=True)
    g = torch.Generator().manual_seed(2)
    render, images = torch.rand(2, 2, 16, 20, 3, generator=g).unbind(0)
    masks = torch.ones(2, 16, 20, dtype=torch.bool)
    terms = loss(render.requires_grad_(), images, masks, 16)
    reference = LossTerms(FitConfig(weight_lpips=0.0, band_radius_px=2.0, band_reference_height=16), background, None,
                          compiled=False)(render, images, masks, 16)
    torch.testing.assert_close(terms["total"], reference["total"], rtol=1e-6, atol=0)
    assert graphs
    called = {node.target for graph in graphs for node in graph.nodes if node.op == "call_function"}
    assert torch.arange not in called and torch.exp not in called
    windows = [t for t in inputs if isinstance(t, torch.Tensor) and t.shape == (11,)]
    assert len(windows) == 1 and torch.equal(windows[0], gaussian_window(torch.float32, "cpu"))


def test_compiled_shift_ssim_matches_conv_in_float32():
    """The compiled loss's SSIM: float32 sums of 11 + 11 taps and 5 moments, in another order; moments of
    [0, 1] images are resolved to ~1e-7, and SSIM's quotient amplifies that (at most 1 / C2 = 1.1e3) only where
    both variances vanish, which random images avoid. Bound 1e-5 on the mean (measured 0) and 1e-5 of the
    largest gradient element on the gradient (measured 1.0e-6)."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 24, 19, generator=g)
    y = (x + 0.1 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    graphs = counters["stats"]["unique_graphs"]
    compiled = torch.compile(lambda a, b: ssim(a, b, blur="shift"))
    xs, xc = x.clone().requires_grad_(), x.clone().requires_grad_()
    fast, reference = compiled(xs, y), ssim(xc, y, blur="conv")
    fast.backward()
    reference.backward()
    assert counters["stats"]["unique_graphs"] > graphs
    torch.testing.assert_close(fast, reference, rtol=0, atol=1e-5)
    assert (xs.grad - xc.grad).abs().max() <= 1e-5 * xc.grad.abs().max()
    with pytest.raises(ValueError, match=r"ssim: blur must be one of \['conv', 'shift'\], found 'fft'"):
        ssim(x, y, blur="fft")


# ---- 4: CG residual checks every k iterations ----


@pytest.mark.parametrize("lam", [0.0, 8.0, 1e4])
def test_cg_checked_every_k_iterations_meets_its_tolerance(lam, rng):
    """Every eigenvalue of A = I + lambda L is at least 1, so |x - A^-1 b| <= |b - A x| <= tol |b| per column
    (pig.field.knn_solve); the dense float64 solve is exact to ~1e-16 cond(A) ~ 1e-11 here. Checking every
    k iterations only runs CG up to k - 1 iterations longer, never stops it earlier. Measured errors with
    tol 1e-9: <= 8.7e-12 |b| (lambda 8), 7.1e-14 |b| (1e4), 0 (lambda 0: A = I)."""
    points = rng.normal(size=(80, 3))
    points[:5] *= 1e-6  # a tight cluster: near-duplicate neighbours
    lap = knn_laplacian(points, 6)
    b = torch.tensor(rng.normal(size=(80, 3)))
    b[:, 2] = 0  # a zero column
    exact = np.linalg.solve(np.eye(80) + lam * lap.toarray(), b.numpy())
    tol, max_iter = 1e-9, 120
    iterations = {}
    for every in (1, 7, 1000):
        system = CGSystem(lap, lam, tol=tol, max_iter=max_iter, check_every=every)
        with warnings.catch_warnings():
            warnings.simplefilter("error", CGNotConverged)
            x = system.solve(b)
        error = np.linalg.norm(x.numpy() - exact, axis=0)
        assert (error <= tol * np.linalg.norm(b.numpy(), axis=0) + 1e-14).all(), (every, error)
        assert x[:, 2].abs().max() == 0
        iterations[every] = system.last_iterations
    assert iterations[1] <= iterations[7] < iterations[1] + 7 and iterations[7] % 7 == 0
    assert iterations[1000] == max_iter  # never checked inside: runs to the cap, then the true residual decides
    for every in (0, -3):
        with pytest.raises(ValueError, match=rf"CGSystem: expected tol > 0, max_iter >= 1 and check_every >= 1, found "
                                             rf"tol=1e-05, max_iter=200, check_every={every}"):
            CGSystem(lap, lam, check_every=every)


def test_compiled_cg_iteration_matches_the_eager_one_and_the_dense_solve(rng):
    """`precond.cg_compile`: the same float64 iteration through torch.compile; the fused reductions may sum in
    another order, so iterates differ by rounding only (bound 1e-12 relative), and the solution meets tol."""
    points = rng.normal(size=(60, 3))
    lap = knn_laplacian(points, 5)
    b = torch.tensor(rng.normal(size=(60, 3)))
    exact = np.linalg.solve(np.eye(60) + 8.0 * lap.toarray(), b.numpy())
    eager = CGSystem(lap, 8.0, tol=1e-9, max_iter=200, check_every=4)
    compiled = CGSystem(lap, 8.0, tol=1e-9, max_iter=200, check_every=4, compiled=True)
    x_eager, x_compiled = eager.solve(b), compiled.solve(b)
    assert compiled.last_iterations == eager.last_iterations
    torch.testing.assert_close(x_compiled, x_eager, rtol=1e-12, atol=1e-12 * float(x_eager.abs().max()))
    error = np.linalg.norm(x_compiled.numpy() - exact, axis=0)
    assert (error <= 1e-9 * np.linalg.norm(b.numpy(), axis=0)).all()


def test_cg_graphs_switch_is_inert_off_cuda(rng):
    """`precond.cg_graphs` only captures CUDA work (tests/gpu/test_cg_graphs.py compares it there): on the CPU the
    solve is the launched one, bit for bit, and captures nothing."""
    points = rng.normal(size=(50, 3))
    lap = knn_laplacian(points, 5)
    b = torch.tensor(rng.normal(size=(50, 2)))
    plain = CGSystem(lap, 8.0, tol=1e-9, check_every=4)
    graphed = CGSystem(lap, 8.0, tol=1e-9, check_every=4, graphs=True)
    assert torch.equal(graphed.solve(b), plain.solve(b)) and not graphed._graphs


# ---- 5, 6, 7: batched render and loss, fused Adam ----


def _splats(k: int, n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    means = 0.4 * torch.randn(k, n, 3, generator=g)
    quats = torch.randn(k, n, 4, generator=g)
    scales = torch.exp(torch.empty(k, n, 3).uniform_(-3.5, -1.5, generator=g))
    opacities = torch.empty(k, n).uniform_(0.2, 0.95, generator=g)
    sh = 0.3 * torch.randn(k, n, 4, 3, generator=g)
    return means, quats, scales, opacities, sh


def _cameras(count: int, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cameras 3 m in front of the origin, looking down -z (y up), a little apart."""
    viewmats = torch.eye(4).repeat(count, 1, 1)
    viewmats[:, :3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    viewmats[:, 2, 3] = 3.0
    viewmats[:, 0, 3] = 0.15 * torch.arange(count)
    K = torch.tensor([[1.2 * width, 0, width / 2], [0, 1.2 * width, height / 2], [0, 0, 1]])
    return viewmats, K.repeat(count, 1, 1)


def test_render_timesteps_equals_one_render_per_timestep():
    """The CPU compositor renders each set of Gaussians into its cameras: bit for bit render_gaussians'."""
    sets, cameras, width, height = 3, 2, 20, 14
    splats = _splats(sets, 60, 0)
    viewmats, Ks = _cameras(sets * cameras, width, height)
    viewmats, Ks = viewmats.view(sets, cameras, 4, 4), Ks.view(sets, cameras, 3, 3)
    background = torch.tensor([0.1, 0.5, 0.9])
    out = render_timesteps(*splats, viewmats, Ks, width, height, background, backend="cpu")
    assert out.color.shape == (sets, cameras, height, width, 3) and out.alpha.shape == (sets, cameras, height, width, 1)
    for k in range(sets):
        one = render_gaussians(*(s[k] for s in splats), viewmats[k], Ks[k], width, height, background, backend="cpu")
        for batched, single in zip(out, one):
            assert torch.equal(batched[k], single)
    assert out.alpha.amax() > 0.5  # the splats are in view


def test_render_timesteps_refuses_mismatched_shapes():
    means, quats, scales, opacities, sh = _splats(3, 10, 0)
    viewmats, Ks = _cameras(6, 8, 8)
    viewmats, Ks = viewmats.view(3, 2, 4, 4), Ks.view(3, 2, 3, 3)
    shapes = r"expected means \(K, N, 3\), viewmats \(K, C, 4, 4\) and Ks \(K, C, 3, 3\), got "
    cases = [
        ((means[0], quats, scales, opacities, sh, viewmats, Ks), shapes + r"\(10, 3\), \(3, 2, 4, 4\) and \(3, 2, 3, 3\)"),
        ((means, quats, scales, opacities, sh, viewmats[:2], Ks[:2]), shapes + r"\(3, 10, 3\), \(2, 2, 4, 4\)"),
        ((means, quats, scales, opacities, sh, viewmats, Ks[:, :1]), shapes + r"\(3, 10, 3\), \(3, 2, 4, 4\) and \(3, 1, 3, 3\)"),
        ((means[:0], quats[:0], scales[:0], opacities[:0], sh[:0], viewmats[:0], Ks[:0]), r"render_timesteps: expected at least one set of Gaussians, got K = 0"),
        ((means, quats[:2], scales, opacities, sh, viewmats, Ks), r"quats: expected 3 sets \(K, N, \.\.\.\) like means, got \(2, 10, 4\)"),
        ((means, quats, scales, opacities[:, None], sh, viewmats, Ks), r"opacities: expected shape \(10,\)"),
        ((means, quats, scales, opacities, torch.cat([sh, sh[:1]]), viewmats, Ks), r"sh: expected 3 sets \(K, N, \.\.\.\) like means, got \(4, 10, 4, 3\)"),
        ((means, quats, scales[:, :4], opacities, sh, viewmats, Ks), r"scales: expected shape \(10, 3\)"),
        ((means, quats, scales, opacities, sh, viewmats, Ks[..., :2]), r"Ks: expected shape \(2, 3, 3\)"),
    ]
    for args, message in cases:
        with pytest.raises(RenderError, match=message):
            render_timesteps(*args, 8, 8, torch.zeros(3), backend="cpu")


def _model(standin: bytes):
    """A small avatar of 3 timesteps with learnt anchors and a body refiner: every optimiser group."""
    rng = np.random.default_rng(0)
    params = SmplxParams(rng.normal(scale=0.2, size=(3, 55, 3)), np.zeros(10), np.zeros((3, 10)), np.zeros((3, 3)))
    return small_avatar(standin, params, num_anchors=400, levels=2, sh_degree=1, hidden_layers=2, hidden_width=32)


@pytest.fixture(scope="module")
def twin_avatars(tmp_path_factory):
    """Two avatars with the same weights (built once for the module: the tests below change gradients only)."""
    from pig.body.standin import write_standin

    path = tmp_path_factory.mktemp("standin") / "body_model.npz"
    write_standin(path)
    return _model(path.read_bytes()), _model(path.read_bytes())


def _view_batch(step: int, cameras: int, width: int, height: int, seed: int) -> ViewBatch:
    g = torch.Generator().manual_seed(seed)
    viewmats, Ks = _cameras(cameras, width, height)
    masks = torch.zeros(cameras, height, width, dtype=torch.bool)
    masks[:, height // 5: -height // 5, width // 3: -width // 3] = True
    images = torch.rand(cameras, height, width, 3, generator=g) * masks[..., None]
    return ViewBatch(step, [f"cam{c}" for c in range(cameras)], viewmats, Ks, images, masks, width, height)


def _batch(lod: int, views: list[list[ViewBatch]]) -> TrainingBatch:
    """One process's batch of `views` (per timestep), each view at its place in their order (Picks.whole)."""
    picks = Picks(lod, [(step_batches[0].timestep, [cam for vb in step_batches for cam in vb.cameras])
                        for step_batches in views])
    return TrainingBatch(0, lod, [step for step, _ in picks.steps], views, 0.0, picks.whole())


def test_batched_iteration_loss_equals_the_per_batch_loss(twin_avatars):
    """One render and one loss for all views against a loss per timestep weighted by its views: the same means,
    summed in another order; float32, bound 1e-6 relative on each term and of each gradient tensor's largest
    element (measured 7.8e-8 on L1, 0 on SSIM, 8.1e-8 on the total, 0 on the gradients)."""
    model = twin_avatars[0]
    views = [[_view_batch(step, 2, 20, 16, seed)] for seed, step in enumerate((0, 2))]
    batch = _batch(0, views)
    assert batch.uniform() is not None
    cfg = FitConfig(weight_lpips=0.0, band_radius_px=2.0, band_reference_height=16)
    background = torch.tensor([0.2, 0.3, 0.4])
    loss = LossTerms(cfg, background, None, compiled=False)
    from pig.render.api import RasterizerConfig

    raster = RasterizerConfig(backend="cpu")
    results = {}
    for batched in (True, False):
        model.zero_grad(set_to_none=True)
        terms = iteration_loss(model, batch, loss, raster, background, batched, lambda name: nullcontext())
        terms["total"].backward()
        results[batched] = ({k: v.detach() for k, v in terms.items()},
                            {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None})
    (fast, fast_grads), (reference, reference_grads) = results[True], results[False]
    assert sorted(fast) == sorted(reference) == ["l1", "ssim", "total"]
    for key in reference:
        torch.testing.assert_close(fast[key], reference[key], rtol=1e-6, atol=0)
    assert fast_grads.keys() == reference_grads.keys() and len(reference_grads) > 5
    for name, grad in reference_grads.items():
        scale = grad.abs().max()
        assert (fast_grads[name] - grad).abs().max() <= 1e-6 * scale + 1e-12, name


@pytest.mark.parametrize("form", ["mmlphuman", "full"])
def test_per_batch_loss_draws_the_lpips_views_of_the_whole_iteration(twin_avatars, form):
    """The LPIPS term on 4 of an iteration's 6 views (MMLPHuman's random views; its form with random windows): the
    loss per timestep draws the views and windows once for the iteration, as the loss of all views at once does,
    not 4 of each timestep's 3 (that is, all of them), and divides by the iteration's count of the views drawn
    (those with a mask, "mmlphuman"; one drawn view's mask is empty). Found by benchmarks/parity_trajectory.py: a
    `pig fit --gpus 2` on the CPU parted from the one-process fit at its first step. Bound: float32 rounding of the
    same terms in other batch sizes, 1e-5 relative (measured: 2.2e-7 on L1, 0 on LPIPS and SSIM)."""
    from pig.avatar.losses import lpips_term
    from pig.render.api import RasterizerConfig

    model = twin_avatars[0]
    views = [[_view_batch(step, 3, 40, 36, seed)] for seed, step in enumerate((0, 2))]
    views[1][0].masks[0] = False
    batch = _batch(0, views)
    cfg = FitConfig(weight_lpips=2.0, lpips_weights="random", lpips_net="alex", lpips_form=form, lpips_crop=32,
                    lpips_views=4, lpips_patches_from=0.0, lpips_start=0.0, band_radius_px=2.0,
                    band_reference_height=36)
    background = torch.tensor([0.2, 0.3, 0.4])
    loss = LossTerms(cfg, background, lpips_term(cfg)[0], compiled=False)
    results = {}
    for batched in (True, False):
        loss.at(0, 0.5)
        terms = iteration_loss(model, batch, loss, RasterizerConfig(backend="cpu"), background, batched,
                               lambda name: nullcontext())
        results[batched] = {k: v.detach() for k, v in terms.items()}
    loss.at(0, 0.5)
    assert len(loss.draw(6)[0]) == 4  # the draw that both made
    assert sorted(results[True]) == sorted(results[False]) == ["l1", "lpips", "ssim", "total"]
    assert results[True]["lpips"] > 0
    for key, value in results[True].items():
        torch.testing.assert_close(results[False][key], value, rtol=1e-5, atol=0, msg=key)


@pytest.mark.parametrize("batched", [True, False])
def test_iteration_loss_with_the_loaders_bands_equals_the_devices(twin_avatars, batched):
    """`fit.host_band`: the views carry their band (as the loader threads compute it, with OpenCV) and the loss
    uses it instead of computing it from the masks: the same pixels, so the same terms and gradients, exactly."""
    model = twin_avatars[0]
    cfg = FitConfig(weight_lpips=0.0, band_radius_px=2.0, band_reference_height=16)
    background = torch.tensor([0.2, 0.3, 0.4])
    loss = LossTerms(cfg, background, None, compiled=False)
    from pig.render.api import RasterizerConfig

    results = []
    for host_band in (False, True):
        views = [[_view_batch(step, 2, 20, 16, seed)] for seed, step in enumerate((0, 2))]
        for step_batches in views:
            vb = step_batches[0]
            vb.masks[0, 2:5, 1:4] = True  # a second blob near the border: the band meets the image edge
            if host_band:
                vb.bands = torch.from_numpy(np.stack([boundary_band_host(m.numpy(), loss.band_radius(vb.height))
                                                      for m in vb.masks]))
        batch = _batch(1, views)
        model.zero_grad(set_to_none=True)
        terms = iteration_loss(model, batch, loss, RasterizerConfig(backend="cpu"), background, batched,
                               lambda name: nullcontext())
        terms["total"].backward()
        results.append(([terms[k].detach() for k in ("l1", "ssim", "total")],
                        [p.grad.clone() for p in model.parameters() if p.grad is not None]))
    (device_terms, device_grads), (host_terms, host_grads) = results
    assert loss.band_radius(16) == 2
    for a, b in zip(device_terms + device_grads, host_terms + host_grads):
        assert torch.equal(a, b)


def test_uniform_batch_only_when_every_timestep_has_the_same_views():
    same = _batch(0, [[_view_batch(0, 2, 8, 6, 0)], [_view_batch(1, 2, 8, 6, 1)]])
    viewmats, Ks, images, masks, width, height, bands = same.uniform()
    assert viewmats.shape == (2, 2, 4, 4) and Ks.shape == (2, 2, 3, 3) and (width, height) == (8, 6)
    assert torch.equal(images, torch.cat([same.views[0][0].images, same.views[1][0].images]))
    assert torch.equal(masks, torch.cat([same.views[0][0].masks, same.views[1][0].masks]))
    assert bands is None  # views without the loader's bands
    for step_batches in same.views:
        step_batches[0].bands = boundary_band(step_batches[0].masks, 1)
    assert torch.equal(same.uniform()[-1], torch.cat([same.views[0][0].bands, same.views[1][0].bands]))
    fewer = _batch(0, [[_view_batch(0, 2, 8, 6, 0)], [_view_batch(1, 1, 8, 6, 1)]])
    other_size = _batch(0, [[_view_batch(0, 2, 8, 6, 0)], [_view_batch(1, 2, 8, 7, 1)]])
    two_sizes = _batch(0, [[_view_batch(0, 1, 8, 6, 0), _view_batch(0, 1, 9, 6, 1)]])
    assert fewer.uniform() is None and other_size.uniform() is None and two_sizes.uniform() is None


def test_fused_adam_matches_pig_adam(twin_avatars):
    """torch's fused Adam and pig.field.optim.Adam apply the same update (bias-corrected moments, eps outside
    the root) in another order of float32 operations: each step rounds a parameter of size ~1 by ~1 ulp
    (6e-8). Bound after 5 steps: 1e-6 of the tensor's largest magnitude (measured <= 1.6e-7); groups with
    per-level grid rates, the anchors, decoders and refiner; gradients huge (1e3), tiny (1e-6) and zero."""
    models = twin_avatars
    precond = PrecondConfig()
    fused, reference = (build_optimizers(m, 1e-3, 1e-4, precond, fused=f) for m, f in zip(models, (True, False)))
    assert all(type(opt) is torch.optim.Adam and opt.defaults["fused"] for opt in fused)
    assert all(type(opt) is Adam for opt in reference)
    rates = sorted({group["lr"] for opt in reference for group in opt.param_groups})
    assert len(rates) >= 4 and [g["lr"] for o in fused for g in o.param_groups] == [g["lr"] for o in reference for g in o.param_groups]
    params = [[p for opt in opts for group in opt.param_groups for p in group["params"]] for opts in (fused, reference)]
    assert all(torch.equal(a, b) for a, b in zip(*params))
    start = [p.detach().clone() for p in params[1]]
    g = torch.Generator().manual_seed(0)
    for step in range(5):
        for i, (a, b) in enumerate(zip(*params)):
            grad = torch.randn(b.shape, generator=g) * (1e3, 1e-6, 1.0, 0.0)[i % 4]
            a.grad, b.grad = grad.clone(), grad.clone()
        for opt in fused + reference:
            opt.step()
    moved = 0
    for a, b, b0 in zip(*params, start):
        scale = max(b.detach().abs().max().item(), 1e-30)
        assert (a - b).abs().max().item() <= 1e-6 * scale, (a - b).abs().max().item() / scale
        moved += bool((b != b0).any())
    assert moved >= len(start) // 2  # the steps moved the parameters (the zero-gradient ones stay)


# ---- 8, 9, 10: the fit loop's log window, learning-rate schedule and time budget ----


def test_lr_factor_closed_form():
    """Warm-up (i + 1) / w over the first w iterations, times final ** progress with progress clamped to [0, 1]."""
    for progress, iteration, warmup, final, expected in [
        (0.0, 0, 0, 1.0, 1.0), (0.7, 50, 0, 1.0, 1.0),  # the paper's constant rates
        (0.0, 0, 4, 1.0, 0.25), (0.1, 2, 4, 1.0, 0.75), (0.2, 3, 4, 1.0, 1.0), (0.3, 40, 4, 1.0, 1.0),
        (0.5, 10, 0, 0.01, 0.1), (1.0, 10, 0, 0.01, 0.01), (2.5, 10, 0, 0.01, 0.01), (-1.0, 0, 0, 0.01, 1.0),
        (0.25, 1, 4, 0.0625, 0.5 * 0.5), (1e-3, 0, 1, 1e-9, math.exp(1e-3 * math.log(1e-9))),
    ]:
        assert math.isclose(lr_factor(progress, iteration, warmup, final), expected, rel_tol=1e-12), (progress, iteration)
    for fields, message in [({"lr_final": 0.0}, r"fit.lr_final must lie in \(0, 1\], found 0.0"),
                            ({"lr_final": 1.5}, r"fit.lr_final must lie in \(0, 1\], found 1.5"),
                            ({"lr_warmup": -1}, r"fit.lr_warmup must be at least 0, found -1"),
                            ({"log_every": 0}, r"fit.log_every must be at least 1, found 0"),
                            ({"time_budget_s": 0.0}, r"fit.time_budget_s must be positive or null, found 0.0"),
                            ({"precision": "fp16"}, r"fit.precision must be one of \('float32', 'tf32', 'bf16'\), found 'fp16'")]:
        with pytest.raises(ConfigError, match=message):
            FitConfig(**fields)


def _preset(tmp_path, name: str, **fit) -> str:
    """The test preset with a small avatar and a quiet loop (no periodic checkpoint unless asked)."""
    return str(derive_preset(tmp_path / f"{name}.yaml", "test", avatar={"num_anchors": 300},
                             fit={"eval_frames": 1, "checkpoint_minutes": 1e6, "prefetch": 1, "loader_workers": 1,
                                  **fit}))


def _log(folder) -> list[dict]:
    import pandas as pd

    return pd.read_csv(folder / "train_log.csv").to_dict("records")


@pytest.mark.slow
def test_log_every_rows_are_means_of_the_per_iteration_losses(small_capture, tmp_path):
    """Rows every 3 iterations, at the evaluations (5, 10) and at the end; each row's loss terms are the mean of
    the iterations since the row before. CPU fits are deterministic, so the per-iteration log is the reference;
    the window's float32 sum of <= 3 terms rounds by ~1e-7 relative (bound 1e-6; measured 7.7e-8)."""
    from pig.avatar.training import fit

    fit(small_capture, tmp_path / "every1", _preset(tmp_path, "every1", iterations=10, eval_every=5, log_every=1))
    fit(small_capture, tmp_path / "every3", _preset(tmp_path, "every3", iterations=10, eval_every=5, log_every=3))
    every1, every3 = _log(tmp_path / "every1"), _log(tmp_path / "every3")
    assert [r["iteration"] for r in every1] == list(range(11))
    assert [r["iteration"] for r in every3] == [0, 3, 5, 6, 9, 10]
    per_iteration = {r["iteration"]: r for r in every1}
    for before, row in zip(every3, every3[1:]):
        window = range(before["iteration"] + 1, row["iteration"] + 1)
        for key in ("loss", "l1", "ssim"):
            expected = np.mean([per_iteration[i][key] for i in window])
            assert math.isclose(row[key], expected, rel_tol=1e-6), (row["iteration"], key, row[key], expected)
        assert row["lod"] == per_iteration[row["iteration"]]["lod"]  # the LOD of the row's own iteration
        evaluated = row["iteration"] in (5, 10)
        assert math.isnan(row["heldout_psnr"]) != evaluated
        if evaluated:
            assert row["heldout_psnr"] == per_iteration[row["iteration"]]["heldout_psnr"]
    a, b = load_avatar(tmp_path / "every1" / "avatar.pt").state_dict(), load_avatar(tmp_path / "every3" / "avatar.pt").state_dict()
    assert all(torch.equal(a[key], b[key]) for key in a)  # logging less often changes nothing else


@pytest.mark.slow
def test_lr_schedule_survives_a_resume(small_capture, tmp_path):
    """A fit with warm-up and decay killed after iteration 4 and resumed ends with the uninterrupted fit's
    weights, bit for bit: the resumed fit scales the preset's base rates, not the decayed rates its
    checkpoint's optimisers hold."""
    from pig.avatar.training import fit

    iterations, warmup, final = 8, 3, 0.05
    preset = _preset(tmp_path, "schedule", iterations=iterations, eval_every=100, lr_warmup=warmup, lr_final=final,
                       checkpoint_minutes=0.0)
    reference = fit(small_capture, tmp_path / "full", preset)

    class Killed(Exception):
        pass

    def kill_at_4(iteration):
        if iteration == 4:
            raise Killed

    with pytest.raises(Killed):
        fit(small_capture, tmp_path / "resumed", preset, on_iteration=kill_at_4)
    state = torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)
    assert state["iteration"] == 4
    # The rates of the 4th iteration (index 3): the base rates times the schedule's factor.
    fit_cfg = load_section(load_preset(preset), "fit", FitConfig)
    expected = lr_factor(3 / iterations, 3, warmup, final)
    decoders = next(g for g in state["optimizers"][1]["param_groups"] if g["name"] == "decoders")
    assert math.isclose(decoders["lr"], fit_cfg.lr_decoders * expected, rel_tol=1e-12) and expected < 0.8
    resumed = fit(small_capture, tmp_path / "resumed", preset)
    a, b = load_avatar(reference).state_dict(), load_avatar(resumed).state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


@pytest.mark.slow
def test_time_budget_stops_the_fit_with_an_evaluated_last_row(small_capture, tmp_path):
    """A 0.5 s budget with iterations that each take over 0.3 s (a sleep in the callback counts as training)
    stops after 1 or 2 of 1000 iterations, between logged rows (log_every 4); the last row is that
    iteration's, with the mean loss of its window and a held-out PSNR, and avatar.pt records it."""
    from pig.avatar.training import fit

    preset = _preset(tmp_path, "budget", iterations=1000, eval_every=1000, log_every=4, time_budget_s=0.5)
    done = []

    def slow(iteration):
        done.append(iteration)
        time.sleep(0.3)

    avatar = fit(small_capture, tmp_path / "budget", preset, on_iteration=slow)
    assert 1 <= len(done) <= 2 and done == list(range(1, len(done) + 1))
    rows = _log(tmp_path / "budget")
    assert [r["iteration"] for r in rows] == [0, len(done)]
    assert math.isfinite(rows[-1]["heldout_psnr"]) and rows[-1]["heldout_psnr"] > 0
    assert math.isfinite(rows[-1]["loss"]) and rows[-1]["loss"] > 0
    assert torch.load(avatar, weights_only=True)["iteration"] == len(done)
    assert not (tmp_path / "budget" / "checkpoint.pt").exists()
