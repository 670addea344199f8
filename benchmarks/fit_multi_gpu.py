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

`--parity ITERATIONS` (with `--repeats R`): R fits of that many iterations per GPU count, each ending with the
held-out novel-view PSNR, printed per run with each count's spread (the 1-GPU run-to-run spread is the yardstick).

NVLink multicast stays off in this benchmark's processes (it must on the GPU machines this project measures on):
NCCL's NVLS collectives (NCCL_NVLS_ENABLE=0), torch's symmetric-memory multicast (TORCH_SYMM_MEM_DISABLE_MULTICAST=1)
and NVSHMEM's (NVSHMEM_DISABLE_NVLS=1); set here, for this script and the processes it starts only (docs/gpu.md).

Run on a 4-GPU machine from the repository root (`.gpu` carried), one GPU count and mode per command so that each
stays within a 10-minute limit (the first also makes the capture; compilation takes minutes the first time per count):

    bash .gpu/device-setup.sh && export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text
    python3 benchmarks/fit_multi_gpu.py --gpus 1 --iterations 120 --warmup 40 --profile-phases 10
    python3 benchmarks/fit_multi_gpu.py --gpus 2 --shard-solves off --iterations 120 --warmup 40 --profile-phases 10
    python3 benchmarks/fit_multi_gpu.py --gpus 2 --shard-solves on --iterations 120 --warmup 40 --profile-phases 10
    (the same for --gpus 4)
    python3 benchmarks/fit_multi_gpu.py --collect --gpus 1 2 4 --shard-solves off on --iterations 120 --warmup 40 \\
        --profile-phases 10
    python3 benchmarks/fit_multi_gpu.py --gpus 1 --parity 3000 --repeats 1   # each GPU count twice
    python3 benchmarks/fit_multi_gpu.py --collect --gpus 1 2 --parity 3000    # the parity table

The capture is made once under --workdir and kept, with every run's records (`--collect` prints the tables of
the runs there without running any; `--new-capture` makes the capture again).
"""
from __future__ import annotations

import os

# Before torch or NCCL start (the spawned ranks inherit them): NVLink multicast off, for this benchmark only.
os.environ.update(NCCL_NVLS_ENABLE="0", TORCH_SYMM_MEM_DISABLE_MULTICAST="1", NVSHMEM_DISABLE_NVLS="1")

import argparse
import csv
import functools
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
import yaml
from torch._dynamo.utils import counters

from pig.config import load_preset

sys.path.insert(0, str(Path(__file__).parent))
from fit_gpu import PhaseTimer, main as fit_gpu_main  # noqa: E402

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
    `profile` iterations after it, and at the last iteration a JSON record of ms/it, peak memory and phases."""

    def __init__(self, out: str, warmup: int, iterations: int, profile: int, rank: int):
        self.out, self.warmup, self.iterations, self.profile, self.rank = Path(out), warmup, iterations, profile, rank
        self.marks: dict[int, float] = {}
        self.graphs = {0: counters["stats"]["unique_graphs"]}  # graphs compiled so far, at the window's ends
        self.timer = PhaseTimer() if profile else None

    def __call__(self, iteration: int) -> None:
        if iteration in (self.warmup, self.iterations):
            torch.cuda.synchronize()
            self.marks[iteration] = time.perf_counter()
            self.graphs[iteration] = counters["stats"]["unique_graphs"]
        if self.timer is not None:
            self.timer.end_iteration()
            self.timer.active = self.iterations <= iteration < self.iterations + self.profile
        if iteration == self.iterations + self.profile:
            record = {"rank": self.rank, "ms": 1000 * (self.marks[self.iterations] - self.marks[self.warmup])
                      / (self.iterations - self.warmup), "peak_gib": torch.cuda.max_memory_allocated() / 2**30,
                      "phases_ms": self.timer.medians_ms() if self.timer else {},
                      # Graphs torch.compile built in the warm-up, the timed window and the profiled iterations (want
                      # 0 after the warm-up), and its graph breaks (want 0; benchmarks/compile_breaks_cpu.py on the CPU).
                      "graphs": [self.graphs[self.warmup] - self.graphs[0],
                                 self.graphs[self.iterations] - self.graphs[self.warmup],
                                 counters["stats"]["unique_graphs"] - self.graphs[self.iterations]],
                      "graph_breaks": sum(counters["graph_break"].values())}
            (self.out / f"rank{self.rank}.json").write_text(json.dumps(record))

    def phase(self, name: str):
        return self.timer(name) if self.timer is not None else _null()


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def rank_hooks(out: str, warmup: int, iterations: int, profile: int, rank: int):
    from pig.avatar.parallel_fit import RankHooks

    probe = RankProbe(out, warmup, iterations, profile, rank)
    return RankHooks(on_iteration=probe, phase=probe.phase)


def write_preset(workdir: Path, name: str, iterations: int, eval_every: int, seed: int, shard_solves: bool) -> Path:
    """The `paper` preset cut to `iterations`, LPIPS on random weights, no checkpoint inside the run."""
    preset = load_preset("paper")
    preset.pop("_path")
    preset["fit"].update(iterations=iterations, eval_every=eval_every, checkpoint_minutes=10**6, lpips_weights="random",
                         seed=seed, shard_solves=shard_solves)
    path = workdir / f"preset_{name}.yaml"
    path.write_text(yaml.safe_dump(preset))
    return path


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
        iterations, eval_every = args.iterations + args.profile_phases, 10**9
        hooks = functools.partial(rank_hooks, str(workdir / name), args.warmup, args.iterations, args.profile_phases)
    out = workdir / name
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    preset = write_preset(workdir, name, iterations, eval_every, args.seed, sharded)
    fit_dir = out / "fit"
    t0 = time.perf_counter()
    if gpus == 1:
        probe = hooks(0) if hooks else None
        fit(capture, fit_dir, str(preset), device="cuda", on_iteration=probe.on_iteration if probe else None,
            **({"phase": probe.phase} if probe else {}))
    else:
        fit_parallel(capture, fit_dir, str(preset), "pig", gpus, "cuda", rank_hooks=hooks)
    with open(fit_dir / "train_log.csv", newline="") as file:
        last = list(csv.DictReader(file))[-1]
    record = {"gpus": gpus, "sharded": sharded, "name": name, "fit_s": time.perf_counter() - t0,
              "heldout_psnr": float(last["heldout_psnr"]), "train_s": float(last["train_s"]),
              "iterations": int(last["iteration"])}
    (out / "run.json").write_text(json.dumps(record))
    return 0


def run_name(gpus: int, mode: str) -> str:
    """A run's folder name: the GPU count, and whether the solves are sharded (one GPU has nothing to shard)."""
    return f"{gpus}gpu" + ("_sharded" if mode == "on" and gpus > 1 else "")


def runs(gpus: list[int], modes: list[str]) -> list[tuple[int, str]]:
    """(GPU count, --shard-solves mode) of each run, in order; one GPU once, whatever the modes."""
    return [(g, m) for g in gpus for m in (modes[:1] if g == 1 else modes)]


def gather(workdir: Path, gpus: int, mode: str) -> dict:
    out = workdir / f"scaling_{run_name(gpus, mode)}"
    ranks = [json.loads(p.read_text()) for p in sorted(out.glob("rank*.json"), key=lambda p: int(p.stem[4:]))]
    return {"gpus": gpus, "ms": max(r["ms"] for r in ranks), "peak_gib": [r["peak_gib"] for r in ranks],
            "phases_ms": ranks[0]["phases_ms"], "rank_phases_ms": [r["phases_ms"] for r in ranks], "sharded": False,
            "rank_graphs": [(r.get("graphs"), r.get("graph_breaks")) for r in ranks],
            **json.loads((out / "run.json").read_text())}


def label(r: dict) -> str:
    return f"{r['gpus']} GPU" + (" sharded" if r["sharded"] else "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/pig_multi_gpu_bench"))
    parser.add_argument("--gpus", type=int, nargs="+", default=[1, 2], help="GPU counts, in this order")
    parser.add_argument("--frames", type=int, default=10, help="captured frames (the capture of benchmarks/fit_gpu.py)")
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--new-capture", action="store_true",
                        help="make the capture again (by default one in --workdir is kept, as are earlier runs' records)")
    parser.add_argument("--iterations", type=int, default=120, help="iterations up to the end of the timed window")
    parser.add_argument("--warmup", type=int, default=40, help="iterations before it (compilation happens there)")
    parser.add_argument("--profile-phases", type=int, default=10, help="iterations timed per phase after the window")
    parser.add_argument("--parity", type=int, default=0, metavar="ITERATIONS", help="parity fits of this length")
    parser.add_argument("--repeats", type=int, default=2, help="parity fits per GPU count")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shard-solves", nargs="+", choices=("off", "on"), default=["off"],
                        help="fit.shard_solves of the runs above one GPU: off (every rank solves), on (each solve on "
                             "one rank), or both, each a run of its own (default: off)")
    parser.add_argument("--collect", action="store_true",
                        help="run nothing: the tables of the runs already in --workdir (one command per GPU count where "
                             "they would not fit a time limit together)")
    parser.add_argument("--run", type=int, default=None, help=argparse.SUPPRESS)  # one GPU count, in this process
    parser.add_argument("--tag", default="a", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.run is not None:
        return run_one(args)
    available = torch.cuda.device_count()
    if max(args.gpus) > available:
        print(f"fit_multi_gpu: {max(args.gpus)} GPUs asked for, {available} visible", file=sys.stderr)
        return 1
    if not args.collect and (args.new_capture or not (args.workdir / CAPTURE).exists()):
        fit_gpu_main(["--workdir", str((args.workdir / CAPTURE).parent), "--frames", str(args.frames), "--cameras",
                      str(args.cameras), "--capture-only"])
    base = [sys.executable, __file__, "--workdir", str(args.workdir), "--seed", str(args.seed)]
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
        for kind in sorted({(r["gpus"], r.get("sharded", False)) for r in records}):
            values = [r["heldout_psnr"] for r in records if (r["gpus"], r.get("sharded", False)) == kind]
            print(f"{label({'gpus': kind[0], 'sharded': kind[1]})}: mean {statistics.mean(values):.3f} dB, spread "
                  f"(max - min) {max(values) - min(values):.3f} dB over {len(values)} run(s)")
        return 0

    results = []
    for gpus, mode in runs(args.gpus, args.shard_solves):
        if not args.collect:
            subprocess.run(base + ["--run", str(gpus), "--shard-solves", mode, "--iterations", str(args.iterations),
                                   "--warmup", str(args.warmup), "--profile-phases", str(args.profile_phases)],
                           check=True)
        results.append(gather(args.workdir, gpus, mode))
        r = results[-1]
        print(f"{label(r)}: {r['ms']:.1f} ms/it, peak {max(r['peak_gib']):.2f} GiB per GPU", flush=True)
    base_ms = results[0]["ms"]
    print(f"\ndevice: {torch.cuda.get_device_name()}; `paper` preset, LPIPS on random weights; capture "
          f"{args.cameras} cameras x {args.frames} frames; {args.iterations - args.warmup} timed iterations after "
          f"{args.warmup}; NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1")
    print("\n| GPUs | solves | ms/it | speed-up | efficiency | peak GiB per GPU | 100k iterations |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        speedup = base_ms / r["ms"]
        solves = "one process" if r["gpus"] == 1 else "sharded" if r["sharded"] else "every rank"
        print(f"| {r['gpus']} | {solves} | {r['ms']:.1f} | {speedup:.2f}x | {100 * speedup / r['gpus']:.0f} % | "
              f"{' / '.join(f'{p:.2f}' for p in r['peak_gib'])} | {r['ms'] * 1e5 / 6e4:.0f} min |")
    print("\nGraphs compiled per rank in the warm-up / the timed window / the profiled iterations, and graph breaks:")
    for r in results:
        print(f"{label(r)}: " + ", ".join(f"rank {rank} {'/'.join(map(str, graphs or ['-']))}, {breaks} breaks"
                                          for rank, (graphs, breaks) in enumerate(r["rank_graphs"])))
    if args.profile_phases:
        names = sorted({k for r in results for k in r["phases_ms"]})
        print(f"\nPer-phase ms on rank 0 (median of {args.profile_phases} synchronised iterations; model.* lie inside "
              "model; `reduce` is the wait for the gradients' all-reduce after the backward)")
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
            f"{label(r)}: step >= {rep:.1f} ms (speed-up <= {base_ms / rep:.1f}x)"
            for r, rep in zip(results, replicated) if rep > 0))
        several = [r for r in results if r["gpus"] > 1]
        if several:
            print(f"\nThe phases the solves move between, per rank (median ms of the same {args.profile_phases} "
                  "iterations; solve_*: the rank's own solves, *.own, and the wait for the others' broadcasts)")
            print("| run | rank | " + " | ".join(SOLVE_PHASES) + " |")
            print("|---|---|" + "---|" * len(SOLVE_PHASES))
            for r in several:
                for rank, phases in enumerate(r["rank_phases_ms"]):
                    cells = " | ".join(f"{phases.get(n, 0.0):.2f}" for n in SOLVE_PHASES)
                    print(f"| {label(r)} | {rank} | {cells} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
