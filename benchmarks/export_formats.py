"""Export formats compared: file size, write time and what each keeps, for splats of the paper's size.

Writes N random splats (SH degree 3, positions inside a body-sized box, scales of a few millimetres) in each of
`pig export --format`'s forms (pig.avatar.export.write_splats) and prints a table: bytes per splat, the size against
the 3DGS .ply, the write time, and the largest position error after decoding (the compressed PLY quantises
positions to 11-10-11 bits within chunks of 256 splats; .splat keeps float32 positions).

    python benchmarks/export_formats.py [--splats 100000] [--seed 0]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from pig.avatar.export import FORMATS, write_splats


def random_splats(count: int, seed: int) -> tuple[torch.Tensor, ...]:
    generator = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=generator, dtype=torch.float64) * torch.tensor([0.6, 1.8, 0.4]) - 0.3
    quats = torch.randn(count, 4, generator=generator, dtype=torch.float64)
    scales = 0.002 + 0.008 * torch.rand(count, 3, generator=generator, dtype=torch.float64)
    opacities = torch.rand(count, generator=generator, dtype=torch.float64)
    sh = 0.3 * torch.randn(count, 16, 3, generator=generator, dtype=torch.float64)
    return means, quats, scales, opacities, sh


def decoded_positions(path: Path, fmt: str) -> np.ndarray:
    """Splat centres read back from a written file (independent of the writer: the formats' published layouts)."""
    data = path.read_bytes()
    if fmt == "splat":
        return np.frombuffer(data, dtype=[("xyz", "<f4", 3), ("rest", "u1", 20)])["xyz"].astype(np.float64)
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    counts = {line.split()[1]: int(line.split()[2]) for line in header if line.startswith("element ")}
    if fmt == "ply":
        columns = sum(1 for line in header if line.startswith("property float"))
        return np.frombuffer(data, "<f4", counts["vertex"] * columns, end).reshape(-1, columns)[:, :3].astype(np.float64)
    chunks = np.frombuffer(data, "<f4", counts["chunk"] * 18, end).reshape(-1, 18).astype(np.float64)
    packed = np.frombuffer(data, "<u4", counts["vertex"] * 4, end + counts["chunk"] * 72).reshape(-1, 4)[:, 0]
    packed = packed.astype(np.int64)
    unit = np.stack([(packed >> 21) & 2047, (packed >> 11) & 1023, packed & 2047], 1) / np.array([2047, 1023, 2047])
    low = np.repeat(chunks[:, :3], 256, 0)[:len(packed)]
    high = np.repeat(chunks[:, 3:6], 256, 0)[:len(packed)]
    return low + unit * (high - low)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--splats", type=int, default=100_000, help="number of splats (default: the paper's 100k)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random splats")
    args = parser.parse_args()
    splats = random_splats(args.splats, args.seed)
    means = splats[0].numpy()
    tree = cKDTree(means)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for fmt, suffix in FORMATS.items():
            path = Path(folder) / f"canonical{suffix}"
            start = time.perf_counter()
            write_splats(path, splats, fmt, np.array([0.0, 1.0, 0.0]))
            seconds = time.perf_counter() - start
            decoded = decoded_positions(path, fmt)
            error_mm = 1000 * tree.query(decoded)[0].max()
            rows.append((fmt, path.stat().st_size, len(decoded), seconds, error_mm))
    ply_bytes = rows[0][1]
    print(f"{args.splats} splats, SH degree 3, torch threads {torch.get_num_threads()}")
    print(f"{'format':<16}{'MB':>8}{'B/splat':>9}{'vs ply':>8}{'splats kept':>13}{'write s':>9}{'max pos err mm':>16}")
    for fmt, size, kept, seconds, error_mm in rows:
        print(f"{fmt:<16}{size / 1e6:>8.2f}{size / args.splats:>9.1f}{size / ply_bytes:>8.3f}{kept:>13}{seconds:>9.2f}"
              f"{error_mm:>16.3f}")


if __name__ == "__main__":
    main()
