"""Renderer speed: the CPU compositor at 128..512 px with 1k..20k Gaussians, gsplat on a GPU.

Prints a table (and writes CSV with --out). Scenes are random Gaussians in the view frustum whose
projected standard deviations are 1-3 px, the regime of DESIGN.md section 5.

    python benchmarks/render.py                       # CPU table
    python benchmarks/render.py --device cuda         # gsplat (and the compositor on the GPU)
    python benchmarks/render.py --peak-memory 50000 512   # peak RSS of one forward + backward
"""
from __future__ import annotations

import argparse
import csv
import io
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

from pig.render import render_gaussians
from pig.render.cpu_compositor import row_spans
from pig.render.projection import project_splats
from pig._io import write_text


def make_scene(n: int, width: int, height: int, device: str, seed: int = 0, sh_degree: int = 3):
    """n Gaussians at depth 2..4 inside the frustum of a camera with f = width; sigma 1-3 px."""
    g = torch.Generator().manual_seed(seed)
    focal = float(width)
    z = 2.0 + 2.0 * torch.rand(n, 1, generator=g)
    u = torch.rand(n, 1, generator=g) * width
    v = torch.rand(n, 1, generator=g) * height
    means = torch.cat([(u - width / 2) * z / focal, (v - height / 2) * z / focal, z], dim=1)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)
    sigma_px = 1.0 + 2.0 * torch.rand(n, 3, generator=g)
    scales = sigma_px * z / focal
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    sh = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g)
    viewmats = torch.eye(4)[None]
    Ks = torch.tensor([[[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]]])
    tensors = [t.to(device) for t in (means, quats, scales, opacities, sh, viewmats, Ks)]
    return tensors[:5], tensors[5], tensors[6]


def count_pairs(gaussians, viewmats, Ks, width, height) -> int:
    """(Gaussian, pixel) pairs the compositor enumerates (its row spans), its unit of work."""
    with torch.no_grad():
        splats = project_splats(*gaussians, viewmats, Ks, width, height, 3)
        geometry = torch.cat([splats.means2d, splats.conics, splats.opacities[:, None]], dim=1)
        return int(row_spans(geometry, splats.radii, splats.camera, width, height).nx.sum())


def time_call(fn, device: str, repeats: int) -> tuple[float, float]:
    """Median wall and process-CPU seconds of `repeats` calls after one warm-up call.

    CPU seconds are the steadier number on a shared machine: they exclude time spent descheduled.
    """
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        if device == "cuda":
            torch.cuda.synchronize()
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        if device == "cuda":
            torch.cuda.synchronize()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu)


def bench(n: int, width: int, height: int, device: str, backend: str, repeats: int) -> dict:
    gaussians, viewmats, Ks = make_scene(n, width, height, device)
    params = [t.requires_grad_(True) for t in gaussians]
    background = torch.zeros(3, device=device)

    def forward():
        with torch.no_grad():
            render_gaussians(*params, viewmats, Ks, width, height, background, backend=backend)

    def forward_backward():
        out = render_gaussians(*params, viewmats, Ks, width, height, background, backend=backend)
        (out.color.sum() + out.alpha.sum() + out.depth.sum()).backward()

    forward_s, forward_cpu_s = time_call(forward, device, repeats)
    both_s, both_cpu_s = time_call(forward_backward, device, repeats)
    return {
        "device": device,
        "backend": backend,
        "threads": torch.get_num_threads(),
        "gaussians": n,
        "width": width,
        "height": height,
        "pairs": count_pairs(gaussians, viewmats, Ks, width, height),
        "forward_s": forward_s,
        "forward_cpu_s": forward_cpu_s,
        "forward_backward_s": both_s,
        "forward_backward_cpu_s": both_cpu_s,
    }


def peak_memory(n: int, size: int) -> None:
    """One CPU forward + backward; prints the process's peak resident memory."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    gaussians, viewmats, Ks = make_scene(n, size, size, "cpu")
    params = [t.requires_grad_(True) for t in gaussians]
    out = render_gaussians(*params, viewmats, Ks, size, size, torch.zeros(3), backend="cpu")
    (out.color.sum() + out.depth.sum()).backward()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    pairs = count_pairs(gaussians, viewmats, Ks, size, size)
    print(f"{n} Gaussians, {size}x{size}, {pairs} pairs: peak RSS {peak / 2**20:.2f} GiB "
          f"(before the scene: {before / 2**20:.2f} GiB)")


def write_csv(rows: list[dict], path: Path) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, buffer.getvalue())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", help="square image sizes (CPU; default 128 256 512)")
    parser.add_argument("--gaussians", type=int, nargs="+", help="Gaussian counts")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--out", type=Path, help="CSV file for the table")
    parser.add_argument("--peak-memory", type=int, nargs=2, metavar=("N", "SIZE"))
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    if args.peak_memory:
        peak_memory(*args.peak_memory)
        return 0
    if args.device == "cuda":
        if not torch.cuda.is_available():
            print("--device cuda: no CUDA device", file=sys.stderr)
            return 2
        configs = [(n, 1330, 1150, backend) for n in args.gaussians or [12500, 25000, 50000, 100000]
                   for backend in ("gsplat", "cpu")]
    else:
        configs = [(n, s, s, "cpu") for s in args.sizes or [128, 256, 512]
                   for n in args.gaussians or [1000, 5000, 10000, 20000]]

    rows = []
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, load average {os.getloadavg()[0]:.1f}")
    print(f"{'device':6} {'backend':7} {'N':>7} {'W x H':>11} {'pairs':>10} "
          f"{'fwd s':>7} {'fwd cpu s':>9} {'fwd+bwd s':>9} {'fwd+bwd cpu s':>13}")
    for n, width, height, backend in configs:
        row = bench(n, width, height, args.device, backend, args.repeats)
        rows.append(row)
        print(f"{row['device']:6} {backend:7} {n:7d} {f'{width} x {height}':>11} {row['pairs']:10d} "
              f"{row['forward_s']:7.3f} {row['forward_cpu_s']:9.3f} {row['forward_backward_s']:9.3f} "
              f"{row['forward_backward_cpu_s']:13.3f}", flush=True)
    if args.out:
        write_csv(rows, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
