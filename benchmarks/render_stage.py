"""Per-frame avatar evaluation in the render stage: preconditioned tensors baked to their value x once
(pig.field.precondition.bake_preconditioning) against solving x = (I + lambda L)^-1 u on every frame.

    python benchmarks/render_stage.py --checkpoint results/synthetic/subject00/pig/avatar.pt [--repeats 6]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from pig.avatar.checkpoint import load_avatar
from pig.field.precondition import bake_preconditioning


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=6)
    args = parser.parse_args()
    solved, baked = load_avatar(args.checkpoint), load_avatar(args.checkpoint)
    bake_preconditioning(baked)
    finest = solved.num_levels - 1
    reference, result = solved.gaussians(0, finest), baked.gaussians(0, finest)
    difference = max((a - b).abs().max().item() for a, b in zip(reference, result))
    times = {"solved per frame": [], "baked once": []}
    for _ in range(args.repeats):  # interleaved, so contention hits both alike
        for name, model in (("solved per frame", solved), ("baked once", baked)):
            start = time.perf_counter()
            model.gaussians(0, finest)
            times[name].append(time.perf_counter() - start)
    print(f"| avatar.gaussians, LOD {finest + 1}/{solved.num_levels}, {solved.level_sizes[-1]} anchors | median [ms] |\n|---|---|")
    for name, values in times.items():
        print(f"| {name} | {sorted(values)[len(values) // 2] * 1e3:.0f} |")
    ratio = sorted(times["solved per frame"])[args.repeats // 2] / sorted(times["baked once"])[args.repeats // 2]
    print(f"ratio solved / baked: {ratio:.2f}; max |difference| of the outputs: {difference:.2e}; threads {torch.get_num_threads()}")


if __name__ == "__main__":
    main()
