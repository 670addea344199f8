"""GPU benchmark of the data-parallel fit (`pig fit --gpus N`, pig/avatar/distributed.py): the scaling table.

On one capture (benchmarks/fit_gpu.py's: a synthetic capture at the paper preset's image size), the `paper` step
with the LPIPS term on random weights (`fit.lpips_weights: random`), on each GPU count of `--gpus` in turn, in
one sitting: ms per iteration (timed after `--warmup` iterations, where compilation happens), peak GPU memory per
GPU, the projected 100k-iteration time, and with `--profile-phases N` where a step goes on rank 0 (the device
synchronised around each part: N more iterations), parted into what every rank repeats (grid, anchor solve,
refiner, optimiser step) and what the ranks share out (decoders, body, render, loss, their backward). Each GPU count
runs in a process of its own (a fresh device and fresh peak-memory counters). One GPU runs today's single-process
fit; N > 1 the data-parallel one.

`--shard-solves off on`: each GPU count above 1 runs twice, with the preconditioned solves on every rank (`off`,
`fit.shard_solves: false`) and each solved by one rank and broadcast (`on`, pig.avatar.distributed.SolveShards);
the phase table then has a row per rank for the phases the solves move between (model.grid, model.anchor_solve,
solve_forward and its rank's own solves solve_forward.own, backward, reduce, solve_backward(.own), step).

`--kernel-profile N`: after those, N more iterations per rank under torch.profiler (CPU and CUDA activities, no
synchronise inserted but at their two ends), summarised per rank (benchmarks/kernel_profile.py) into the rank's
record: wall ms/it; the GPU's busy time (the union of its kernels' intervals, overlapping streams counted once), of
which NCCL kernels, and the other kernels' (compute); NCCL time that no compute overlaps; the host's time in the
step's torch operators (main and autograd threads) less its blocking CUDA waits; kernels per iteration; and rank
0's 8 costliest kernels. The table's last line is each rank's GPU idle fraction (1 - busy / wall): high at 4 ranks,
with host time near wall, is a host-bound step; a large NCCL-alone time is an all-reduce the backward does not hide.
In those iterations (and only there) each phase of the step is a profiler annotation (`RankProbe.phase`:
"pig_phase:loss", ...; the synchronised `--profile-phases` iterations come before them, never the same), and a table
per run gives, per phase and rank, the host's window (ms/it), its blocking CUDA waits, the kernels launched inside it
(from the main or the autograd thread), their summed time, their union (GPU busy) and NCCL's part, and a verdict:
"wait" where the waits fill half the window, else "host" where GPU busy < 50 % of the window (launch-bound),
"GPU" where >= 75 %, else "mixed".
The scaling table also gives the gradients' bytes all-reduced per step and their buckets (GradientReducer), and
with the kernel profile the all-reduce's implied bus bandwidth.

`--cg-lagged`: every run with `precond.cg_lagged` on (the anchors' CG without a blocking read on its owner; issue 42),
its folder replacing the same GPU count's: run it after the baseline's command. `--compile-mode reduce-overhead`
likewise with `fit.compile_mode` (the step's compiled regions replayed as CUDA graphs), and `--pin-cpus` with each rank
pinned to its own share of the cores (`pig fit --pin-cpus`; run33: a rank's host time per kernel ~2x the one
process's, 48.5 ms for 1157 kernels against 42.3 for 1988).

`--parity ITERATIONS` (with `--repeats R`): R fits of that many iterations per GPU count, each ending with the
held-out novel-view PSNR, printed per run with each count's spread (the 1-GPU run-to-run spread is the yardstick),
and each other count's verdict against 1 GPU (`parity_verdict`: its mean inside the 1-GPU range and within two
standard errors of the 1-GPU mean; run45's two runs a count could not decide it, NOTES).

NVLink multicast stays off in this benchmark's processes (it must on the GPU machines this project measures on):
NCCL's NVLS collectives (NCCL_NVLS_ENABLE=0), torch's symmetric-memory multicast (TORCH_SYMM_MEM_DISABLE_MULTICAST=1)
and NVSHMEM's (NVSHMEM_DISABLE_NVLS=1); set here, for this script and the processes it starts only (docs/gpu.md).

Run on a 4-GPU machine from the repository root (`.gpu` carried). Each GPU count compiles for minutes (run30: the
1 and 2 GPU counts 294 s together, the 4 GPU count 246 s; making the 8-camera capture about a minute more), so one
command runs what fits a 10-minute limit, the costliest count first so that a cut-short command keeps it:

    bash .gpu/device-setup.sh && export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text
    timeout 530 python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg --gpus 4 1 --shard-solves on \
        --iterations 100 --warmup 40 --profile-phases 5 --kernel-profile 5
    python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg --gpus 2 --shard-solves on off --iterations 100 --warmup 40
    python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg --collect   # every scaling run in /tmp/mg, by GPU count
    python3 benchmarks/fit_multi_gpu.py --gpus 1 --parity 3000 --repeats 1   # each GPU count twice
    python3 benchmarks/fit_multi_gpu.py --collect --gpus 1 2 --parity 3000    # the parity table

The capture is made once under --workdir and kept, with every run's records (`--collect` prints the tables of
the runs there without running any, all of them unless --gpus or --shard-solves name some; a run folder that is
missing or that its run did not finish is named and left out; `--new-capture` makes the capture again). The
capture the tables name is the one on disk (its cameras, frames and image size), whatever --cameras says.
"""
from __future__ import annotations

import os

# Before torch or NCCL start (the spawned ranks inherit them): NVLink multicast off, for this benchmark only.
os.environ.update(NCCL_NVLS_ENABLE="0", TORCH_SYMM_MEM_DISABLE_MULTICAST="1", NVSHMEM_DISABLE_NVLS="1")

import argparse
import csv
import functools
import json
import re
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import torch
from torch._dynamo.utils import counters

from pig.config import derive_preset
from pig.data.capture import Capture

sys.path.insert(0, str(Path(__file__).parent))
from fit_gpu import PhaseTimer, main as fit_gpu_main  # noqa: E402
from kernel_profile import (ITERATION, PHASE, bus_bandwidth_gbs, phase_verdict, split_trace, summarise,  # noqa: E402
                            trace_rows)

# Parts of a step that every rank computes whole, whatever the GPU count (the rest is shared out by views).
REPLICATED = ("model.grid", "model.anchor_solve", "model.refiner", "step")
# With the solves sharded: their owners' solves and the broadcasts, which the view count does not shrink either.
SHARDED_SOLVES = ("solve_forward", "solve_backward")
# The phases the solves move between, printed per rank.
SOLVE_PHASES = ("model.grid", "model.anchor_solve", "solve_forward", "solve_forward.own", "backward", "reduce",
                "solve_backward", "solve_backward.own", "step")
CAPTURE = "data/capture"  # under --workdir: benchmarks/fit_gpu.py's capture, made once, kept for later commands


class RankProbe:
    """One rank's timing: the device synchronised where the timed window starts and ends, the phases of the
    `profile` iterations after it, the `kernels` iterations after those under torch.profiler (no synchronise
    inserted but at their ends, each phase an annotation: benchmarks/kernel_profile.py), and at the last iteration a
    JSON record of ms/it, peak memory, phases, the kernel profile's summary (by phase too) and the gradient
    all-reduce's size. `synchronize` and `peak_bytes`: the CUDA device's by default (a CPU test passes its own)."""

    def __init__(self, out: str, warmup: int, iterations: int, profile: int, rank: int, kernels: int = 0,
                 synchronize: Callable[[], None] = torch.cuda.synchronize,
                 peak_bytes: Callable[[], int] = torch.cuda.max_memory_allocated):
        self.out, self.warmup, self.iterations, self.profile, self.rank = Path(out), warmup, iterations, profile, rank
        self.kernels, self.synchronize, self.peak_bytes = kernels, synchronize, peak_bytes
        self.marks: dict[int, float] = {}
        self.graphs = {0: counters["stats"]["unique_graphs"]}  # graphs compiled so far, at the window's ends
        self.timer = PhaseTimer(synchronize) if profile else None
        self.profiler = self.annotation = None
        self.kernel_summary: dict | None = None
        self.bucket_bytes: list[int] | None = None  # the gradient all-reduce's buckets (one process: none)

    def reducer(self, reducer) -> None:
        self.bucket_bytes = reducer.bucket_bytes

    def __call__(self, iteration: int) -> None:
        if iteration in (self.warmup, self.iterations):
            self.synchronize()
            self.marks[iteration] = time.perf_counter()
            self.graphs[iteration] = counters["stats"]["unique_graphs"]
        if self.timer is not None:
            self.timer.end_iteration()
            self.timer.active = self.iterations <= iteration < self.iterations + self.profile
        first = self.iterations + self.profile
        last = first + self.kernels
        if self.kernels and first <= iteration <= last:
            self._kernel_profile(iteration, first, last)
        if iteration == last:
            record = {"rank": self.rank, "ms": 1000 * (self.marks[self.iterations] - self.marks[self.warmup])
                      / (self.iterations - self.warmup), "peak_gib": self.peak_bytes() / 2**30,
                      "phases_ms": self.timer.medians_ms() if self.timer else {},
                      # Graphs torch.compile built in the warm-up, the timed window and the profiled iterations (want
                      # 0 after the warm-up), and its graph breaks (want 0; benchmarks/compile_breaks_cpu.py on the CPU).
                      "graphs": [self.graphs[self.warmup] - self.graphs[0],
                                 self.graphs[self.iterations] - self.graphs[self.warmup],
                                 counters["stats"]["unique_graphs"] - self.graphs[self.iterations]],
                      "graph_breaks": sum(counters["graph_break"].values()),
                      "kernels": self.kernel_summary, "bucket_bytes": self.bucket_bytes}
            (self.out / f"rank{self.rank}.json").write_text(json.dumps(record))

    def _kernel_profile(self, iteration: int, first: int, last: int) -> None:
        """Iterations first+1..last under the profiler, each in an annotation (ITERATION) on this thread; the device
        synchronised before the first, so that no earlier work runs into it, and after the last, so that its work
        is all in."""
        if iteration == last:
            self.synchronize()
        if self.annotation is not None:
            self.annotation.__exit__(None, None, None)
        if iteration == first:
            self.synchronize()
            activities = {torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA}
            self.profiler = torch.profiler.profile(activities=activities & torch.profiler.supported_activities())
            self.profiler.start()
        if iteration < last:
            self.annotation = torch.profiler.record_function(ITERATION)
            self.annotation.__enter__()
        else:
            self.profiler.stop()
            try:  # a trace that cannot be read (a torch whose export differs) loses the kernel profile only
                self.kernel_summary = summarise(split_trace(trace_rows(self.profiler)))
            except Exception as err:  # noqa: BLE001 (the rank's timing and phases are still written)
                print(f"rank {self.rank}: kernel profile not read ({type(err).__name__}: {err})", file=sys.stderr)
            self.profiler = self.annotation = None

    def phase(self, name: str):
        """The timer's phase in the synchronised iterations; in the profiled ones (an ITERATION annotation open) an
        annotation PHASE + name, which synchronises nothing; elsewhere nothing."""
        if self.annotation is not None:
            return torch.profiler.record_function(PHASE + name)
        return self.timer(name) if self.timer is not None else _null()


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def rank_hooks(out: str, warmup: int, iterations: int, profile: int, kernels: int, rank: int):
    from pig.avatar.parallel_fit import RankHooks

    probe = RankProbe(out, warmup, iterations, profile, rank, kernels)
    return RankHooks(on_iteration=probe, phase=probe.phase, on_reducer=probe.reducer)


def parity_verdict(reference: list[float], values: list[float]) -> str:
    """The parity rule fixed before hold C3 (issue 42): the runs' mean inside the 1-GPU runs' range, and the
    difference of the means within two of its standard errors (Welch: each count's own sample variance)."""
    difference = statistics.mean(values) - statistics.mean(reference)
    inside = min(reference) <= statistics.mean(values) <= max(reference)
    verdict = f"difference of means {difference:+.3f} dB, mean {'inside' if inside else 'outside'} the 1-GPU range"
    if min(len(reference), len(values)) < 2:
        return verdict + "; standard error needs two runs of each: parity not decided"
    error = (statistics.variance(reference) / len(reference) + statistics.variance(values) / len(values)) ** 0.5
    within = abs(difference) <= 2 * error
    holds = inside and within
    return (verdict + f", standard error {error:.3f} dB ({abs(difference) / error if error else float('inf'):.2f} "
            f"of them): parity {'holds' if holds else 'not shown'}")


def write_preset(workdir: Path, name: str, iterations: int, eval_every: int, seed: int, shard_solves: bool,
                 cg_lagged: bool = False, compile_mode: str = "default") -> Path:
    """The `paper` preset cut to `iterations`, LPIPS on random weights, no checkpoint inside the run; `cg_lagged`:
    precond.cg_lagged on (the anchors' CG without a blocking read); `compile_mode`: fit.compile_mode."""
    return derive_preset(workdir / f"preset_{name}.yaml", "paper",
                         fit={"iterations": iterations, "eval_every": eval_every, "checkpoint_minutes": 10**6,
                              "lpips_weights": "random", "seed": seed, "shard_solves": shard_solves,
                              "compile_mode": compile_mode},
                         precond={"cg_lagged": True} if cg_lagged else {})


def run_one(args) -> int:
    """One GPU count (`--run N`), in this process: the timed fit, or the parity fit; writes its records."""
    from pig.avatar.parallel_fit import fit_parallel
    from pig.avatar.training import fit

    gpus, workdir = args.run, args.workdir
    [mode] = args.shard_solves
    sharded = mode == "on" and gpus > 1
    capture = workdir / CAPTURE
    if args.parity:
        name = f"parity_{run_name(gpus, mode)}_{args.tag}"
        iterations, eval_every, hooks = args.parity, args.parity, None
    else:
        name = f"scaling_{run_name(gpus, mode)}"
        # One iteration after those measured: the fit's closing held-out evaluation runs inside its last iteration.
        iterations, eval_every = args.iterations + args.profile_phases + args.kernel_profile + 1, 10**9
        hooks = functools.partial(rank_hooks, str(workdir / name), args.warmup, args.iterations, args.profile_phases,
                                  args.kernel_profile)
    out = workdir / name
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    preset = write_preset(workdir, name, iterations, eval_every, args.seed, sharded, args.cg_lagged, args.compile_mode)
    fit_dir = out / "fit"
    t0 = time.perf_counter()
    if gpus == 1:
        probe = hooks(0) if hooks else None
        fit(capture, fit_dir, str(preset), device="cuda", on_iteration=probe.on_iteration if probe else None,
            **({"phase": probe.phase} if probe else {}))
    else:
        fit_parallel(capture, fit_dir, str(preset), "pig", gpus, "cuda", rank_hooks=hooks, pin_cpus=args.pin_cpus)
    with open(fit_dir / "train_log.csv", newline="") as file:
        last = list(csv.DictReader(file))[-1]
    record = {"gpus": gpus, "sharded": sharded, "name": name, "fit_s": time.perf_counter() - t0,
              "heldout_psnr": float(last["heldout_psnr"]), "train_s": float(last["train_s"]),
              "iterations": int(last["iteration"]), "device": torch.cuda.get_device_name(),
              "capture": describe_capture(capture), "warmup": args.warmup, "timed": args.iterations - args.warmup,
              "profile_phases": args.profile_phases, "kernel_profile": args.kernel_profile, "cg_lagged": args.cg_lagged,
              "pin_cpus": args.pin_cpus, "compile_mode": args.compile_mode}
    (out / "run.json").write_text(json.dumps(record))
    return 0


def describe_capture(folder: Path) -> str:
    """The capture on disk: its cameras, frames and image size (whatever --cameras and --frames say now)."""
    capture = Capture.load(folder, cache_mb=0)
    sizes = sorted({(c.width, c.height) for c in capture.cameras.values()})
    return (f"{len(capture.cameras)} cameras x {len(capture.frames)} frames, "
            + ", ".join(f"{w} x {h}" for w, h in sizes))


def run_name(gpus: int, mode: str) -> str:
    """A run's folder name: the GPU count, and whether the solves are sharded (one GPU has nothing to shard)."""
    return f"{gpus}gpu" + ("_sharded" if mode == "on" and gpus > 1 else "")


def runs(gpus: list[int], modes: list[str]) -> list[tuple[int, str]]:
    """(GPU count, --shard-solves mode) of each run, in order; one GPU once, whatever the modes."""
    return [(g, m) for g in gpus for m in (modes[:1] if g == 1 else modes)]


class MissingRun(Exception):
    """A run folder that is absent or that its run did not finish writing."""


def gather(out: Path) -> dict:
    """The records of the scaling run in `out`: run.json and one rank*.json per GPU (MissingRun, naming what is
    missing, where the run did not get that far)."""
    if not out.is_dir():
        raise MissingRun(f"{out}: no such run folder")
    if not (out / "run.json").is_file():
        raise MissingRun(f"{out}: no run.json (the run did not finish)")
    run = json.loads((out / "run.json").read_text())
    ranks = []
    for rank in range(run["gpus"]):
        path = out / f"rank{rank}.json"
        if not path.is_file():
            raise MissingRun(f"{path}: missing ({run['gpus']} GPUs ran; the rank did not reach its last iteration)")
        ranks.append(json.loads(path.read_text()))
    return {"ms": max(r["ms"] for r in ranks), "peak_gib": [r["peak_gib"] for r in ranks],
            "phases_ms": ranks[0]["phases_ms"], "rank_phases_ms": [r["phases_ms"] for r in ranks],
            "rank_graphs": [(r.get("graphs"), r.get("graph_breaks")) for r in ranks],
            "rank_kernels": [r.get("kernels") for r in ranks], "bucket_bytes": ranks[0].get("bucket_bytes"), **run}


def scaling_runs(workdir: Path) -> list[tuple[int, str]]:
    """(GPU count, --shard-solves mode) of every scaling run folder in `workdir`, by GPU count, the solves on every
    rank before sharded."""
    found = []
    for path in workdir.glob("scaling_*gpu*"):
        match = re.fullmatch(r"scaling_(\d+)gpu(_sharded)?", path.name)
        if match and path.is_dir():
            found.append((int(match[1]), "on" if match[2] else "off"))
    return sorted(found)


def label(r: dict) -> str:
    return f"{r['gpus']} GPU" + (" sharded" if r["sharded"] else "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/pig_multi_gpu_bench"))
    parser.add_argument("--gpus", type=int, nargs="+", default=None,
                        help="GPU counts, in this order (default: 1 2; with --collect: every run in --workdir)")
    parser.add_argument("--frames", type=int, default=10, help="captured frames (the capture of benchmarks/fit_gpu.py)")
    parser.add_argument("--cameras", type=int, default=8, help="captured cameras, where the capture is made")
    parser.add_argument("--new-capture", action="store_true",
                        help="make the capture again (by default one in --workdir is kept, as are earlier runs' records)")
    parser.add_argument("--iterations", type=int, default=120, help="iterations up to the end of the timed window")
    parser.add_argument("--warmup", type=int, default=40, help="iterations before it (compilation happens there)")
    parser.add_argument("--profile-phases", type=int, default=10, help="iterations timed per phase after the window")
    parser.add_argument("--kernel-profile", type=int, default=0, metavar="N",
                        help="N iterations under torch.profiler after those, per rank: GPU busy and NCCL time, host "
                             "time, kernels per iteration (default 0: none)")
    parser.add_argument("--parity", type=int, default=0, metavar="ITERATIONS", help="parity fits of this length")
    parser.add_argument("--repeats", type=int, default=2, help="parity fits per GPU count")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shard-solves", nargs="+", choices=("off", "on"), default=None,
                        help="fit.shard_solves of the runs above one GPU: off (every rank solves), on (each solve on "
                             "one rank), or both, each a run of its own (default: off; with --collect: every run)")
    parser.add_argument("--collect", action="store_true",
                        help="run nothing: the tables of the runs already in --workdir (those of --gpus and "
                             "--shard-solves, else all)")
    parser.add_argument("--cg-lagged", action="store_true",
                        help="precond.cg_lagged on in every run: the anchors' CG without a blocking read (a run "
                             "replaces the folder of the same GPU count and mode: after the baseline, or another --workdir)")
    parser.add_argument("--compile-mode", choices=("default", "reduce-overhead"), default="default",
                        help="fit.compile_mode in every run (reduce-overhead: CUDA graphs; a run replaces the folder of "
                             "the same GPU count and mode: after the baseline, or another --workdir)")
    parser.add_argument("--pin-cpus", action="store_true",
                        help="each rank pinned to its own share of the cores (pig fit --pin-cpus; a run replaces the "
                             "folder of the same GPU count and mode: after the baseline, or another --workdir)")
    parser.add_argument("--run", type=int, default=None, help=argparse.SUPPRESS)  # one GPU count, in this process
    parser.add_argument("--tag", default="a", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    everything = args.collect and args.gpus is None and args.shard_solves is None
    args.gpus = args.gpus or [1, 2]
    args.shard_solves = args.shard_solves or ["off"]
    if args.run is not None:
        return run_one(args)
    available = torch.cuda.device_count()
    if not args.collect and max(args.gpus) > available:
        print(f"fit_multi_gpu: {max(args.gpus)} GPUs asked for, {available} visible", file=sys.stderr)
        return 1
    if not args.collect and (args.new_capture or not (args.workdir / CAPTURE).exists()):
        fit_gpu_main(["--workdir", str((args.workdir / CAPTURE).parent), "--frames", str(args.frames), "--cameras",
                      str(args.cameras), "--capture-only"])
    base = [sys.executable, __file__, "--workdir", str(args.workdir), "--seed", str(args.seed), "--compile-mode",
            args.compile_mode] + ["--cg-lagged"] * args.cg_lagged + ["--pin-cpus"] * args.pin_cpus
    if args.parity:
        for repeat in range(0 if args.collect else args.repeats):
            for gpus, mode in runs(args.gpus, args.shard_solves):  # alternating, so that a drift touches each alike
                tag = f"{time.strftime('%H%M%S')}_{repeat}"
                subprocess.run(base + ["--run", str(gpus), "--shard-solves", mode, "--parity", str(args.parity),
                                       "--tag", tag], check=True)
        records = [json.loads(p.read_text()) for p in sorted(args.workdir.glob("parity_*gpu_*/run.json"))]
        print(f"\nHeld-out novel-view PSNR after {args.parity} `paper` iterations (LPIPS on random weights), every "
              f"parity run in {args.workdir}")
        print("| GPUs | run | held-out PSNR dB | train s | wall s |")
        print("|---|---|---|---|---|")
        for r in sorted(records, key=lambda r: (r["gpus"], r["name"])):
            print(f"| {r['gpus']} | {r['name']} | {r['heldout_psnr']:.3f} | {r['train_s']:.0f} | {r['fit_s']:.0f} |")
        kinds = {kind: [r["heldout_psnr"] for r in records if (r["gpus"], r.get("sharded", False)) == kind]
                 for kind in sorted({(r["gpus"], r.get("sharded", False)) for r in records})}
        for kind, values in kinds.items():
            print(f"{label({'gpus': kind[0], 'sharded': kind[1]})}: mean {statistics.mean(values):.3f} dB, spread "
                  f"(max - min) {max(values) - min(values):.3f} dB over {len(values)} run(s)")
        reference = kinds.get((1, False), [])
        for kind, values in kinds.items():
            if kind != (1, False) and reference:
                print(f"{label({'gpus': kind[0], 'sharded': kind[1]})} against 1 GPU: "
                      f"{parity_verdict(reference, values)}")
        return 0

    plan = scaling_runs(args.workdir) if everything else runs(args.gpus, args.shard_solves)
    if not plan:
        print(f"fit_multi_gpu: no scaling run folder (scaling_*gpu*) in {args.workdir}", file=sys.stderr)
        return 1
    results = []
    for gpus, mode in plan:
        if not args.collect:  # a failed count is named below and the next one still runs (a GPU hold is short)
            code = subprocess.run(base + ["--run", str(gpus), "--shard-solves", mode, "--iterations",
                                          str(args.iterations), "--warmup", str(args.warmup), "--profile-phases",
                                          str(args.profile_phases), "--kernel-profile", str(args.kernel_profile)]
                                  ).returncode
            if code:
                print(f"fit_multi_gpu: the {run_name(gpus, mode)} run ended with exit code {code}", file=sys.stderr)
        try:
            results.append(gather(args.workdir / f"scaling_{run_name(gpus, mode)}"))
        except MissingRun as err:
            print(f"fit_multi_gpu: {err}; left out of the tables", file=sys.stderr)
            continue
        r = results[-1]
        print(f"{label(r)}: {r['ms']:.1f} ms/it, peak {max(r['peak_gib']):.2f} GiB per GPU", flush=True)
    if not results:
        print(f"fit_multi_gpu: no finished scaling run to show in {args.workdir}", file=sys.stderr)
        return 1
    print_tables(results, args, args.workdir / CAPTURE)
    return 0


def print_tables(results: list[dict], args, capture: Path) -> None:
    """The scaling table of `results` (gather's records), by GPU count whatever order they ran in, and those of
    their phase and kernel profiles."""
    results = sorted(results, key=lambda r: (r["gpus"], r["sharded"]))
    base = results[0]
    devices = sorted({r.get("device", "unknown (not recorded)") for r in results})
    captures = sorted({r.get("capture") or (describe_capture(capture) if capture.is_dir() else "unknown")
                       for r in results})
    windows = sorted({(r.get("timed", args.iterations - args.warmup), r.get("warmup", args.warmup)) for r in results})
    lagged = sorted({"on" if r.get("cg_lagged") else "off" for r in results})
    modes = sorted({r.get("compile_mode", "default") for r in results})
    pinned = sorted({"on" if r.get("pin_cpus") else "off" for r in results})
    print(f"\ndevice: {', '.join(devices)}; `paper` preset, LPIPS on random weights, precond.cg_lagged "
          f"{'/'.join(lagged)}, fit.compile_mode {'/'.join(modes)}, ranks pinned to CPUs {'/'.join(pinned)}; "
          f"capture {'; '.join(captures)}; "
          + ", ".join(f"{timed} timed iterations after {warmup}" for timed, warmup in windows)
          + "; NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1")
    print(f"(speed-up against the first row, {label(base)}; all-reduced: the gradients' bytes per step and buckets, "
          "pig.avatar.distributed.GradientReducer)")
    print("\n| GPUs | solves | ms/it | speed-up | efficiency | peak GiB per GPU | 100k iterations | all-reduced MiB "
          "| buckets |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        speedup = base["ms"] / r["ms"]
        solves = "one process" if r["gpus"] == 1 else "sharded" if r["sharded"] else "every rank"
        buckets = r.get("bucket_bytes")
        reduced = (f"{sum(buckets) / 2**20:.1f} | {len(buckets)}" if buckets else "- | -")
        print(f"| {r['gpus']} | {solves} | {r['ms']:.1f} | {speedup:.2f}x | "
              f"{100 * speedup * base['gpus'] / r['gpus']:.0f} % | "
              f"{' / '.join(f'{p:.2f}' for p in r['peak_gib'])} | {r['ms'] * 1e5 / 6e4:.0f} min | {reduced} |")
    print("\nGraphs compiled per rank in the warm-up / the timed window / the profiled iterations, and graph breaks:")
    for r in results:
        print(f"{label(r)}: " + ", ".join(f"rank {rank} {'/'.join(map(str, graphs or ['-']))}, {breaks} breaks"
                                          for rank, (graphs, breaks) in enumerate(r["rank_graphs"])))
    phased = [r for r in results if r["phases_ms"]]
    if phased:
        print_phases(phased, base, sorted({r.get("profile_phases", args.profile_phases) for r in phased}))
    profiled = [r for r in results if any(r["rank_kernels"])]
    if profiled:
        print_kernels(profiled)
        for r in profiled:
            if any(k and k.get("phases") for k in r["rank_kernels"]):
                print_kernel_phases(r)


def print_phases(results: list[dict], base: dict, counts: list[int]) -> None:
    names = sorted({k for r in results for k in r["phases_ms"]})
    print(f"\nPer-phase ms on rank 0 (median of {'/'.join(map(str, counts))} synchronised iterations; model.* lie "
          "inside model; `reduce` is the wait for the gradients' all-reduce after the backward)")
    print("| phase | " + " | ".join(label(r) for r in results) + " |")
    print("|---|" + "---|" * len(results))
    for n in names:
        print(f"| {n} | " + " | ".join(f"{r['phases_ms'].get(n, 0.0):.1f}" for r in results) + " |")
    top = [n for n in names if "." not in n]  # model.* and solve_*.own lie inside other phases
    sums = [sum(r["phases_ms"].get(n, 0.0) for n in top) for r in results]
    replicated = [sum(r["phases_ms"].get(n, 0.0) for n in REPLICATED + SHARDED_SOLVES) for r in results]
    print("| sum of phases | " + " | ".join(f"{s:.1f}" for s in sums) + " |")
    print("| not split by views (" + ", ".join(REPLICATED + SHARDED_SOLVES) + ") | "
          + " | ".join(f"{s:.1f}" for s in replicated) + " |")
    # Amdahl: these do not shrink with the views per rank. Without sharding the backward's solves lie inside
    # `backward` (not counted here); with it, in solve_backward (counted).
    print("\nCap from the parts not split by views alone: " + ", ".join(
        f"{label(r)}: step >= {rep:.1f} ms (speed-up <= {base['ms'] / rep:.1f}x)"
        for r, rep in zip(results, replicated) if rep > 0))
    several = [r for r in results if r["gpus"] > 1]
    if several:
        print("\nThe phases the solves move between, per rank (median ms of the same iterations; solve_*: the "
              "rank's own solves, *.own, and the wait for the others' broadcasts)")
        print("| run | rank | " + " | ".join(SOLVE_PHASES) + " |")
        print("|---|---|" + "---|" * len(SOLVE_PHASES))
        for r in several:
            for rank, phases in enumerate(r["rank_phases_ms"]):
                cells = " | ".join(f"{phases.get(n, 0.0):.2f}" for n in SOLVE_PHASES)
                print(f"| {label(r)} | {rank} | {cells} |")


def print_kernels(results: list[dict]) -> None:
    """The kernel profiles' table per run and rank, rank 0's costliest kernels, and what they say of the cause."""
    print("\nKernel profile per rank (torch.profiler, CPU + CUDA, no synchronise inside; means over "
          f"{'/'.join(sorted({str(r['rank_kernels'][0]['iterations']) for r in results if r['rank_kernels'][0]}))} "
          "iterations; the profiler's own "
          "host overhead is in wall and host). GPU busy: the union of the device's kernels (overlapping streams "
          "counted once); NCCL alone: busy time when only NCCL kernels run (communication nothing overlaps); host: "
          "the step's threads (main, autograd) in torch operators, less their blocking CUDA waits (host wait)")
    print("| run | rank | wall ms/it | GPU busy ms/it | NCCL ms/it | compute ms/it | NCCL alone ms/it | host ms/it | "
          "host wait ms/it | kernels/it | GPU idle | all-reduce bus GB/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        for rank, k in enumerate(r["rank_kernels"]):
            if not k:
                print(f"| {label(r)} | {rank} | - | - | - | - | - | - | - | - | - | - |")
                continue
            buckets = r.get("bucket_bytes")
            bandwidth = (f"{bus_bandwidth_gbs(sum(buckets), k['all_reduce_ms'], r['gpus']):.0f}"
                         if buckets and k["all_reduce_ms"] > 0 else "-")
            print(f"| {label(r)} | {rank} | {k['wall_ms']:.1f} | {k['gpu_busy_ms']:.1f} | {k['nccl_ms']:.2f} | "
                  f"{k['compute_ms']:.1f} | {k['nccl_alone_ms']:.2f} | {k['host_ms']:.1f} | {k['host_wait_ms']:.1f} "
                  f"| {k['kernels']:.0f} | {100 * k['gpu_idle']:.0f} % | {bandwidth} |")
    print("(all-reduce bus GB/s: the gradients' bytes over the NCCL all-reduce kernels' time, x 2 (N - 1) / N; a "
          "kernel's time includes its wait for the slowest rank, so this is a lower bound on the link's rate)")
    for r in results:
        k = r["rank_kernels"][0]
        if k:
            print(f"\nTop {len(k['top_kernels'])} kernels on rank 0 of {label(r)} by total time")
            print("| kernel | ms/it | launches/it |")
            print("|---|---|---|")
            for name, ms, launches in k["top_kernels"]:
                print(f"| {name[:90]} | {ms:.2f} | {launches:.1f} |")
    print("\nGPU idle per rank (1 - busy / wall): " + "; ".join(
        f"{label(r)}: " + " / ".join(f"{100 * k['gpu_idle']:.0f} %" if k else "-" for k in r["rank_kernels"])
        for r in results))
    print("Reading: GPUs idle for much of the step as the ranks grow, with host ms/it near wall, is a host-bound step "
          "(launches, Python, autograd, threads competing for the cores); a large NCCL-alone time is communication "
          "that the backward does not hide; neither, with compute ms/it not shrinking with the views a rank takes, "
          "is work that each rank repeats or that does not scale with its views.")


def print_kernel_phases(r: dict) -> None:
    """A run's kernel profile by phase (kernel_profile.summarise_phases), a row per phase and rank."""
    print(f"\nKernel profile by phase, {label(r)} (ms per profiled iteration; the host's window of the phase on the "
          "main thread, its blocking CUDA waits; the kernels launched inside it from the main or the autograd thread, "
          "their summed time, their union (GPU busy, wherever it lies) and NCCL's part of it; a nested phase, "
          "*.own, counts in its own row and in its parent's. Verdict: wait where waits >= 50 % of the window, else "
          "host where busy < 50 % of it (the device waits for launches), GPU where >= 75 %, else mixed)")
    print("| phase | rank | host ms | host wait ms | launches | kernel ms | GPU busy ms | NCCL ms | busy / host | "
          "verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    names = list(dict.fromkeys(n for k in r["rank_kernels"] if k for n in k.get("phases", {})))  # in step order
    for name in names:
        for rank, k in enumerate(r["rank_kernels"]):
            p = (k or {}).get("phases", {}).get(name)
            if p is None:
                print(f"| {name} | {rank} | - | - | - | - | - | - | - | - |")
                continue
            share = f"{100 * p['gpu_busy_ms'] / p['host_ms']:.0f} %" if p["host_ms"] > 0 else "-"
            print(f"| {name} | {rank} | {p['host_ms']:.2f} | {p['host_wait_ms']:.2f} | {p['launches']:.0f} | "
                  f"{p['kernel_ms']:.2f} | {p['gpu_busy_ms']:.2f} | {p['nccl_ms']:.2f} | {share} | "
                  f"{phase_verdict(p)} |")


if __name__ == "__main__":
    raise SystemExit(main())
