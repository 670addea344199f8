"""Start-up of the synthetic generator's render workers: wall seconds of a capture too small to take any rendering
time, 4 workers, from a main module (this script) that takes --main-import-s seconds to import, as
benchmarks/fit_gpu.py takes to import torch's compiler and the fitting code on a bare GPU host.

    python benchmarks/synthetic_start.py [--main-import-s 3 --workers 4]

Run it with PYTHONPATH at two checkouts to compare them. Workers that start one after another, each re-importing
this script (spawn does, as __mp_main__), take ~workers x (import + the generator's own imports); workers that start
together and leave it alone, ~one worker's imports (pig.data.synthetic.workers: benchmarks/NOTES.md, "Synthetic
capture generator: workers start together").
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

if __name__ == "__mp_main__":  # a render worker importing this script
    time.sleep(float(os.environ["MAIN_IMPORT_S"]))

from pig.data.synthetic import SyntheticConfig, generate_capture  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--main-import-s", type=float, default=3.0)
    parser.add_argument("--workers", type=int, default=4)
    args = parser.parse_args()
    os.environ["MAIN_IMPORT_S"] = str(args.main_import_s)  # the workers inherit it
    cfg = SyntheticConfig(cameras=args.workers, frames=4, width=32, height=32, workers=args.workers)
    with tempfile.TemporaryDirectory() as folder:
        wall = time.perf_counter()
        generate_capture(Path(folder) / "raw", cfg, progress=False)
        wall = time.perf_counter() - wall
    print("| workers | main module import s | generate wall s |\n|---|---|---|")
    print(f"| {args.workers} | {args.main_import_s:.1f} | {wall:.1f} |")


if __name__ == "__main__":
    main()
