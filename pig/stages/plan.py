"""Plan stage: prints the fits that a set of tables needs, which are done, and the GPU-hours of the others.

The workflow's `plan_tables` target runs it over every table of a dataset (workflow/rules/tables.smk); the
estimate is pig.avatar.plan's: the preset's iterations times a time per iteration that the user can set.
"""
from __future__ import annotations

from pathlib import Path

from pig.avatar.plan import MS_PER_ITERATION, MS_PER_ITERATION_LPIPS, format_plan, plan_fits
from pig.config import load_preset
from pig._cli import add_common_arguments, add_preset_argument, run_cli, stage_parser


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("plan", __doc__, "pig plan --results results/synthetic --run subject00 pig --run subject00 "
                                           "no_precond --preset paper --gpus 8")
    parser.add_argument("--results", type=Path, required=True,
                        help="the dataset's results folder: a fit's outputs are in {results}/{subject}/{variant}/")
    parser.add_argument("--run", nargs=2, action="append", required=True, metavar=("SUBJECT", "VARIANT"),
                        help="one fit (repeat for each)")
    parser.add_argument("--ms-per-iteration", type=float, default=MS_PER_ITERATION,
                        help=f"ms per fit iteration without the LPIPS term (default {MS_PER_ITERATION}: H100)")
    parser.add_argument("--ms-per-iteration-lpips", type=float, default=MS_PER_ITERATION_LPIPS,
                        help=f"ms per fit iteration with it (default {MS_PER_ITERATION_LPIPS}: H100)")
    parser.add_argument("--gpus", type=int, default=1, help="GPUs for the wall-time estimate (0: none given)")
    add_preset_argument(parser, "reads `fit` and `variants`")
    add_common_arguments(parser)
    args = parser.parse_args(argv)
    planned = plan_fits(load_preset(args.preset), [tuple(run) for run in args.run], args.results,
                        args.ms_per_iteration, args.ms_per_iteration_lpips)
    print(format_plan(planned, args.gpus))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
