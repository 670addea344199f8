"""Preprocess stage time on the default (cpu-demo) synthetic capture: thread-pool sizes and output scales.

    python benchmarks/preprocess.py [--raw DIR] [--profile cpu-demo]

Generates the profile's synthetic capture into a temporary folder unless --raw names one, then runs
the stage several times in this process and prints a table (images phase, projection check, total).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from pig.config import load_profile, load_section, load_yaml
from pig.data.formats import open_capture
from pig.data.splits import SplitConfig
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.stages.preprocess import PreprocessConfig, preprocess_capture

REPO = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--raw", type=Path, default=None, help="existing raw synthetic subject folder")
    parser.add_argument("--profile", default="cpu-demo")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    profile = load_profile(args.profile)
    dataset = load_yaml(REPO / "config" / "datasets" / "synthetic.yaml")
    split_cfg = load_section(dataset, "split", SplitConfig)
    with tempfile.TemporaryDirectory() as tmp:
        raw_root = args.raw
        if raw_root is None:
            start = time.perf_counter()
            raw_root = generate_capture(Path(tmp) / "subject00", load_section(profile, "synthetic", SyntheticConfig),
                                        progress=False)
            print(f"generated {raw_root} in {time.perf_counter() - start:.1f} s")
        raw = open_capture("thuman4", raw_root)
        base = load_section(profile, "preprocess", PreprocessConfig)
        rows = []
        for workers, scale in ((1, 1.0), (2, 1.0), (2, 0.5)):
            cfg = PreprocessConfig(**{**base.__dict__, "workers": workers, "scale": scale})
            for repeat in range(args.repeats):
                report = preprocess_capture(raw, Path(tmp) / f"out_{workers}_{scale}_{repeat}", cfg,
                                            raw_root / "body_model.npz", split_cfg, "subject00", progress=False)
                rows.append((workers, scale, report["images"], report["seconds_images"], report["seconds_check"],
                             report["seconds"]))
    print(f"{'workers':>7} {'scale':>5} {'images':>6} {'images_s':>8} {'img/s':>6} {'check_s':>7} {'total_s':>7}")
    for workers, scale, images, images_s, check_s, total_s in rows:
        print(f"{workers:>7} {scale:>5} {images:>6} {images_s:>8.2f} {images / images_s:>6.1f} {check_s:>7.2f} "
              f"{total_s:>7.2f}")
    best = {key: min(r[3] for r in rows if r[:2] == key) for key in ((1, 1.0), (2, 1.0))}
    print(f"images phase, 2 workers / 1 worker (best of {args.repeats}): {best[(2, 1.0)] / best[(1, 1.0)]:.2f}")


if __name__ == "__main__":
    main()
