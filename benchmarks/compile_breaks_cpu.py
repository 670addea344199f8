"""Graph breaks and recompilations of the compiled fit on the CPU: one process against a data-parallel fit (gloo),
each with the step timer of the GPU benchmarks (fit_gpu.PhaseTimer, as `fit_multi_gpu.py --profile-phases` runs it:
on from iteration `--profile-from`) or without it.

Every switch of the `paper` preset that compiles is on (fit.compile: decoders and L1 + SSIM; fit.compile_posing;
fit.lpips_compile with the `mmlphuman` LPIPS term on random weights; precond.cg_compile with the CG anchor solve), on
the test preset's avatar and a small synthetic capture (5 cameras x 4 frames at 48 px, made once under --workdir),
3 timesteps x 2 views a step. Each run is a fresh process per rank (Dynamo's counters are per process). Per run and
rank it prints: graph breaks (torch._dynamo.utils.counters["graph_break"]) and what broke, graphs compiled
(counters["stats"]["unique_graphs"]), recompilations (records of the `recompiles` log) and which guard failed, and the
phases the timer measured.

    PYTHONPATH=$PWD python benchmarks/compile_breaks_cpu.py --processes 1 2 --timer off on

`--backend eager` runs Dynamo's tracing alone (no inductor, no C++ compiler): the breaks and the guards are Dynamo's,
the same under any backend, in seconds instead of minutes.
"""
from __future__ import annotations

import argparse
import functools
import json
import logging
import shutil
import sys
from pathlib import Path

import torch
from torch.multiprocessing import start_processes

sys.path.insert(0, str(Path(__file__).parent))
from fit_gpu import PhaseTimer  # noqa: E402
from precond_adam_power import small_capture  # noqa: E402

# The compiling switches of the `paper` preset, on the test preset (LPIPS on random weights: nothing downloaded).
COMPILED_FIT = dict(timesteps=3, views=2, eval_every=10**6, checkpoint_minutes=10**6, log_every=1, precision="bf16",
                    compile=True, compile_posing=True, batched_render=True, host_band=True, weight_lpips=2.0,
                    lpips_weights="random", lpips_net="alex", lpips_form="mmlphuman", lpips_crop=32, lpips_start=0.0,
                    lpips_patches_from=0.0, lpips_bf16_head=True, lpips_compile=True)
COMPILED_PRECOND = dict(knn_solver="cg", cg_compile=True, cg_check_every=8)
RECOMPILES_LOG = "torch._dynamo.guards.__recompiles"


def make_capture(root: Path) -> Path:
    """The tests' small capture (precond_adam_power.small_capture), made once under `root`."""
    out = root / "capture"
    if not (out / "split.json").exists():
        shutil.rmtree(root / "raw", ignore_errors=True)
        shutil.rmtree(out, ignore_errors=True)
        small_capture(root)
    return out


def write_preset(folder: Path, iterations: int, shard_solves: bool) -> str:
    from pig.config import derive_preset

    return str(derive_preset(folder / "preset.yaml", "test",
                             fit={**COMPILED_FIT, "iterations": iterations, "shard_solves": shard_solves},
                             precond=COMPILED_PRECOND))


class _Recompiles(logging.Handler):
    """Keeps the `recompiles` log's records: the function recompiled and the first guard that failed."""

    def __init__(self):
        super().__init__()
        self.records: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        lines = [line.strip() for line in record.getMessage().splitlines() if line.strip()]
        failed = next((line for line in lines if line.startswith("- ")), "")
        self.records.append(f"{lines[0] if lines else ''} {failed}".strip())


class RankCount:
    """A rank's `on_iteration`: turns the timer on from iteration `profile_from` (None: never) and after the last
    iteration writes the rank's counts to `out`/rank{r}.json."""

    def __init__(self, out: str, rank: int, iterations: int, profile_from: int | None, timer: PhaseTimer | None):
        self.path = Path(out) / f"rank{rank}.json"
        self.rank, self.iterations, self.profile_from, self.timer = rank, iterations, profile_from, timer
        self.recompiles = _Recompiles()
        torch._logging.set_logs(recompiles=True)
        log = logging.getLogger(RECOMPILES_LOG)
        log.propagate = False  # counted here, not printed
        log.addHandler(self.recompiles)

    def __call__(self, iteration: int) -> None:
        if self.timer is not None:
            self.timer.end_iteration()
            self.timer.active = iteration >= self.profile_from
        if iteration == self.iterations:
            from torch._dynamo.utils import counters

            breaks = {" ".join(reason.split("\n")[:3]): count for reason, count in counters["graph_break"].items()}
            timed = self.timer.medians_ms() if self.timer is not None else {}
            record = {"rank": self.rank, "graph_breaks": sum(breaks.values()), "break_reasons": breaks,
                      "graphs": counters["stats"]["unique_graphs"], "recompiles": len(self.recompiles.records),
                      "recompiled": self.recompiles.records,
                      "phases": sorted(k for k, ms in timed.items() if k.startswith("model.") and ms > 0)}
            self.path.write_text(json.dumps(record))


def use_backend(backend: str) -> None:
    """torch.compile with `backend` in this process from now on (the fit's own calls name none)."""
    if backend != "inductor":
        torch.compile = functools.partial(torch.compile, backend=backend)


def rank_hooks(out: str, backend: str, iterations: int, profile_from: int | None, rank: int):
    """A rank's hooks (pig.avatar.parallel_fit.RankHooks), made in the rank's process before its model."""
    from pig.avatar.parallel_fit import RankHooks

    use_backend(backend)
    timer = PhaseTimer(synchronize=lambda: None) if profile_from is not None else None
    return RankHooks(on_iteration=RankCount(out, rank, iterations, profile_from, timer), phase=timer)


def _one_process(index: int, capture: str, out: str, preset: str, backend: str, iterations: int,
                 profile_from: int | None) -> None:
    from pig.avatar.training import fit

    hooks = rank_hooks(out, backend, iterations, profile_from, 0)
    fit(Path(capture), Path(out) / "fit", preset, on_iteration=hooks.on_iteration, progress_s=1e6,
        **({"phase": hooks.phase} if hooks.phase is not None else {}))


def run(workdir: Path, capture: Path, processes: int, iterations: int, profile_from: int | None, backend: str,
        shard_solves: bool = False) -> list[dict]:
    """One fit of `iterations` iterations on `processes` processes (1: the one-process fit, in a process of its own);
    each rank's counts."""
    out = workdir / f"p{processes}_{'timer' if profile_from is not None else 'plain'}_{backend}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    preset = write_preset(out, iterations, shard_solves)
    if processes == 1:
        start_processes(_one_process, args=(str(capture), str(out), preset, backend, iterations, profile_from),
                        nprocs=1, start_method="spawn")
    else:
        from pig.avatar.parallel_fit import fit_parallel

        fit_parallel(capture, out / "fit", preset, "pig", processes, "cpu", progress_s=1e6, timeout_s=1800,
                     rank_hooks=functools.partial(rank_hooks, str(out), backend, iterations, profile_from))
    return [json.loads((out / f"rank{rank}.json").read_text()) for rank in range(processes)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/pig_compile_breaks"))
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--timer", nargs="+", choices=("off", "on"), default=["off", "on"],
                        help="the step timer of the GPU benchmarks off, or on from --profile-from")
    parser.add_argument("--iterations", type=int, default=6)
    parser.add_argument("--profile-from", type=int, default=3, help="the iteration after which the timer turns on")
    parser.add_argument("--backend", default="inductor", help="torch.compile's backend (eager: Dynamo alone)")
    parser.add_argument("--shard-solves", action="store_true", help="fit.shard_solves in the data-parallel fits")
    args = parser.parse_args(argv)
    if args.backend == "inductor" and shutil.which("g++") is None and shutil.which("c++") is None:
        parser.error("the inductor backend on the CPU needs a C++ compiler; none found (try --backend eager)")
    args.workdir.mkdir(parents=True, exist_ok=True)
    capture = make_capture(args.workdir)
    rows = []
    for timer in args.timer:
        for processes in args.processes:
            profile_from = args.profile_from if timer == "on" else None
            for r in run(args.workdir, capture, processes, args.iterations, profile_from, args.backend,
                         args.shard_solves):
                rows.append((processes, timer, r))
    print(f"backend {args.backend}, {args.iterations} iterations"
          + (f", timer on after iteration {args.profile_from}" if "on" in args.timer else "")
          + (", solves sharded" if args.shard_solves else ""))
    print("| processes | timer | rank | graph breaks | graphs compiled | recompilations | model parts timed |")
    print("|---|---|---|---|---|---|---|")
    for processes, timer, r in rows:
        print(f"| {processes} | {timer} | {r['rank']} | {r['graph_breaks']} | {r['graphs']} | {r['recompiles']} | "
              f"{', '.join(r['phases']) or '-'} |")
    for processes, timer, r in rows:
        for reason, count in r["break_reasons"].items():
            print(f"{processes} process(es), timer {timer}, rank {r['rank']}: {count} x break: {reason}")
        for line in r["recompiled"]:
            print(f"{processes} process(es), timer {timer}, rank {r['rank']}: recompiled: {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
