"""The host synchronisations of one fit step, found on the CPU: phase x op x count, with the line that made each.

Runs the fit's own loop (pig.avatar.training.fit, and a data-parallel rank: pig.avatar.training.fit_rank in a
one-process gloo group, so that shard_loss, the LossShare and SolveShards run) on the `test` preset with the
`paper` preset's switches that shape a step's host work: the LPIPS term in the `mmlphuman` form (random weights,
from the first iteration, random windows), the anchors' CG solve (`precond.knn_solver: cg`, check every 8),
batched render, host band, fused Adam, `log_every` 50, `fit.shard_solves` in the data-parallel rank. One iteration
after `--warmup` is recorded with pig.host_syncs.HostSyncs: the ops that make a CUDA host wait for its device.

On the CPU nothing waits; the calls are those a GPU step makes, except the render phase's: the CPU compositor
(pig.render.cpu_compositor) stands in for gsplat, whose rasterizer sizes its tile-intersection buffers from the data
(a read of their count each render, structural). Its rows are marked "CPU renderer"; one_hot's checks, which
CUDA skips, "CPU only".

    PYTHONPATH=$PWD python benchmarks/host_syncs_cpu.py
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path

import torch
import torch.distributed as dist

from pig.config import derive_preset
from pig.host_syncs import CPU_ONLY, HostSyncs

# The `paper` preset's switches that shape a step's host work, on the `test` preset's sizes (module docstring).
PAPER_SWITCHES = {
    "fit": dict(timesteps=3, views=2, weight_lpips=2.0, lpips_weights="random", lpips_net="alex", lpips_form="mmlphuman",
                lpips_crop=32, lpips_start=0.0, lpips_patches_from=0.0, batched_render=True, host_band=True,
                fused_adam=True, log_every=50, eval_every=10**6, checkpoint_minutes=10**6, loader_workers=1, prefetch=1),
    "precond": dict(knn_solver="cg", cg_check_every=8),
}
# The CPU path's renderer (the CPU backend of pig.render.api.render_gaussians); gsplat renders on a GPU.
CPU_RENDERER = ("pig/render/cpu_compositor.py", "pig/render/projection.py")


def on_cuda(sync) -> bool:
    """Whether a CUDA step makes this sync: not the CPU renderer's, not a CPU-only check."""
    return not sync.site.startswith(CPU_RENDERER) and not sync.op.endswith(CPU_ONLY)


def write_preset(folder: Path, iterations: int, shard_solves: bool, precond: dict | None = None) -> str:
    """The `test` preset with PAPER_SWITCHES (and `precond` overrides), `iterations` long; its path."""
    return str(derive_preset(folder / f"preset_{'shard' if shard_solves else 'one'}.yaml", "test",
                             fit={**PAPER_SWITCHES["fit"], "iterations": iterations, "shard_solves": shard_solves},
                             precond={**PAPER_SWITCHES["precond"], **(precond or {})}))


class StepRecorder:
    """The fit's `phase` hook and `on_iteration` callback: records the host syncs of iteration `warmup` + 1 (1-based),
    from the end of the one before it to its own end (the loop's bookkeeping between iterations included, as
    "between")."""

    def __init__(self, warmup: int):
        self.warmup = warmup
        self.stack: list[str] = []
        self.syncs = HostSyncs(lambda: self.stack[-1] if self.stack else "between")

    @contextmanager
    def __call__(self, name: str):
        self.stack.append(name)
        try:
            yield
        finally:
            self.stack.pop()

    def on_iteration(self, iteration: int) -> None:
        if iteration == self.warmup:
            self.syncs.__enter__()
        elif iteration == self.warmup + 1:
            self.syncs.__exit__(None, None, None)


def one_process(capture: Path, work: Path, warmup: int, precond: dict | None = None) -> HostSyncs:
    """The syncs of one step of a one-process fit."""
    from pig.avatar.training import fit

    recorder = StepRecorder(warmup)
    fit(capture, work / "fit_one", write_preset(work, warmup + 2, False, precond), on_iteration=recorder.on_iteration,
        phase=recorder, progress_s=1e9, overwrite=True)
    return recorder.syncs


def data_parallel_rank(capture: Path, work: Path, warmup: int, precond: dict | None = None) -> HostSyncs:
    """The syncs of one step of rank 0 of a data-parallel fit (one process, gloo), solves sharded."""
    from pig.avatar.distributed import Parallel
    from pig.avatar.training import fit_rank

    recorder = StepRecorder(warmup)
    store = dist.TCPStore("127.0.0.1", 0, 1, is_master=True, timeout=timedelta(seconds=60))
    dist.init_process_group("gloo", store=store, rank=0, world_size=1)
    try:
        (work / "fit_rank").mkdir(exist_ok=True)
        fit_rank(capture, work / "fit_rank", write_preset(work, warmup + 2, True, precond), "pig",
                 Parallel(0, 1, torch.device("cpu"), dist.group.WORLD), recorder.on_iteration, recorder, 1e9, False)
    finally:
        dist.destroy_process_group()
    return recorder.syncs


def make_capture(root: Path) -> Path:
    """The tests' small capture (tests/conftest.py: 5 cameras x 4 frames at 48 px)."""
    from pig.data.synthetic import SyntheticConfig, generate_capture
    from pig.stages.preprocess import main as preprocess

    raw = generate_capture(root / "raw", SyntheticConfig(cameras=5, frames=4, width=48, height=48, workers=1),
                           progress=False)
    preprocess(["--input", str(raw), "--output", str(root / "capture"), "--preset", "test", "--format", "thuman4",
                "--body-model", str(raw / "body_model.npz"), "--no-progress"])
    return root / "capture"


def summary(runs: dict[str, HostSyncs]) -> str:
    """Per phase and op, the count in each run; rows of the CPU compositor marked."""
    keys: Counter = Counter()
    marked = set()
    for syncs in runs.values():
        for sync, count in syncs.counts.items():
            keys[(sync.phase, sync.op)] += count
            if sync.site.startswith(CPU_RENDERER):
                marked.add((sync.phase, sync.op))
    lines = ["| phase | op | " + " | ".join(runs) + " |", "|---|---|" + "---|" * len(runs)]
    for phase, op in sorted(keys):
        note = " (CPU renderer)" if (phase, op) in marked else ""
        lines.append(f"| {phase} | {op}{note} | "
                     + " | ".join(str(s.by_phase_op()[(phase, op)]) for s in runs.values()) + " |")
    lines.append("| all | | " + " | ".join(str(sum(s.counts.values())) for s in runs.values()) + " |")
    lines.append("| those of a CUDA step (not the CPU renderer's, not CPU only) | | " + " | ".join(
        str(sum(c for sync, c in s.counts.items() if on_cuda(sync))) for s in runs.values()) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--warmup", type=int, default=2, help="iterations before the recorded one")
    parser.add_argument("--cg-lagged", action="store_true", help="precond.cg_lagged on (the CG without blocking reads)")
    parser.add_argument("--workdir", type=Path, help="kept (default: a temporary folder)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    precond = {"cg_lagged": True} if args.cg_lagged else None
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        capture = make_capture(work / "data")
        runs = {"one process": one_process(capture, work, args.warmup, precond),
                "data-parallel rank": data_parallel_rank(capture, work, args.warmup, precond)}
    print(f"\nHost synchronisations of fit iteration {args.warmup + 1} (torch {torch.__version__}; `test` preset with the "
          f"`paper` switches, benchmarks/host_syncs_cpu.py; precond.cg_lagged {'on' if args.cg_lagged else 'off'}): ops "
          "that make a CUDA host wait for its device, per phase (`between`: the loop outside the phases)\n")
    print(summary(runs))
    for name, syncs in runs.items():
        print()
        print(syncs.table(f"{name}, by line (innermost first; < its callers):\n"))


if __name__ == "__main__":
    sys.exit(main())
