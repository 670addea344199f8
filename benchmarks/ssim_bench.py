"""SSIM cost in the loss: separable valid filtering of the five stacked moments (pig.metrics.ssim)
against a dense 11x11 window applied per moment (the straightforward form), forward + backward.

    python benchmarks/ssim_bench.py [--size 256] [--batch 4] [--repeats 5]
"""
from __future__ import annotations

import argparse
import time

import torch
import torch.nn.functional as F

from pig.metrics.ssim import K1, K2, gaussian_window, ssim


def dense_ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Baseline: a dense 2-D window, one convolution per moment."""
    taps = gaussian_window(x.dtype)
    window = (taps[:, None] * taps[None, :]).expand(3, 1, 11, 11)
    blur = lambda t: F.conv2d(t, window, groups=3)  # noqa: E731
    mu_x, mu_y = blur(x), blur(y)
    var_x, var_y, cov = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2, blur(x * y) - mu_x * mu_y
    c1, c2 = K1**2, K2**2
    return ((2 * mu_x * mu_y + c1) * (2 * cov + c2) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))).mean()


def seconds(fn, x, y, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        x.grad = None
        start = time.perf_counter()
        fn(x, y).backward()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.manual_seed(0)
    x = torch.rand(args.batch, 3, args.size, args.size, requires_grad=True)
    y = torch.rand(args.batch, 3, args.size, args.size)
    assert torch.allclose(ssim(x, y), dense_ssim(x, y), atol=1e-5)
    fast, dense = seconds(ssim, x, y, args.repeats), seconds(dense_ssim, x, y, args.repeats)
    print(f"| form | {args.batch}x3x{args.size}^2 fwd+bwd [ms] |\n|---|---|")
    print(f"| separable, stacked moments | {fast * 1e3:.1f} |\n| dense 11x11 per moment | {dense * 1e3:.1f} |")
    print(f"ratio dense / separable: {dense / fast:.2f}")


if __name__ == "__main__":
    main()
