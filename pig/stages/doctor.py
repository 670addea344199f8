"""Doctor stage: what this machine has and lacks for a preset and a dataset, one line per check, with what to do.

torch and its CUDA build, gsplat's CUDA extension, nvcc, the metric weights (present and checksummed), the body
model, and free disk at the results folder against what the preset and dataset write (pig.doctor). Exit status 0
when everything the preset and dataset need is there, 1 when something needed is missing; `warn` lines (e.g. the
evaluation's LPIPS and FID weights, whose columns are n/a without them) do not fail it.
"""
from __future__ import annotations

from pathlib import Path

from pig.config import load_preset
from pig.doctor import report, run_checks
from pig._cli import add_common_arguments, add_preset_argument, run_cli, stage_parser


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("doctor", __doc__, "pig doctor --preset paper --dataset thuman4 --results /scratch/results")
    add_preset_argument(parser, "its GPU jobs, metric weights and sizes")
    parser.add_argument("--dataset", default="synthetic",
                        help="a dataset in config/datasets/ or a dataset YAML path (default: synthetic)")
    parser.add_argument("--results", type=Path, default=Path("results"),
                        help="where the workflow writes (default: results, as snakemake run from the checkout)")
    add_common_arguments(parser)
    args = parser.parse_args(argv)
    preset = load_preset(args.preset)
    checks = run_checks(preset, args.dataset, args.results)
    print(report(checks, preset, args.dataset))
    return 1 if any(check.verdict == "missing" for check in checks) else 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
