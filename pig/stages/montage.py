"""Montage stage: ground truth, render and error of a few views of one rendered split, as one PNG for the report.

The picture is pig.render.montage.split_montage (finest LOD; error on a fixed colour scale); the workflow's
`snakemake --report` shows one per split next to the tables.
"""
from __future__ import annotations

from pathlib import Path

from pig.render.montage import split_montage
from pig._cli import add_common_arguments, run_cli, stage_parser
from pig._io import write_figure
from pig._outputs import claim_files


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("montage", __doc__, "pig montage --capture results/synthetic/subject00/capture --renders results/synthetic/subject00/pig/renders/novel_view "
                                              "--split novel_view --output results/synthetic/subject00/pig/montage/novel_view.png")
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture directory")
    parser.add_argument("--renders", type=Path, required=True, help="renders/{split} directory of the render stage")
    parser.add_argument("--split", required=True, help="split the renders show (novel_view, novel_pose)")
    parser.add_argument("--output", type=Path, required=True, help="PNG file to write")
    parser.add_argument("--views", type=int, default=4, help="views shown, spread evenly over the split (default 4)")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a file of the same name in an --output folder the montage stage did not write")
    args = parser.parse_args(argv)
    if args.output.suffix.lower() != ".png":
        parser.error(f"--output {args.output}: expected a .png file")
    claim_files(args.output.parent, [args.output.name], "montage", (args.capture, args.renders), args.overwrite)
    write_figure(args.output, split_montage(args.capture, args.renders, args.split, args.views), dpi=100)
    print(args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
