"""The data-parallel fit on 2 GPUs (NCCL; pig.avatar.distributed): one step against one GPU, and a short fit.

Run on a machine with 2 or more GPUs (skipped otherwise). NVLink multicast is turned off for these processes only
(docs/gpu.md). The step: the 2 ranks' summed gradients against one GPU's, bound 1e-3 of each tensor's largest
gradient (gsplat's backward adds with atomics in any order, so even two one-GPU steps differ by float32 rounding
of many terms; a view lost or counted twice moves them by ~1e-1); both ranks' gradients and weights after the step
bit-identical; with the solves sharded (fit.shard_solves) as without.
"""
import sys
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from torch.multiprocessing import start_processes

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from preset_files import write_test_preset  # noqa: E402
from test_fit_parallel import STEP_FIT, WORLD, _log, _one_step, _placement_hooks, _step_rank  # noqa: E402

from pig.avatar.parallel_fit import fit_parallel, gpu_local_cpus  # noqa: E402

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available() or torch.cuda.device_count() < 2, reason="needs 2 CUDA devices"),
]


@pytest.fixture(autouse=True)
def no_multicast(monkeypatch):
    for name, value in (("NCCL_NVLS_ENABLE", "0"), ("TORCH_SYMM_MEM_DISABLE_MULTICAST", "1"), ("NVSHMEM_DISABLE_NVLS", "1")):
        monkeypatch.setenv(name, value)


@pytest.mark.parametrize("shard_solves", [False, True])
def test_two_gpus_compute_the_one_gpu_step(small_capture, tmp_path, shard_solves):
    preset = write_test_preset(tmp_path, **STEP_FIT, shard_solves=shard_solves)
    store = dist.TCPStore("127.0.0.1", 0, WORLD, is_master=True, wait_for_workers=False)
    start_processes(_step_rank, args=(store.port, str(small_capture), preset, str(tmp_path), "cuda"), nprocs=WORLD,
                    start_method="spawn")
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in range(WORLD)]
    terms, grads, weights, _, solves = _one_step(small_capture, preset, None, "cuda:0")
    ran = [rank[6] for rank in ranks]  # each solve on one rank when sharded, else on both
    runs_of = {key: sum(r.get(key, 0) for r in ran) for key in solves}
    assert runs_of == {key: 1 if shard_solves else WORLD for key in solves}
    for key in terms:
        torch.testing.assert_close(ranks[0][0][key], terms[key], rtol=1e-4, atol=1e-6)
    for name, reference in grads.items():
        assert torch.equal(ranks[0][1][name], ranks[1][1][name]), name
        torch.testing.assert_close(ranks[0][1][name], reference, rtol=0, atol=1e-3 * reference.abs().max().item(), msg=name)
    for name in weights:
        assert torch.equal(ranks[0][2][name], ranks[1][2][name]), name


def test_short_fit_on_two_gpus(small_capture, tmp_path):
    preset = write_test_preset(tmp_path, iterations=6, eval_every=3, checkpoint_minutes=0.0, log_every=1)
    path = fit_parallel(small_capture, tmp_path / "out", preset, "pig", WORLD, "cuda", progress_s=1e6, timeout_s=300)
    assert path.exists() and not (tmp_path / "out" / "checkpoint.pt").exists()
    rows = _log(tmp_path / "out")
    assert [int(r["iteration"]) for r in rows] == list(range(7)) and rows[-1]["heldout_psnr"] != ""


def test_pinned_ranks_run_near_their_gpus(small_capture, tmp_path):
    """--pin-cpus on GPUs: disjoint CPU sets, each inside its GPU's NUMA node where the system tells it (and the node
    has enough CPUs for its ranks)."""
    import ast
    import functools
    import os

    preset = write_test_preset(tmp_path, iterations=2, eval_every=10**6, checkpoint_minutes=10**6)
    fit_parallel(small_capture, tmp_path / "out", preset, "pig", WORLD, "cuda", progress_s=1e6, timeout_s=300,
                 rank_hooks=functools.partial(_placement_hooks, str(tmp_path)), pin_cpus=True)
    placed = [ast.literal_eval((tmp_path / f"placement{rank}").read_text()) for rank in range(WORLD)]
    sets = [set(cpus) for cpus, _, _ in placed]
    assert not sets[0] & sets[1] and all(sets)
    for rank, cpus in enumerate(sets):
        near = gpu_local_cpus(rank)
        print(f"rank {rank}: {len(cpus)} CPUs, GPU-local {sorted(near)[:4] if near else 'unknown'}...")
        if near and len(near & set(os.sched_getaffinity(0))) >= WORLD * len(cpus):
            assert cpus <= near, (rank, sorted(cpus), sorted(near))
