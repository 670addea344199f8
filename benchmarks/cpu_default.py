"""The CPU default's fit (cpu-demo preset) under candidate overrides: quality over seeds, or the cost of a step.

Quality (default): per candidate and seed, the fit stage on a preprocessed capture, then the render stage on both
held-out splits and the evaluate stage at the finest LOD, as the default target runs them; prints one row per fit
(fit wall time, novel-view and novel-pose PSNR, and the fit's last held-out PSNR: of its weight average and of its
last iterate where it keeps one, `fit.average_decay`) and the mean per candidate. The CPU fit is deterministic for a given
thread count, so the PSNRs repeat exactly; the seed (`fit.seed`: initialisation and batch order) is what spreads
them, so compare candidates over several seeds. `--jobs 2` runs two fits side by side (one thread each): their
PSNRs stay exact, their times do not. A second table gives each fit's probe PSNR by iteration (`fit.probe_every`). `--processes N` fits each candidate as N gloo processes of `--threads` threads
(pig.avatar.parallel_fit, the data-parallel fit of `pig fit --gpus N`, on the CPU): each process takes its share of
the batch's views, so `fit.views` must be at least N.

A candidate is `NAME:section.key=value,...` (fit_gpu.parse_variant); the longest part of NAME up to a `_` that names
one of the preset's method variants picks that variant (`no_precond_eps:precond.adam_eps=1.0e-15` fits
`no_precond`, `pig_uniform:...` and `default:` fit `pig`), in both modes.

Step cost (`--steps N`): per candidate, N iterations of the fit with `--threads` torch threads, seconds per
iteration over iterations 10..N, the candidates taken in turn `--repeats` times in one process; `--profile-ops K`
also prints the K operators that took the most CPU time over those iterations. `--against DIR` times the
first candidate under this checkout's code and under DIR's (another checkout, e.g. `git worktree add DIR b8824cc`),
each round in fresh processes, alternating which goes first, and prints the ratio (a shared machine's load
drifts, so interleaved rounds are the fair comparison).

    python benchmarks/cpu_default.py --capture results/synthetic/subject00/capture --seeds 0 1 --jobs 2 \\
        --candidate default: --candidate d8:field.features=8,fit.iterations=1800
    python benchmarks/cpu_default.py --capture results/synthetic/subject00/capture --seeds 0 \\
        --candidate pig: --candidate pig_uniform:precond.form=filter,precond.optimizer=uniform_adam
    python benchmarks/cpu_default.py --capture results/synthetic/subject00/capture --steps 40 --threads 1 \\
        --candidate default: --candidate d8:field.features=8
    python benchmarks/cpu_default.py --capture results/synthetic/subject00/capture --steps 30 --threads 2 \\
        --repeats 4 --against ../pig-b8824cc
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import yaml

from fit_gpu import parse_variant, variant_preset
from pig.config import load_preset


def write_preset(base: str, overrides: dict, path: Path, variant: str, **fit) -> Path:
    """Preset `base` with a candidate's `overrides`, winning over `variant`'s own keys too (fit_gpu.variant_preset)."""
    preset = load_preset(base)
    preset.pop("_path")
    preset = variant_preset(preset, variant, overrides)
    preset["fit"].update(fit)
    path.write_text(yaml.safe_dump(preset))
    return path


def method_variant(name: str, variants: dict) -> str:
    """The preset variant a candidate NAME fits: its longest prefix ending at a `_` (or NAME itself) that is one of
    `variants`, else `pig`."""
    parts = name.split("_")
    prefixes = ("_".join(parts[:n]) for n in range(len(parts), 0, -1))
    return next((prefix for prefix in prefixes if prefix in variants), "pig")


def quality(capture: Path, name: str, overrides: dict, seed: int, workdir: Path, base: str, threads: int,
            processes: int = 1) -> dict:
    """Fit, render both splits, evaluate the finest LOD; the stages as subprocesses, as the workflow runs them."""
    variant = method_variant(name, load_preset(base)["variants"])
    root = workdir / f"{name}_seed{seed}"
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    preset = write_preset(base, overrides, root / "preset.yaml", variant, seed=seed,
                          **({"cpu_threads": threads} if processes > 1 else {}))

    def stage(*args: str) -> None:
        with open(root / "log.txt", "a") as log:
            subprocess.run([sys.executable, "-m", *args, "--preset", str(preset)], check=True, stdout=log, stderr=log)

    started = time.perf_counter()
    if processes > 1:  # the fit stage starts several processes on CUDA only: the library call, in its own process
        with open(root / "log.txt", "a") as log:
            subprocess.run([sys.executable, "-c", "import sys; from pig.avatar.parallel_fit import fit_parallel; "
                            "fit_parallel(sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[5], int(sys.argv[4]), 'cpu', "
                            "progress_s=60.0)", str(capture), str(root / "fit"), str(preset), str(processes), variant],
                           check=True, stdout=log, stderr=log)
    else:
        stage("pig.stages.fit", "--capture", str(capture), "--output", str(root / "fit"), "--threads", str(threads),
              "--variant", variant)
    row = {"name": name, "seed": seed, "variant": variant, "fit_s": time.perf_counter() - started}
    for split in ("novel_view", "novel_pose"):
        renders = root / "renders" / split
        stage("pig.stages.render", "--checkpoint", str(root / "fit" / "avatar.pt"), "--capture", str(capture),
              "--split", split, "--output", str(renders))
        levels = sorted(int(p.name[3:]) for p in renders.glob("lod*"))
        stage("pig.stages.evaluate", "--capture", str(capture), "--renders", str(renders), "--split", split,
              "--lod", str(levels[-1]), "--output", str(root / "metrics"))
        row[split] = json.loads((root / "metrics" / f"{split}_lod{levels[-1]}.json").read_text())["psnr"]
    with open(root / "fit" / "train_log.csv", newline="") as file:
        log = list(csv.DictReader(file))
    last = log[-1]
    row["probes"] = " ".join(f"{r['iteration']}: {float(r['probe_psnr']):.2f}" for r in log if r.get("probe_psnr"))
    # The fit's own last held-out evaluation; with a weight average also its iterate's (the same trajectory).
    row["heldout"] = float(last["heldout_psnr"])
    row["heldout_iterate"] = float(last["heldout_psnr_iterate"] or last["heldout_psnr"])
    print(f"| {name} | {seed} | {row['fit_s']:.0f} | {row['novel_view']:.2f} | {row['novel_pose']:.2f} "
          f"| {row['heldout']:.2f} | {row['heldout_iterate']:.2f} |", flush=True)
    return row


def step_cost(capture: Path, candidates: list[tuple[str, dict]], steps: int, threads: int, repeats: int,
              workdir: Path, base: str, profile_ops: int = 0) -> None:
    import torch

    from pig.avatar.training import fit

    variants = load_preset(base)["variants"]
    times: dict[str, list[float]] = {name: [] for name, _ in candidates}
    for _ in range(repeats):
        for name, overrides in candidates:
            preset = write_preset(base, overrides, workdir / f"{name}.yaml", method_variant(name, variants),
                                  iterations=steps, eval_every=10**6, checkpoint_minutes=10**6)
            marks = {}
            out = workdir / f"{name}_steps"
            shutil.rmtree(out, ignore_errors=True)
            ops = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) if profile_ops else None

            def tick(i: int) -> None:
                if i in (10, steps):
                    marks[i] = time.perf_counter()
                    if ops is not None:  # the timed steps under the profiler (which slows them a little)
                        ops.start() if i == 10 else ops.stop()

            fit(capture, out, str(preset), variant=method_variant(name, variants), threads=threads, on_iteration=tick)
            times[name].append((marks[steps] - marks[10]) / (steps - 10))
            if ops is not None:
                print(f"\nOperators by CPU time, {name}, steps 10..{steps}:\n"
                      + ops.key_averages().table(sort_by="self_cpu_time_total", row_limit=profile_ops))
    first = statistics.median(times[candidates[0][0]])
    print(f"\n| candidate | s/it ({threads} threads, median of {repeats}) | vs first |\n|---|---|---|")
    for name, values in times.items():
        print(f"| {name} | {statistics.median(values):.3f} | {statistics.median(values) / first:.2f} |")


def step_cost_against(capture: Path, candidate: str, steps: int, threads: int, repeats: int, other: Path,
                      workdir: Path, base: str) -> None:
    """s/it of `candidate` under this checkout and under `other`, one fresh process per round and checkout."""
    trees = {"this": Path(__file__).resolve().parents[1], "against": other.resolve()}
    times: dict[str, list[float]] = {name: [] for name in trees}
    for round_ in range(repeats):
        for name in (list(trees) if round_ % 2 == 0 else list(trees)[::-1]):
            tree = trees[name]
            out = subprocess.run(
                [sys.executable, str(tree / "benchmarks" / "cpu_default.py"), "--capture", str(capture.resolve()),
                 "--steps", str(steps), "--threads", str(threads), "--repeats", "1", "--candidate", candidate,
                 "--preset", base, "--workdir", str(workdir / f"{name}{round_}")],
                cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, check=True, capture_output=True, text=True)
            value = float(re.findall(r"^\| [^|]+ \| ([0-9.]+) \|", out.stdout, re.M)[-1])
            times[name].append(value)
            print(f"round {round_} {name} ({tree}): {value:.3f} s/it", flush=True)
    this, against = statistics.median(times["this"]), statistics.median(times["against"])
    ratios = [a / b for a, b in zip(times["this"], times["against"])]
    print(f"\n| code | s/it ({threads} threads, median of {repeats}) | per round |\n|---|---|---|")
    for name, values in times.items():
        print(f"| {name} ({trees[name]}) | {statistics.median(values):.3f} | {' '.join(f'{v:.3f}' for v in values)} |")
    print(f"\nthis / against: {this / against:.3f} (medians); per round {' '.join(f'{r:.3f}' for r in ratios)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture (the default run's)")
    parser.add_argument("--candidate", action="append", default=[], help="NAME:section.key=value,... (repeatable)")
    parser.add_argument("--preset", default="cpu-demo", help="the preset the candidates override")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--jobs", type=int, default=1, help="fits side by side (quality mode)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of each fit (of each process)")
    parser.add_argument("--processes", type=int, default=1, help="quality mode: gloo processes of each fit")
    parser.add_argument("--steps", type=int, default=0, help="step-cost mode: iterations per candidate (> 10)")
    parser.add_argument("--repeats", type=int, default=2, help="step-cost mode: rounds over the candidates")
    parser.add_argument("--profile-ops", type=int, default=0,
                        help="step-cost mode: print the N operators of most CPU time over the timed steps")
    parser.add_argument("--against", type=Path, default=None,
                        help="step-cost mode: another checkout whose code to time the first candidate under, in turn")
    parser.add_argument("--workdir", type=Path, default=None, help="default: a temporary folder")
    args = parser.parse_args(argv)
    candidates = [parse_variant(c) for c in args.candidate] or [("default", {})]
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="pig_cpu_default_"))
    workdir.mkdir(parents=True, exist_ok=True)
    if args.steps:
        if args.steps <= 10:
            parser.error("--steps must exceed 10 (the first 10 iterations are not timed)")
        if args.against is not None:
            if not (args.against / "benchmarks" / "cpu_default.py").is_file():
                parser.error(f"--against {args.against}: no benchmarks/cpu_default.py there (expected a pig checkout)")
            step_cost_against(args.capture, args.candidate[0] if args.candidate else "default:", args.steps,
                              args.threads, args.repeats, args.against, workdir, args.preset)
            return 0
        step_cost(args.capture, candidates, args.steps, args.threads, args.repeats, workdir, args.preset, args.profile_ops)
        return 0
    print("| candidate | seed | fit s | novel view dB | novel pose dB | fit's held-out dB | its iterate's |\n"
          "|---|---|---|---|---|---|---|", flush=True)
    runs = [(name, overrides, seed) for name, overrides in candidates for seed in args.seeds]
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda run: quality(args.capture, *run, workdir, args.preset, args.threads, args.processes),
                             runs))
    print("\n| candidate | seeds | novel view dB (mean) | novel pose dB (mean) |\n|---|---|---|---|")
    for name, _ in candidates:
        mine = [r for r in rows if r["name"] == name]
        print(f"| {name} | {len(mine)} | {statistics.mean(r['novel_view'] for r in mine):.2f} | "
              f"{statistics.mean(r['novel_pose'] for r in mine):.2f} |")
    print("\n| candidate | seed | variant | overrides | probe PSNR by iteration |\n|---|---|---|---|---|")
    for (name, overrides, _), row in zip(runs, rows):
        over = ", ".join(f"{s}.{k}={v}" for s, kv in overrides.items() for k, v in kv.items()) or "-"
        print(f"| {name} | {row['seed']} | {row['variant']} | {over} | {row['probes']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
