"""Fit stage: optimise an avatar on the train split of a preprocessed capture; resumable, logged.

Writes avatar.pt, train_log.csv and train_log.png (redrawn at full held-out evaluations and probes) into --output,
a progress line (iteration, loss, held-out PSNR, time left) to stderr every --progress-seconds, and with
--tensorboard the scalars for TensorBoard; the optimisation itself is pig.avatar.training.fit (Section 3.5, Eq. 15).
With --gpus N (N > 1) one fit runs on N GPUs at once, one process each (pig.avatar.distributed; docs/gpu.md).
"""
from __future__ import annotations

from pathlib import Path

from pig.avatar.parallel_fit import fit_parallel
from pig.avatar.training import fit
from pig.progress import LOG_INTERVAL_S
from pig._cli import add_common_arguments, add_device_argument, add_preset_argument, run_cli, stage_parser


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("fit", __doc__, "pig fit --capture results/synthetic/subject00/capture --output results/synthetic/subject00/pig --preset test "
                                          "--device cpu")
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture directory (results/.../capture)")
    parser.add_argument("--output", type=Path, required=True, help="variant directory; gets avatar.pt, train_log.csv/.png")
    add_preset_argument(parser, "its avatar, fit, field, precond, rasterizer and variants sections")
    parser.add_argument("--variant", default="pig", help="method variant from the preset's `variants` section")
    add_device_argument(parser)
    parser.add_argument("--gpus", type=int, default=1, metavar="N",
                        help="fit on N GPUs at once, one process each (cuda:0..N-1 of those visible; each computes part of "
                             "every iteration's views); 0 or 1: one process on --device (default: 1; the workflow passes "
                             "the fit rule's gpu resource)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads of a CPU fit (default: the preset's fit.cpu_threads; the workflow passes "
                             "the rule's threads); with --gpus N, the threads its N processes share out (default: the "
                             "cores this process may run on)")
    parser.add_argument("--pin-cpus", action="store_true",
                        help="with --gpus N: each process pinned to its own share of the cores (its GPU's NUMA node "
                             "first), with as many torch and OpenCV threads, so that no rank's threads slow another's "
                             "kernel launches")
    parser.add_argument("--progress-seconds", type=float, default=LOG_INTERVAL_S, metavar="SECONDS",
                        help="seconds between progress lines (iteration, loss, held-out PSNR, time left) on stderr "
                             f"(default: {LOG_INTERVAL_S:g}; --quiet: none)")
    parser.add_argument("--tensorboard", action="store_true",
                        help="also write TensorBoard scalars to --output/tensorboard/ (needs pip install 'pig[tensorboard]')")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace avatar.pt, checkpoint.pt, train_log.* in an --output folder the fit stage did not write")
    args = parser.parse_args(argv)
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be at least 1, found {args.threads}")
    if not args.progress_seconds > 0:
        parser.error(f"--progress-seconds must be positive, found {args.progress_seconds}")
    if args.gpus < 0:
        parser.error(f"--gpus must be at least 0, found {args.gpus}")
    if args.pin_cpus and args.gpus < 2:
        parser.error("--pin-cpus shares the cores out among the processes of --gpus N (N >= 2)")
    if args.gpus > 1:
        if args.device not in ("auto", "cuda"):
            parser.error(f"--gpus {args.gpus} fits on cuda:0..{args.gpus - 1}; --device {args.device} cannot go with it")
        path = fit_parallel(args.capture, args.output, args.preset, args.variant, args.gpus, "cuda", overwrite=args.overwrite,
                            progress_s=args.progress_seconds, tensorboard=args.tensorboard, cores=args.threads,
                            pin_cpus=args.pin_cpus)
    else:
        path = fit(args.capture, args.output, args.preset, args.variant, args.device, overwrite=args.overwrite,
                   threads=args.threads, progress_s=args.progress_seconds, tensorboard=args.tensorboard)
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
