"""Stage `generate`: write the synthetic capture (THuman4 layout + ground-truth meshes) for a compute preset.

The dataset every stage after it reads (DESIGN.md section 4); sizes come from the preset's `synthetic` section.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pig.config import load_preset, load_section
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig._cli import add_common_arguments, add_preset_argument, run_cli, stage_parser


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = stage_parser("generate", __doc__, "pig generate --output results/synthetic/data/subject00 --preset test")
    parser.add_argument("--output", required=True, type=Path, help="subject folder to create (THuman4 layout)")
    add_preset_argument(parser, "its synthetic section")
    parser.add_argument("--seed", type=int, default=None, help="override synthetic.seed")
    parser.add_argument("--workers", type=int, default=None, help="override synthetic.workers (render processes)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing non-empty output folder that is not an earlier generated capture")
    add_common_arguments(parser)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    overrides = {k: v for k, v in (("seed", args.seed), ("workers", args.workers)) if v is not None}
    cfg = load_section(load_preset(args.preset), "synthetic", SyntheticConfig, overrides)
    start = time.perf_counter()
    out = generate_capture(args.output, cfg, overwrite=args.overwrite, progress=not args.quiet)
    print(f"generate: wrote {cfg.cameras} cameras x {cfg.frames} frames ({cfg.width}x{cfg.height}) to {out} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
