"""What torch's deterministic kernels cost a CPU fit: the avatar's forward + backward (grid, refiner, body, transport,
decoders: every op deterministic mode can change on the CPU; the compositor's kernels are the same either way),
timed with deterministic algorithms off and on in turn, in one process, and the two gradients compared.

The one kernel that differs is index_put_ with accumulate (the backward of the transport's vertex gathers): two
threads add with atomics in a racing order, deterministic mode adds serially. Prints ms per pass of each setting
(wall and process CPU time, medians over the rounds: on a loaded machine the CPU time is the steadier),
their ratios, and how many parameter gradients of two passes differ in each setting.

    python benchmarks/determinism_cpu.py --checkpoint results/synthetic/subject00/pig/avatar.pt --threads 2
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from pig.avatar.checkpoint import load_avatar


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, required=True, help="avatar.pt of a CPU fit (its sizes are timed)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=10, help="passes per setting, alternating")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    model = load_avatar(args.checkpoint)
    model.train()
    for p in model.parameters():
        p.requires_grad_(True)
    lod, steps = model.num_levels - 1, torch.tensor([0])
    weights = {}

    def one_pass() -> tuple[float, list[torch.Tensor]]:
        model.zero_grad(set_to_none=True)
        t0, c0 = time.perf_counter(), time.process_time()
        g = model(steps, lod)
        loss = sum((getattr(g, name) * weights.setdefault(name, torch.rand_like(getattr(g, name)))).sum()
                   for name in ("means", "quats", "scales", "opacities", "sh"))
        loss.backward()
        seconds = time.perf_counter() - t0, time.process_time() - c0
        return seconds, [p.grad.clone() if p.grad is not None else None for p in model.parameters()]

    times = {False: [], True: []}
    grads = {False: [], True: []}
    one_pass()  # warm-up
    before = torch.are_deterministic_algorithms_enabled()
    try:
        for round_ in range(args.rounds):
            for setting in ((False, True) if round_ % 2 == 0 else (True, False)):
                torch.use_deterministic_algorithms(setting)
                seconds, grad = one_pass()
                times[setting].append(seconds)
                grads[setting].append(grad)
    finally:
        torch.use_deterministic_algorithms(before)

    def differing(runs: list[list]) -> int:
        """Parameter gradients that differ between any pass and the first."""
        return sum(any(not torch.equal(run[k], runs[0][k]) for run in runs[1:])
                   for k in range(len(runs[0])) if runs[0][k] is not None)

    total = sum(g is not None for g in grads[False][0])
    print(f"{args.checkpoint}: {model.level_sizes[-1]} anchors, {args.threads} threads, {args.rounds} passes each\n")
    print("| deterministic | wall ms per forward + backward (median) | per pass | process CPU ms (median) | "
          "gradients differing between passes |\n|---|---|---|---|---|")
    wall = {k: [t[0] for t in v] for k, v in times.items()}
    cpu = {k: [t[1] for t in v] for k, v in times.items()}
    for setting in (False, True):
        print(f"| {'on' if setting else 'off'} | {1000 * statistics.median(wall[setting]):.1f} | "
              f"{' '.join(f'{1000 * t:.0f}' for t in wall[setting])} | {1000 * statistics.median(cpu[setting]):.1f} | "
              f"{differing(grads[setting])} of {total} |")
    print(f"\non / off: wall {statistics.median(wall[True]) / statistics.median(wall[False]):.3f}, process CPU "
          f"{statistics.median(cpu[True]) / statistics.median(cpu[False]):.3f} (medians)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
