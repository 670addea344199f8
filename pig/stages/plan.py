"""Plan stage: prints the fits that a set of tables needs, which are done, and the GPU-hours of the others: each
fit's iterations, then the render and evaluate of its held-out splits, and the wall time on some GPUs.

The workflow's `plan_tables` target runs it over every table of a dataset (workflow/rules/tables.smk); the
estimate is pig.avatar.plan's: the preset's iterations times a time per iteration, and the protocol's views (the
dataset's nominal sizes, pig.doctor.nominal_protocol: no data needed) at rates per frame and view, all of which the
user can set.
"""
from __future__ import annotations

from pathlib import Path

from pig.avatar.plan import MS_PER_ITERATION, MS_PER_ITERATION_LPIPS, ProtocolRates, plan_tables
from pig.config import load_preset
from pig.doctor import load_dataset, nominal_protocol
from pig._cli import add_common_arguments, add_preset_argument, run_cli, stage_parser

RATES = ProtocolRates()


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("plan", __doc__, "pig plan --results results/dna --dataset dna --run 0102 pig --run 0102 "
                                           "no_precond --preset paper --gpus 1 4 8")
    parser.add_argument("--results", type=Path, required=True,
                        help="the dataset's results folder: a fit's outputs are in {results}/{subject}/{variant}/")
    parser.add_argument("--run", nargs=2, action="append", required=True, metavar=("SUBJECT", "VARIANT"),
                        help="one fit (repeat for each)")
    parser.add_argument("--dataset", help="a dataset name (config/datasets/) or YAML path: its protocol's views "
                                          "are counted for render and evaluate, and its raw views for preprocess "
                                          "(without it, the fits alone)")
    parser.add_argument("--ms-per-iteration", type=float, default=MS_PER_ITERATION,
                        help=f"ms per fit iteration without the LPIPS term (default {MS_PER_ITERATION}: H100)")
    parser.add_argument("--ms-per-iteration-lpips", type=float, default=MS_PER_ITERATION_LPIPS,
                        help=f"ms per fit iteration with it (default {MS_PER_ITERATION_LPIPS}: H100)")
    rates = parser.add_argument_group("render, evaluate and preprocess rates (defaults measured on one H100 at "
                                      "1330 x 1150: benchmarks/NOTES.md, run26 and run7; per-view costs scale "
                                      "with a view's pixels)")
    rates.add_argument("--render-ms-per-frame", type=float, default=RATES.render_ms_per_frame,
                       help=f"GPU ms to pose one frame at one LOD (default {RATES.render_ms_per_frame})")
    rates.add_argument("--render-ms-per-view", type=float, default=RATES.render_ms_per_view,
                       help=f"GPU ms to render and encode one view at one LOD (default {RATES.render_ms_per_view})")
    rates.add_argument("--evaluate-s-per-split", type=float, default=RATES.evaluate_s_per_split,
                       help=f"GPU s of one evaluate pass's start and FID (default {RATES.evaluate_s_per_split})")
    rates.add_argument("--evaluate-ms-per-view", type=float, default=RATES.evaluate_ms_per_view,
                       help="GPU ms to score one view at one LOD: PSNR, SSIM, LPIPS-VGG, FID features "
                            f"(default {RATES.evaluate_ms_per_view})")
    rates.add_argument("--preprocess-views-per-s", type=float, default=RATES.preprocess_views_per_s,
                       help=f"raw views preprocessed a second on the CPU (default {RATES.preprocess_views_per_s}: "
                            "16 threads)")
    parser.add_argument("--gpus", type=int, nargs="+", default=[1],
                        help="GPU counts for the wall-time estimate, e.g. 1 4 8 (0: none)")
    add_preset_argument(parser, "reads `fit`, `avatar`, `preprocess` and `variants`")
    add_common_arguments(parser)
    args = parser.parse_args(argv)
    if any(count < 0 for count in args.gpus):
        parser.error(f"--gpus: expected counts of 0 or more, found {args.gpus}")
    preset = load_preset(args.preset)
    protocol = nominal_protocol(preset, load_dataset(args.dataset)[0]) if args.dataset else None
    rates = ProtocolRates(args.render_ms_per_frame, args.render_ms_per_view, args.evaluate_s_per_split,
                          args.evaluate_ms_per_view, args.preprocess_views_per_s)
    print(plan_tables(preset, [tuple(run) for run in args.run], args.results, args.ms_per_iteration,
                      args.ms_per_iteration_lpips, protocol, rates, [count for count in args.gpus if count]))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
