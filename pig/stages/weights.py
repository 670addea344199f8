"""Weights stage: lists the metric networks' weight files (found or missing, checksum ok or bad) and fetches them.

The files are LPIPS's AlexNet / VGG16 backbones and linear layers and FID's Inception (pig.metrics.weight_files
holds each one's URL and SHA-256). Listing reads only the disk; `--fetch` is the project's only network use: it
downloads the missing files, checks each SHA-256 before the file takes its name, and replaces nothing already
there. The workflow's `fetch_weights` rule runs `pig weights --fetch`.
"""
from __future__ import annotations

from pathlib import Path

from pig.metrics.weight_files import WEIGHT_FILES, check_and_fetch
from pig._cli import add_common_arguments, run_cli, stage_parser


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("weights", __doc__, "pig weights --fetch --only vgg16 lpips-vgg")
    parser.add_argument("--fetch", action="store_true",
                        help="download the missing files (each SHA-256 checked; nothing is replaced); without it, only "
                             "list them. The workflow's rule does the same: snakemake --cores 1 fetch_weights")
    parser.add_argument("--only", nargs="+", metavar="NAME",
                        help=f"these files only: {', '.join(f.name for f in WEIGHT_FILES)} (default: all)")
    parser.add_argument("--dest", type=Path, help="look up and fetch into this folder instead of the torch hub cache "
                                                  "($TORCH_HOME/hub/checkpoints); then name the files by path in "
                                                  "the preset's *_weights keys")
    add_common_arguments(parser)
    args = parser.parse_args(argv)
    return 0 if check_and_fetch(args.only, args.fetch, args.dest) else 1


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
