"""Export stage: the avatar as standard 3DGS .ply files, canonical and per motion frame, with correspondences.

Writes OUTPUT/canonical.ply (rest pose, upright along the capture's up axis) and, with --motion,
OUTPUT/frame_{i:06d}.ply for each selected motion frame i, placed in the capture's frame as the animate stage places
them, plus OUTPUT/correspondences.npz (stable anchor ids and per-frame splat centres) and export.json (each file's up
axis, the capture's ground); the conventions are in pig.avatar.export.
"""
from __future__ import annotations

from pathlib import Path

from pig.avatar.export import FORMATS, export_avatar
from pig.config import resolve_device
from pig._cli import add_common_arguments, add_device_argument, run_cli, stage_parser

MOTION_FORM = ("a motion npz: AMASS (poses (N, 156) SMPL-H or (N, 165) SMPL-X, trans, mocap_framerate), THuman4 "
               "smpl_params.npz or DNA-style fullpose (N, 55, 3) with transl")


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("export", __doc__, "pig export --checkpoint results/synthetic/subject00/pig/avatar.pt --motion "
                                             "pig/data/motions/demo.npz --frames 0:144:12 --output results/synthetic/subject00/pig/export")
    parser.add_argument("--checkpoint", type=Path, required=True, help="avatar.pt of the fit stage")
    parser.add_argument("--output", type=Path, required=True, help="export directory to write")
    parser.add_argument("--motion", type=Path, help=f"{MOTION_FORM}; adds frame_*.ply and correspondences.npz")
    parser.add_argument("--frames", metavar="START:STOP[:STEP]",
                        help="motion frames to export, STOP excluded (default: all)")
    parser.add_argument("--lod", type=int, help="level of detail, 0 = coarsest (default: the finest)")
    parser.add_argument("--up", choices=["+x", "-x", "+y", "-y", "+z", "-z"],
                        help="the capture's up axis (default: inferred from the avatar's training poses)")
    parser.add_argument("--format", default="ply", choices=list(FORMATS),
                        help="ply: 3DGS PLY, every viewer; splat: antimatter15's .splat; ply_compressed: SuperSplat's "
                             ".compressed.ply (default: ply)")
    add_device_argument(parser)
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --output folder that is not an earlier export")
    args = parser.parse_args(argv)
    output = export_avatar(args.checkpoint, args.output, args.lod, None, None, args.frames, args.motion,
                           resolve_device(args.device, "--device"), args.overwrite, args.up, args.format)
    print(output)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
