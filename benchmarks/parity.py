"""Held-out PSNR curves of fit runs made by `benchmarks/fit_gpu.py --eval-every N --json F` (one or more files):
a table of every variant's PSNR per evaluation with its difference to the first variant's, and a plot. With
`--iterate`, the curves of the iterates of runs that evaluated a weight average. With `--path NAME=RUN,RUN,...`
(twice or more), repeated runs of each path are pooled: per evaluation each path's mean, the difference of the means
to the first path's, and each path's spread (largest minus smallest run), which is the scale a difference between
paths has to be read against, since a GPU fit does not repeat itself.

    python benchmarks/parity.py benchmarks/gpu_runs/run9/parity_fast.json benchmarks/gpu_runs/run9/parity_baseline.json \
        --reference baseline --plot benchmarks/gpu_runs/run9/parity.png
    python benchmarks/parity.py benchmarks/gpu_runs/run22/*.json --path float32=base_a,base_b --path fast=fast_a,fast_b
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit_gpu import plot_heldout  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("results", type=Path, nargs="+", help="fit_gpu.py --json files")
    parser.add_argument("--reference", default=None, help="variant the others are compared with (default: the first)")
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--iterate", action="store_true",
                        help="the iterates' PSNR where the runs evaluated a weight average (fit.average_decay)")
    parser.add_argument("--path", action="append", default=[], metavar="NAME=RUN,RUN",
                        help="pool repeated runs of one path (repeatable; the first is the reference)")
    args = parser.parse_args(argv)
    runs = [r for path in args.results for r in json.loads(path.read_text())["results"]]
    for r in runs:
        r["heldout"] = {int(k): v for k, v in r["heldout"].items()}
        if args.iterate:  # before the average starts the iterate is what was evaluated
            r["heldout"].update({int(k): v for k, v in r.get("heldout_iterate", {}).items()})
    reference = args.reference or runs[0]["name"]  # read before sorting: the list is empty to a sort's key
    runs.sort(key=lambda r: r["name"] != reference)
    first = runs[0]
    print(f"| iteration | " + " | ".join(r["name"] for r in runs) + " | " +
          " | ".join(f"{r['name']} - {first['name']}" for r in runs[1:]) + " |")
    print("|---|" + "---|" * (2 * len(runs) - 1))
    worst = {r["name"]: 0.0 for r in runs[1:]}
    for step in sorted(first["heldout"]):
        values = [r["heldout"].get(step, float("nan")) for r in runs]
        for r, v in zip(runs[1:], values[1:]):
            worst[r["name"]] = max(worst[r["name"]], abs(v - values[0]))
        print(f"| {step} | " + " | ".join(f"{v:.3f}" for v in values) + " | " +
              " | ".join(f"{v - values[0]:+.3f}" for v in values[1:]) + " |")
    for name, value in worst.items():
        print(f"largest |{name} - {first['name']}|: {value:.3f} dB")
    if args.path:
        print_paths(runs, args.path)
    if args.plot is not None:
        plot_heldout(runs, args.plot)
    return 0


def print_paths(runs: list[dict], specs: list[str]) -> None:
    by_name = {r["name"]: r for r in runs}
    paths = []
    for spec in specs:
        name, _, members = spec.partition("=")
        missing = [m for m in members.split(",") if m not in by_name]
        if not members or missing:
            raise SystemExit(f"parity: --path {spec}: runs {missing or '(none)'} not among {sorted(by_name)}")
        paths.append((name, [by_name[m]["heldout"] for m in members.split(",")]))
    steps = sorted(set.intersection(*(set(h) for _, curves in paths for h in curves)))
    names = [name for name, _ in paths]
    print(f"\n| iteration | " + " | ".join(f"{n} mean" for n in names) + " | " +
          " | ".join(f"{n} - {names[0]}" for n in names[1:]) + " | " + " | ".join(f"{n} spread" for n in names) + " |")
    print("|---|" + "---|" * (3 * len(names) - 1))
    worst = {n: 0.0 for n in names[1:]}
    for step in steps:
        values = [[h[step] for h in curves] for _, curves in paths]
        means = [sum(v) / len(v) for v in values]
        for n, m in zip(names[1:], means[1:]):
            worst[n] = max(worst[n], abs(m - means[0]))
        print(f"| {step} | " + " | ".join(f"{m:.3f}" for m in means) + " | " +
              " | ".join(f"{m - means[0]:+.3f}" for m in means[1:]) + " | " +
              " | ".join(f"{max(v) - min(v):.3f}" for v in values) + " |")
    for name, value in worst.items():
        print(f"largest |{name} - {names[0]}| of the means: {value:.3f} dB")


if __name__ == "__main__":
    raise SystemExit(main())
