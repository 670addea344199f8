"""The synthetic generator's render workers with and without their one-BLAS-thread limit
(pig.data.synthetic.capture.WORKER_THREAD_LIMITS), alternated in one process: wall and CPU seconds (the parent's
and the workers') of one capture at the paper's image size.

    python benchmarks/synthetic_workers.py [--cameras 4 --frames 4 --workers 2 --repeats 2]

Without the limit OpenBLAS starts a thread per core in every worker; the CPU seconds show what idle threads spin.
On a host with many cores and several workers that is most of the generation (benchmarks/NOTES.md).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import pig.data.synthetic.capture as capture
from pig.data.synthetic import SyntheticConfig, generate_capture
from synthetic_generate import cpu_seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    cfg = SyntheticConfig(cameras=args.cameras, frames=args.frames, width=1330, height=1150, supersample=2,
                          workers=args.workers)
    views = args.cameras * args.frames
    limits = dict(capture.WORKER_THREAD_LIMITS)
    print(f"{views} views at 1330 x 1150 (supersample 2), {args.workers} workers")
    print("| workers' BLAS threads | wall s | CPU s (parent + workers) | CPU s a view |\n|---|---|---|---|")
    for _ in range(args.repeats):
        for label, limit in (("a thread per core (no limit)", {}), ("one (WORKER_THREAD_LIMITS)", limits)):
            capture.WORKER_THREAD_LIMITS = limit
            with tempfile.TemporaryDirectory() as folder:
                wall, cpu = time.perf_counter(), cpu_seconds()
                generate_capture(Path(folder) / "raw", cfg, progress=False)
                wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
            print(f"| {label} | {wall:.1f} | {cpu:.1f} | {cpu / views:.2f} |", flush=True)
    capture.WORKER_THREAD_LIMITS = limits


if __name__ == "__main__":
    main()
