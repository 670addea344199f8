"""Export stage: the avatar as standard 3DGS .ply files, canonical and per motion frame, with correspondences.

Writes OUTPUT/canonical.ply (zero pose, zero translation) and, with --motion, OUTPUT/frame_{i:06d}.ply for
each selected motion frame i plus OUTPUT/correspondences.npz (stable anchor ids and per-frame splat centres);
the conventions are in pig.avatar.export.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pig.avatar.export import export_avatar
from pig.body.npz import read_npz
from pig.config import resolve_device
from pig.stages._cli import add_common_arguments, run_cli

MOTION_FORM = "a motion npz with 'fullpose' (N, 55, 3) SMPL-X axis-angles and 'transl' (N, 3)"


def _read_motion(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(full pose (N, 55, 3), translation (N, 3)) of a DNA-Rendering-style SMPL-X npz; shapes are checked by
    `export_avatar`."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: motion file not found; expected {MOTION_FORM}")
    arrays = read_npz(path, ValueError, MOTION_FORM, keys=("fullpose", "transl"))
    missing = [key for key in ("fullpose", "transl") if key not in arrays]
    if missing:
        raise ValueError(f"{path}: no {' or '.join(repr(k) for k in missing)}; expected {MOTION_FORM}")
    return arrays["fullpose"], arrays["transl"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pig.stages.export", description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True, help="avatar.pt of the fit stage")
    parser.add_argument("--output", type=Path, required=True, help="export directory to write")
    parser.add_argument("--motion", type=Path, help=f"{MOTION_FORM}; adds frame_*.ply and correspondences.npz")
    parser.add_argument("--frames", metavar="START:STOP[:STEP]",
                        help="motion frames to export, STOP excluded (default: all)")
    parser.add_argument("--lod", type=int, help="level of detail, 0 = coarsest (default: the finest)")
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --output folder that is not an earlier export")
    args = parser.parse_args(argv)
    poses, transl = _read_motion(args.motion) if args.motion is not None else (None, None)
    output = export_avatar(args.checkpoint, args.output, args.lod, poses, transl, args.frames, args.motion,
                           resolve_device(args.device, "--device"), args.overwrite)
    print(output)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
