"""Host synchronisations (pig.host_syncs): the counter, a fit step's syncs against a documented list, and the KNN CG
without a blocking read (precond.cg_lagged) against a dense float64 solve."""
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from pig.config import ConfigError, load_section
from pig.field.knn_graph import knn_laplacian
from pig.field.knn_solve import CGSystem
from pig.field.precondition import PrecondConfig
from pig.host_syncs import CPU_ONLY, HostSyncs
from pig.metrics.ssim import ssim

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from host_syncs_cpu import data_parallel_rank, one_process  # noqa: E402

# The syncs a CPU fit step may make (phase, op, file and function), each with why it stays. A step that makes one
# outside this list fails here: remove it, or add it with its reason.
ALLOWED = {
    # The CPU renderer stands in for gsplat, whose rasterizer reads its tile-intersection count each render
    # (structural: it sizes the buffers from the data).
    **{("render", op, f"pig/render/{where}"): "CPU renderer" for op, where in (
        ("Tensor.cpu", "cpu_compositor.py (_bands)"), ("Tensor.tolist", "cpu_compositor.py (_bands)"),
        ("Tensor.tolist", "cpu_compositor.py (composite)"), ("blocking copy to device", "cpu_compositor.py (composite)"),
        ("nonzero", "cpu_compositor.py (forward)"), ("nonzero", "cpu_compositor.py (_runs)"),
        ("nonzero", "cpu_compositor.py (row_spans)"), ("nonzero", "projection.py (project_splats)"),
        ("repeat_interleave", "cpu_compositor.py (forward)"), ("repeat_interleave", "cpu_compositor.py (row_spans)"),
        ("unique_consecutive", "cpu_compositor.py (_bands)"))},
    ("backward", "nonzero", "pig/render/cpu_compositor.py (_runs)"): "CPU renderer",
    # The eager transport asks whether any attachment triangle is degenerate; `fit.compile_posing` (the `paper`
    # preset's) runs it sync-free (pig.avatar.model.AvatarModel.compile_posing).
    ("model", "_local_scalar_dense", "pig/body/transport.py (surface_frames)"): "eager posing",
    # one_hot's bounds checks, skipped on CUDA.
    ("model", "_local_scalar_dense" + CPU_ONLY, "pig/body/transport.py (_perpendicular)"): "CPU only",
}


def _key(sync) -> tuple[str, str, str]:
    return sync.phase, sync.op, re.sub(r":\d+ ", " ", sync.site)


def test_counter_sees_reads_of_device_data_not_of_host_data():
    x = torch.arange(6.0)
    with HostSyncs(lambda: "p") as syncs:
        x.sum().item()  # device data read back
        x[x > 2]  # a boolean mask: its size comes from the data
        x.tolist()
        torch.tensor([1.0, 2.0], device="cpu")  # host data to the device, blocking
        packet = torch.tensor([1.0, 2.0])  # host data, read on the host: waits for nothing
        packet.tolist()
        (packet * 2).sum().item()
        x.repeat_interleave(torch.tensor([1, 1, 1, 1, 1, 1]), output_size=6)  # sized by the caller
        torch.nn.functional.one_hot(x.long(), 6)  # its checks are skipped on CUDA
        host = torch.empty(3)
        host.copy_(x[:3], non_blocking=True)  # into pinned memory on a GPU: no wait
        host.copy_(x[:3])
    ops = sorted(s.op for s in syncs.counts.elements())
    assert ops == sorted(["_local_scalar_dense", "index (boolean mask)", "Tensor.tolist", "blocking copy to device",
                          "_local_scalar_dense" + CPU_ONLY, "_local_scalar_dense" + CPU_ONLY, "blocking copy to host"])
    assert all(s.phase == "p" and s.site.startswith("tests/test_host_syncs.py:") for s in syncs.counts)


def test_ssim_window_is_made_on_the_device():
    # The loss phase's SSIM made its window on the host and copied it to the device each evaluation: a blocking
    # copy, which on a GPU waits for everything queued (in a data-parallel step, the LPIPS divisor's all-reduce).
    x, y = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0)).unbind(0)
    with HostSyncs() as syncs:
        value = ssim(x[None], y[None])
    assert not syncs.counts
    offsets = np.arange(-5, 6, dtype=np.float64)
    taps = np.exp(-0.5 * (offsets / 1.5) ** 2)
    reference = torch.from_numpy(taps / taps.sum()).float()
    from pig.metrics.ssim import gaussian_window
    assert torch.equal(gaussian_window(torch.float32, "cpu"), reference)
    assert torch.isfinite(value)


@pytest.mark.parametrize("lagged", [False, True])
def test_fit_step_syncs_only_as_documented(small_capture, tmp_path, lagged):
    # One iteration after two, one process and a data-parallel rank (solves sharded), the `paper` switches that
    # shape a step (benchmarks/host_syncs_cpu.py). The checked CG's residual reads are the only addition with
    # precond.cg_lagged off; the old step also copied SSIM's window to the device blocking in the loss.
    precond = {"cg_lagged": True} if lagged else None
    runs = {"one": one_process(small_capture, tmp_path, 2, precond),
            "rank": data_parallel_rank(small_capture, tmp_path, 2, precond)}
    for name, syncs in runs.items():
        keys = {_key(s) for s in syncs.counts}
        cg = {k for k in keys if k[2] == "pig/field/knn_solve.py (solve)"}
        assert keys - cg - set(ALLOWED) == set(), (name, syncs.table())
        if lagged:
            assert not cg, name
        else:  # the forward's and the backward's solve read their residual
            assert {k[1] for k in cg} == {"_local_scalar_dense"} and len({k[0] for k in cg}) == 2, name
        assert not any(k[0] == "loss" for k in keys), name


def _dense(laplacian, lam):
    return np.eye(laplacian.shape[0]) + lam * laplacian.toarray()


@pytest.mark.parametrize("lam, tol", [(8.0, 1e-6), (1e4, 1e-6), (1e6, 1e-4), (1e-8, 1e-6)])
def test_lagged_cg_reaches_tol_within_bounded_solves_without_blocking(lam, tol):
    rng = np.random.default_rng(1)
    laplacian = knn_laplacian(rng.normal(size=(200, 3)), 8)
    a = _dense(laplacian, lam)
    system = CGSystem(laplacian, lam, tol=tol, max_iter=4000, check_every=8, lagged=True)
    start, drift = rng.normal(size=(200, 3)), rng.normal(size=(200, 3))
    rhs = [start + 0.01 * i * drift for i in range(30)]  # a slowly changing right-hand side, as in a fit
    rhs[20] = np.zeros_like(start)  # an all-zero one on the way
    system.solve(torch.from_numpy(rhs[0]), "f")  # the first: the solver's tables reach the device
    rights = [torch.from_numpy(b) for b in rhs[1:]]
    with HostSyncs() as syncs, warnings.catch_warnings():
        warnings.simplefilter("error")  # the cap is never reached
        solutions = [system.solve(b, "f") for b in rights]
    assert not syncs.counts, syncs.table()
    errors = []
    for b, x in zip(rhs[1:], solutions):
        norm = max(np.linalg.norm(b, axis=0).max(), 1e-300)
        errors.append((np.linalg.norm(x.numpy() - np.linalg.solve(a, b), axis=0).max() / norm,
                       np.linalg.norm(b - a @ x.numpy(), axis=0).max() / norm))
    first = next(i for i, (_, residual) in enumerate(errors) if residual <= tol)
    assert first <= 8  # within a bounded number of solves (the count doubles while it misses)
    late = errors[first + 2:]
    assert all(residual <= tol and error <= tol for error, residual in late), errors
    assert np.all(system.solve(torch.zeros(200, 3), "f").numpy() == 0)


def test_lagged_cg_shrinks_its_count_after_an_easy_stretch():
    rng = np.random.default_rng(2)
    laplacian = knn_laplacian(rng.normal(size=(150, 3)), 8)
    system = CGSystem(laplacian, 1e3, tol=1e-8, max_iter=4000, check_every=4, lagged=True)
    b = torch.from_numpy(rng.normal(size=(150, 2)))
    for _ in range(8):
        system.solve(b, "f")
    grown = system.last_iterations
    for _ in range(8):  # the same right-hand side: the warm start is the solution, one block suffices
        system.solve(b, "f")
    assert grown > 4 and system.last_iterations < grown


def test_cg_lagged_is_a_validated_precond_key():
    preset = {"_path": "p.yaml", "precond": {"cg_lagged": "yes"}}
    with pytest.raises(ConfigError, match="cg_lagged"):
        load_section(preset, "precond", PrecondConfig)
    assert load_section({"precond": {"cg_lagged": True}}, "precond", PrecondConfig).cg_lagged


def test_lpips_divisor_is_waited_for_after_the_distances_are_queued():
    # A data-parallel rank's LPIPS divisor is an all-reduce over the ranks (pig.avatar.distributed.SummedCount): it
    # was waited for when launched, so the loss's kernels queued after it waited for the slowest rank too; now it is
    # waited for at the division, after the distances, with the same value.
    from pig.avatar.losses import lpips_views

    order = []

    def lpips(a, b):
        order.append("distances")
        return (a - b).abs().flatten(1).mean(1)

    def count():
        order.append("count")
        return torch.tensor(4.0)

    generator = torch.Generator().manual_seed(0)
    x, y = torch.rand(2, 3, 3, 24, 24, generator=generator).unbind(0)
    masks = torch.zeros(3, 24, 24, dtype=torch.bool)
    masks[:, 4:20, 6:18] = True
    value = lpips_views(lpips, x, y, masks, torch.zeros(3), "mmlphuman", 16, count=count)
    assert order == ["distances", "count"]
    assert torch.equal(value, lpips_views(lpips, x, y, masks, torch.zeros(3), "mmlphuman", 16, count=torch.tensor(4.0)))


def test_counter_tells_a_named_host_copy_from_a_cpu_fit_moving_to_its_device():
    x = torch.arange(4.0)
    with HostSyncs() as syncs:
        x.to(torch.device("cpu"))  # a CPU fit's .to(device): on a GPU a move to the GPU, no copy to the host
        x.to("cpu", torch.float64)  # the host, named (FactorizedSystem's SuperLU round trip): a copy on a GPU
    assert [s.op for s in syncs.counts] == ["Tensor.to(cpu)"]
