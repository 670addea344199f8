"""The latent grid's two costs in a CPU fit step, alone: the levels' DCT solves and the lookups (forward + backward).

Solves: ms per `LatticeSystem.solve` of each level (d channels, float32), as the fit runs one per level forward and
one backward. Lookups: the levels' trilinear lookups at N points, forward and backward (gradients into the volumes
and the points), three ways: one after another (`sample_volume` per level, the fit's until issue 40's round four),
the levels split over two Python threads, and each level's channels in two halves as a batch of two (torch's CPU
grid sampler parallelises over the batch only; the halves are a view of the volume). Each way's values and
gradients are compared bit for bit with the first's. Medians over --repeats calls, --threads torch threads.

    python benchmarks/grid_cpu.py --threads 1
    python benchmarks/grid_cpu.py --threads 2
    GOMP_SPINCOUNT=10000 python benchmarks/grid_cpu.py --threads 2   # OpenMP's idle threads spin less
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import torch

from pig.field.latent_grid import sample_volume
from pig.field.lattice_solve import LatticeSystem


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def one_by_one(volumes, coords):
    return sum(sample_volume(v, coords) for v in volumes) / len(volumes)


class TwoThreads(torch.autograd.Function):
    """The levels' lookups, the odd-indexed ones on a second Python thread, forward and backward; the points'
    gradient summed in the order autograd sums one_by_one's (the last level's first): bit for bit its result."""

    pool: ThreadPoolExecutor | None = None

    @staticmethod
    def split(work, items):
        def run(part):
            with torch.no_grad():
                return [work(item) for item in part]

        if TwoThreads.pool is None:
            TwoThreads.pool = ThreadPoolExecutor(1, initializer=torch.set_num_threads, initargs=(1,))
        far = TwoThreads.pool.submit(run, items[1::2])
        out = [None] * len(items)
        out[0::2] = run(items[0::2])
        out[1::2] = far.result()
        return out

    @staticmethod
    def forward(ctx, grid, *volumes):
        ctx.save_for_backward(grid, *volumes)
        outs = TwoThreads.split(lambda v: torch.grid_sampler(v[None], grid, 0, 1, True), list(volumes))
        return tuple(out.reshape(v.shape[0], -1).T for out, v in zip(outs, volumes))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        grid, *volumes = ctx.saved_tensors
        parts = TwoThreads.split(lambda gv: torch.ops.aten.grid_sampler_3d_backward(
            gv[0].T.reshape(1, gv[1].shape[0], 1, 1, -1), gv[1][None], grid, 0, 1, True, [True, True]),
            list(zip(grads, volumes)))
        grid_grad = parts[-1][1]
        for part in parts[-2::-1]:
            grid_grad = grid_grad + part[1]
        return (grid_grad, *(part[0][0] for part in parts))


def two_threads(volumes, coords):
    return sum(TwoThreads.apply(coords.flip(-1).reshape(1, 1, 1, -1, 3), *volumes)) / len(volumes)


class ChannelHalves(torch.autograd.Function):
    """One level's lookup with its channels in two halves, a batch of two: the values and the volume's gradient are
    one_by_one's bit for bit; the points' gradient adds the two halves' channel sums (rounding apart)."""

    @staticmethod
    def forward(ctx, grid, volume):
        ctx.save_for_backward(grid, volume)
        halves = volume.view(2, volume.shape[0] // 2, *volume.shape[1:])
        return torch.grid_sampler(halves, grid.expand(2, -1, -1, -1, -1), 0, 1, True).reshape(volume.shape[0], -1).T

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        grid, volume = ctx.saved_tensors
        halves = volume.view(2, volume.shape[0] // 2, *volume.shape[1:])
        grad_volume, grad_grid = torch.ops.aten.grid_sampler_3d_backward(
            grad.T.reshape(2, halves.shape[1], 1, 1, -1), halves, grid.expand(2, -1, -1, -1, -1), 0, 1, True, [True, True])
        return grad_grid.sum(0, keepdim=True), grad_volume.view_as(volume)


def channel_halves(volumes, coords):
    grid = coords.flip(-1).reshape(1, 1, 1, -1, 3)
    return sum(ChannelHalves.apply(grid, v) for v in volumes) / len(volumes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolutions", type=int, nargs="+", default=[8, 16, 24, 32, 40, 48], help="cpu-demo's")
    parser.add_argument("--features", type=int, default=8)
    parser.add_argument("--points", type=int, default=16000, help="the cpu-demo's anchors, all looked up a step")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    volumes = [torch.randn(args.features, r, r, r, generator=gen) for r in args.resolutions]
    coords = torch.rand(args.points, 3, generator=gen) * 2.2 - 1.1  # some beyond the box: clamped
    weights = torch.randn(args.points, args.features, generator=gen)

    print(f"{args.threads} torch threads, d = {args.features}, float32, median of {args.repeats}")
    print("\n| level | solve ms |\n|---|---|")
    total = 0.0
    for r, volume in zip(args.resolutions, volumes):
        system = LatticeSystem((r, r, r), 2.0)
        ms = median_ms(lambda: system.solve(volume), args.repeats)
        total += ms
        print(f"| {r}^3 | {ms:.2f} |")
    print(f"| all ({len(volumes)} levels) | {total:.2f} |")

    def step(lookup):
        vols = [v.clone().requires_grad_() for v in volumes]
        points = coords.clone().requires_grad_()
        z = lookup(vols, points * 1.0)
        (z * weights).sum().backward()
        return z.detach(), [v.grad for v in vols], points.grad

    reference = step(one_by_one)
    print(f"\n| lookups at {args.points} points, forward + backward | ms | values, volume grads, point grads "
          "bit-identical to one after another |\n|---|---|---|")
    for name, lookup in (("one after another", one_by_one), ("levels on two threads", two_threads),
                         ("channel halves as a batch of two", channel_halves)):
        z, grads, point_grad = step(lookup)
        same = (torch.equal(z, reference[0]), all(torch.equal(a, b) for a, b in zip(grads, reference[1])),
                torch.equal(point_grad, reference[2]))
        print(f"| {name} | {median_ms(lambda: step(lookup), args.repeats):.2f} | {', '.join(map(str, same))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
