"""CPU compositor: analytic cases, a per-pixel loop reference, finite differences, batching, bands."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pig.config import load_preset, load_section
from pig.render import RasterizerConfig, RenderError, render_gaussians
from pig.render.cpu_compositor import row_spans
from pig.render.projection import project_splats

C0 = 0.28209479177387814  # SH band-0 constant
C1 = 0.4886025119029199  # SH band-1 constant


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # Tiny tensors: a second intra-op thread only adds synchronisation, badly so on shared cores.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _intrinsics(f, cx, cy, dtype=torch.float64):
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _viewmat(rotation, translation, dtype=torch.float64):
    view = torch.eye(4, dtype=dtype)
    view[:3, :3] = torch.as_tensor(rotation, dtype=dtype)
    view[:3, 3] = torch.as_tensor(translation, dtype=dtype)
    return view


def _gaussians(n, sh_bases, dtype=torch.float64, seed=0, depth=(2.0, 4.0), spread=0.5, scale=(0.02, 0.08)):
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) * 2 - 1) * spread
    z = depth[0] + (depth[1] - depth[0]) * torch.rand(n, 1, generator=g, dtype=dtype)
    means = torch.cat([xy * z, z], dim=1)  # camera space of an identity camera
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats = quats / quats.norm(dim=1, keepdim=True)
    scales = scale[0] + (scale[1] - scale[0]) * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.1 + 0.85 * torch.rand(n, generator=g, dtype=dtype)
    sh = 0.5 * torch.randn(n, sh_bases, 3, generator=g, dtype=dtype)
    return means, quats, scales, opacities, sh


def _render(gaussians, viewmats, Ks, width, height, background=(0.1, 0.2, 0.3), **kwargs):
    means, quats, scales, opacities, sh = gaussians
    return render_gaussians(
        means, quats, scales, opacities, sh, viewmats, Ks, width, height, background, backend="cpu", **kwargs
    )


def _single(position, scale, opacity, sh0, dtype=torch.float64):
    means = torch.tensor([position], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype)
    scales = torch.full((1, 3), scale, dtype=dtype)
    opacities = torch.tensor([opacity], dtype=dtype)
    sh = torch.tensor([[sh0]], dtype=dtype)
    return means, quats, scales, opacities, sh


# ---------------------------------------------------------------- slow, obviously-correct reference


def _reference(gaussians, viewmat, K, width, height, background):
    """Per-pixel loop in float64 numpy, written from the 3DGS/gsplat definitions (SH degree <= 1)."""
    means, quats, scales, opacities, sh = (t.detach().numpy() for t in gaussians)
    view, K = viewmat.numpy(), K.numpy()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    campos = -view[:3, :3].T @ view[:3, 3]
    splats = []
    for i in range(len(means)):
        p = view[:3, :3] @ means[i] + view[:3, 3]
        if p[2] < 0.01 or opacities[i] < 1 / 255:
            continue
        w, x, y, z = quats[i] / np.linalg.norm(quats[i])
        rot = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        cov_world = rot @ np.diag(scales[i] ** 2) @ rot.T
        cov_cam = view[:3, :3] @ cov_world @ view[:3, :3].T
        # gsplat evaluates the Jacobian at the centre clamped to 1.3x the field of view.
        tx = np.clip(p[0] / p[2], -cx / fx - 0.15 * width / fx, (width - cx) / fx + 0.15 * width / fx)
        ty = np.clip(p[1] / p[2], -cy / fy - 0.15 * height / fy, (height - cy) / fy + 0.15 * height / fy)
        jac = np.array([[fx / p[2], 0, -fx * tx / p[2]], [0, fy / p[2], -fy * ty / p[2]]])
        cov2d = jac @ cov_cam @ jac.T + 0.3 * np.eye(2)
        center = np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])
        d = (means[i] - campos) / np.linalg.norm(means[i] - campos)
        basis = np.array([C0, -C1 * d[1], C1 * d[2], -C1 * d[0]])[: sh.shape[1]]
        color = np.maximum(basis @ sh[i] + 0.5, 0.0)
        splats.append((p[2], i, center, np.linalg.inv(cov2d), opacities[i], color))
    splats.sort(key=lambda s: (s[0], s[1]))
    color = np.zeros((height, width, 3))
    alpha = np.zeros((height, width, 1))
    depth = np.zeros((height, width, 1))
    for row in range(height):
        for col in range(width):
            pixel = np.array([col + 0.5, row + 0.5])
            transmittance, rgb, z_sum = 1.0, np.zeros(3), 0.0
            for z, _, center, conic, opacity, c in splats:
                delta = center - pixel
                sigma = 0.5 * delta @ conic @ delta
                a = min(0.999, opacity * math.exp(-sigma))
                if sigma < 0 or a < 1 / 255:
                    continue
                if transmittance * (1 - a) <= 1e-4:
                    break
                rgb += a * transmittance * c
                z_sum += a * transmittance * z
                transmittance *= 1 - a
            color[row, col] = rgb + transmittance * np.asarray(background)
            alpha[row, col] = 1 - transmittance
            depth[row, col] = z_sum / max(1 - transmittance, 1e-10)
    return color, alpha, depth


def test_matches_per_pixel_reference():
    rng = np.random.default_rng(3)
    width, height = 24, 18
    K = _intrinsics(20.0, 11.3, 9.1)
    means, quats, scales, opacities, sh = _gaussians(40, 4, seed=1, spread=0.6, scale=(0.05, 0.3))
    # A pile of opaque splats on one pixel ray (early termination), one behind the camera, one faint.
    means[:8] = torch.tensor([0.1, -0.05, 2.0]) + torch.arange(8, dtype=torch.float64)[:, None] * torch.tensor(
        [0.0, 0.0, 0.1]
    )
    opacities[:8] = 0.97
    means[8] = torch.tensor([0.0, 0.0, -1.0])
    opacities[9] = 0.003
    rotation = _rotation(rng)
    translation = np.array([0.2, -0.1, 0.5])
    # Place the scene in front of this camera: world = R^T (p_cam - t).
    world = (means - torch.as_tensor(translation)) @ torch.as_tensor(rotation)
    gaussians = (world, quats, scales, opacities, sh)
    view = _viewmat(rotation, translation)
    background = (0.3, 0.6, 0.9)
    out = _render(gaussians, view[None], K[None], width, height, background)
    ref_color, ref_alpha, ref_depth = _reference(gaussians, view, K, width, height, background)
    assert ref_alpha.max() > 0.99  # the pile saturates a pixel, so termination is exercised
    np.testing.assert_allclose(out.color[0].numpy(), ref_color, atol=1e-10)
    np.testing.assert_allclose(out.alpha[0].numpy(), ref_alpha, atol=1e-10)
    np.testing.assert_allclose(out.depth[0].numpy(), ref_depth, atol=1e-8)


# ---------------------------------------------------------------- analytic cases


def test_single_isotropic_gaussian_peaks_with_analytic_value():
    f, z, s, opacity, sh0 = 40.0, 3.0, 0.05, 0.8, [0.4, -0.2, 1.0]
    K = _intrinsics(f, 8.5, 6.5)
    # Off-axis by x: the centre lands on pixel 12 (centre 12.5) exactly.
    x = (12.5 - 8.5) * z / f
    gaussians = _single([x, 0.0, z], s, opacity, sh0)
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = _render(gaussians, torch.eye(4, dtype=torch.float64)[None], K[None], 20, 14, background)
    color = np.maximum(C0 * np.array(sh0) + 0.5, 0.0)
    row, col = divmod(int(out.alpha[0, ..., 0].argmax()), 20)
    assert (row, col) == (6, 12)
    expected_peak = opacity * color + (1 - opacity) * background.numpy()
    np.testing.assert_allclose(out.color[0, 6, 12].numpy(), expected_peak, rtol=1e-12)
    np.testing.assert_allclose(float(out.alpha[0, 6, 12, 0]), opacity, rtol=1e-12)
    np.testing.assert_allclose(float(out.depth[0, 6, 12, 0]), z, rtol=1e-12)
    # One pixel above: EWA covariance of an isotropic Gaussian off-axis in x, plus the 0.3 blur.
    var_y = (f * s / z) ** 2 + 0.3
    expected_alpha = opacity * math.exp(-0.5 / var_y)
    np.testing.assert_allclose(float(out.alpha[0, 5, 12, 0]), expected_alpha, rtol=1e-12)


def test_occlusion_order_follows_depth_not_index():
    K = _intrinsics(30.0, 5.5, 5.5)
    view = torch.eye(4, dtype=torch.float64)[None]
    red, green = [0.5 / C0, -0.5 / C0, -0.5 / C0], [-0.5 / C0, 0.5 / C0, -0.5 / C0]  # colours (1,0,0), (0,1,0)
    near = _single([0.0, 0.0, 2.0], 0.05, 0.9, red)
    far = _single([0.0, 0.0, 3.0], 0.05, 0.9, green)
    front_first = tuple(torch.cat([a, b]) for a, b in zip(near, far))
    back_first = tuple(torch.cat([b, a]) for a, b in zip(near, far))
    background = [0.0, 0.0, 1.0]
    one = _render(front_first, view, K[None], 11, 11, background)
    two = _render(back_first, view, K[None], 11, 11, background)
    assert torch.equal(one.color, two.color)
    np.testing.assert_allclose(one.color[0, 5, 5].numpy(), [0.9, 0.1 * 0.9, 0.01], rtol=1e-12)
    np.testing.assert_allclose(float(one.depth[0, 5, 5, 0]), (0.9 * 2 + 0.09 * 3) / 0.99, rtol=1e-12)


def test_zero_opacity_renders_background_exactly():
    gaussians = list(_gaussians(30, 9, dtype=torch.float32))
    gaussians[3] = torch.zeros(30, requires_grad=True)
    K = _intrinsics(30.0, 16.0, 12.0, torch.float32)
    background = torch.tensor([0.25, 0.5, 0.75])
    out = _render(gaussians, torch.eye(4)[None], K[None], 32, 24, background)
    assert torch.equal(out.color, background.expand(1, 24, 32, 3))
    assert torch.equal(out.alpha, torch.zeros(1, 24, 32, 1))
    assert torch.equal(out.depth, torch.zeros(1, 24, 32, 1))


def test_gaussian_behind_camera_contributes_nothing():
    K = _intrinsics(30.0, 16.0, 12.0)
    view = torch.eye(4, dtype=torch.float64)[None]
    visible = _single([0.0, 0.0, 2.0], 0.1, 0.7, [1.0, 0.0, 0.5])
    behind = _single([0.0, 0.0, -1.0], 0.5, 0.99, [3.0, 3.0, 3.0])
    on_plane = _single([0.1, 0.1, 0.0], 0.5, 0.99, [3.0, 3.0, 3.0])  # z = 0: would divide by zero
    both = [torch.cat(t).requires_grad_(True) for t in zip(visible, behind, on_plane)]
    alone = _render(visible, view, K[None], 32, 24)
    out = _render(both, view, K[None], 32, 24)
    for a, b in zip(out, alone):
        assert torch.equal(a, b)
    (out.color.sum() + out.depth.sum()).backward()
    for tensor in both:
        assert torch.isfinite(tensor.grad).all()
        assert torch.equal(tensor.grad[1:], torch.zeros_like(tensor.grad[1:]))


def test_early_termination_drops_pairs_after_transmittance_floor():
    K = _intrinsics(30.0, 5.5, 5.5)
    view = torch.eye(4, dtype=torch.float64)[None]
    colors = np.eye(3)[np.arange(8) % 3] * (0.2 + 0.1 * np.arange(8))[:, None]
    pile = [_single([0.0, 0.0, 2.0 + 0.1 * k], 0.05, 0.8, list((colors[k] - 0.5) / C0)) for k in range(8)]
    gaussians = tuple(torch.cat(t) for t in zip(*pile))
    background = np.array([0.3, 0.3, 0.3])
    out = _render(gaussians, view, K[None], 11, 11, background)
    # T after k splats is 0.2^k: the 6th would take it to 6.4e-5 <= 1e-4, so only 5 composite.
    expected = sum(0.8 * 0.2**k * colors[k] for k in range(5)) + 0.2**5 * background
    np.testing.assert_allclose(out.color[0, 5, 5].numpy(), expected, rtol=1e-12)
    np.testing.assert_allclose(float(out.alpha[0, 5, 5, 0]), 1 - 0.2**5, rtol=1e-12)


def test_full_opacity_is_clamped_to_0999():
    K = _intrinsics(30.0, 5.5, 5.5)
    gaussians = _single([0.0, 0.0, 2.0], 0.05, 1.0, [0.0, 0.0, 0.0])
    out = _render(gaussians, torch.eye(4, dtype=torch.float64)[None], K[None], 11, 11, [1.0, 1.0, 1.0])
    np.testing.assert_allclose(float(out.alpha[0, 5, 5, 0]), 0.999, rtol=1e-12)
    np.testing.assert_allclose(out.color[0, 5, 5].numpy(), 0.999 * 0.5 + 0.001, rtol=1e-12)


# ---------------------------------------------------------------- gradients, batching, bands


def test_gradients_match_finite_differences():
    K = _intrinsics(14.0, 6.2, 4.7)
    rotation = _rotation(np.random.default_rng(5))
    view = _viewmat(rotation, [0.1, 0.2, 0.3])[None]
    means, quats, scales, opacities, sh = _gaussians(5, 4, seed=2, spread=0.4, scale=(0.08, 0.2))
    world = (means - torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)) @ torch.as_tensor(rotation)
    inputs = [t.clone().requires_grad_(True) for t in (world, quats, scales, opacities, sh)]
    weights = torch.rand(3, 1, 9, 12, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def loss(*tensors):
        out = _render(tensors, view, K[None], 12, 9)
        return torch.stack(
            [(weights[0] * out.color).sum(), (weights[1] * out.alpha).sum(), (weights[2, ..., :1] * out.depth).sum()]
        )

    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_batched_cameras_equal_separate_calls():
    rng = np.random.default_rng(7)
    gaussians = [t.requires_grad_(True) for t in _gaussians(400, 16, seed=4)]
    # Cameras orbiting the scene centre (0, 0, 3): p_cam = R (p - c) + c.
    centre = np.array([0.0, 0.0, 3.0])
    rotations = [np.eye(3)] + [Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix() for _ in range(2)]
    views = torch.stack([_viewmat(r, centre - r @ centre) for r in rotations])
    Ks = torch.stack([_intrinsics(40.0 + 5 * i, 20.0, 15.0) for i in range(3)])
    background = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.2, 0.4, 0.6]], dtype=torch.float64)
    batched = _render(gaussians, views, Ks, 40, 30, background)
    (batched.color.sum() + batched.depth.sum() + batched.alpha.sum()).backward()
    grads_batched = [t.grad.clone() for t in gaussians]
    for t in gaussians:
        t.grad = None
    total = 0.0
    for i in range(3):
        single = _render(gaussians, views[i : i + 1], Ks[i : i + 1], 40, 30, background[i])
        for a, b in zip(batched, single):
            torch.testing.assert_close(a[i : i + 1], b, rtol=1e-5, atol=1e-6)
        total = total + single.color.sum() + single.depth.sum() + single.alpha.sum()
    total.backward()
    assert (batched.alpha.amax(dim=(1, 2, 3)) > 0.5).all()  # every camera sees the scene
    for a, t in zip(grads_batched, gaussians):
        torch.testing.assert_close(a, t.grad, rtol=1e-8, atol=1e-8)


def test_bands_equal_one_band():
    gaussians = [t.requires_grad_(True) for t in _gaussians(300, 9, seed=6, scale=(0.02, 0.2))]
    views = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    Ks = torch.stack([_intrinsics(40.0, 24.0, 16.0), _intrinsics(30.0, 20.0, 18.0)])
    results = []
    for max_pairs in (10**9, 500):
        out = _render(gaussians, views, Ks, 48, 32, max_pairs=max_pairs)
        (out.color.square().sum() + out.depth.sum()).backward()
        results.append((out, [t.grad.clone() for t in gaussians]))
        for t in gaussians:
            t.grad = None
    (one, grads_one), (many, grads_many) = results
    for a, b in zip(one, many):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)  # float64 cumsum rounding ~1e-12
    for a, b in zip(grads_one, grads_many):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-8)


def test_float32_keeps_precision_over_many_pairs():
    # ~300k pairs: one float32 running sum of log(1 - alpha) over them is off by 1.3e-3 here (measured).
    gaussians64 = _gaussians(6000, 1, seed=8, spread=0.8, scale=(0.01, 0.04))
    gaussians32 = [t.float() for t in gaussians64]
    K = _intrinsics(120.0, 64.0, 64.0)
    out64 = _render(gaussians64, torch.eye(4, dtype=torch.float64)[None], K[None], 128, 128)
    out32 = _render(gaussians32, torch.eye(4)[None], K.float()[None], 128, 128)
    assert out64.alpha.mean() > 0.5
    torch.testing.assert_close(out32.color.double(), out64.color, rtol=0, atol=2e-5)
    torch.testing.assert_close(out32.alpha.double(), out64.alpha, rtol=0, atol=2e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_row_spans_cover_every_pixel_that_reaches_the_alpha_cutoff(dtype):
    # Elongated, rotated and large splats, some cut by the image border.
    gaussians = _gaussians(300, 1, dtype=dtype, seed=9, spread=0.7, scale=(0.005, 0.4))
    gaussians[2][:, 0] *= 0.05
    K = _intrinsics(40.0, 24.0, 16.0, dtype)
    splats = project_splats(*gaussians, torch.eye(4, dtype=dtype)[None], K[None], 48, 32, 0)
    geometry = torch.cat([splats.means2d, splats.conics, splats.opacities[:, None]], dim=1)
    spans = row_spans(geometry, splats.radii, splats.camera, 48, 32)
    covered = torch.zeros(len(geometry), 32, 48, dtype=torch.bool)
    for s, row, x0, nx in zip(*(t.tolist() for t in (spans.splat, spans.row, spans.x0, spans.nx))):
        covered[s, row, x0 : x0 + nx] = True
    g = geometry.double()
    dx = g[:, 0, None, None] - (torch.arange(48, dtype=torch.float64) + 0.5)
    dy = g[:, 1, None, None] - (torch.arange(32, dtype=torch.float64)[:, None] + 0.5)
    sigma = 0.5 * (g[:, 2, None, None] * dx * dx + g[:, 4, None, None] * dy * dy) + g[:, 3, None, None] * dx * dy
    reaches = g[:, 5, None, None] * torch.exp(-sigma) >= (1 - 1e-6) / 255
    assert reaches.sum() > 10_000
    assert not (reaches & ~covered).any()
    assert covered.sum() < 1.2 * reaches.sum()  # tight: few pairs enumerated in vain


# ---------------------------------------------------------------- inputs and configuration


def test_bad_inputs_raise_clear_errors():
    gaussians = list(_gaussians(5, 4, dtype=torch.float32))
    K = _intrinsics(30.0, 16.0, 12.0, torch.float32)[None]
    with pytest.raises(RenderError, match=r"scales: expected shape \(5, 3\)"):
        bad = gaussians.copy()
        bad[2] = bad[2][:, :2]
        _render(bad, torch.eye(4)[None], K, 32, 24)
    with pytest.raises(RenderError, match="K=5 is not"):
        bad = gaussians.copy()
        bad[4] = torch.zeros(5, 5, 3)
        _render(bad, torch.eye(4)[None], K, 32, 24)
    with pytest.raises(RenderError, match=r"Ks: expected shape \(2, 3, 3\)"):
        _render(gaussians, torch.eye(4).expand(2, 4, 4), K, 32, 24)
    with pytest.raises(RenderError, match=r"background: expected shape \(3,\) or \(1, 3\)"):
        _render(gaussians, torch.eye(4)[None], K, 32, 24, background=[0.0, 0.0])
    with pytest.raises(RenderError, match="needs CUDA tensors"):
        render_gaussians(*gaussians, torch.eye(4)[None], K, 32, 24, [0.0, 0.0, 0.0], backend="gsplat")


@pytest.mark.parametrize("preset", ["test", "cpu-demo", "paper"])
def test_presets_define_the_rasterizer_section(preset):
    config = load_section(load_preset(preset), "rasterizer", RasterizerConfig)
    assert config.backend in ("auto", "cpu", "gsplat")
    assert config.max_pairs >= 100_000
