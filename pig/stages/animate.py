"""Animate stage: drive a fitted avatar with a motion clip (or hold a pose) and render a video from a capture camera or an orbit.

Writes --output/animation.webm (VP9, browser-playable), animation.json, and with --png / --exr the frames
(PNG with alpha; EXR with R, G, B, A and depth Z); with --page, an HTML page playing the video (the report's
item). The library call is pig.avatar.animation.animate.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from pig.avatar.animation import Orbit, animate
from pig.body.motion import FPS_RANGE
from pig.config import load_preset, load_section
from pig.render.api import RasterizerConfig
from pig.render.video_page import is_video_page, video_page
from pig._io import write_text
from pig._outputs import check_apart
from pig._cli import add_common_arguments, add_device_argument, add_preset_argument, run_cli, stage_parser

MIN_FPS, MAX_FPS = FPS_RANGE
MAX_SECONDS = 3600.0  # an hour of a still pose; motions bring their own length
SIDE_RANGE = (16, 8192)  # orbit image sides in pixels: VP9 and the renderer's memory


def _in_range(kind: type, low: float, high: float, low_open: bool = False):
    """An argparse type: `kind` of `text` within [low, high] ((low, high] with `low_open`), finite."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                             f"found {text!r}") from None
        if not math.isfinite(value) or value > high or value < low or (low_open and value == low):
            bound = f"above {low:g}" if low_open else f"at least {low:g}"
            raise argparse.ArgumentTypeError(f"expected a finite value {bound} and at most {high:g}, found {text}")
        return value
    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("animate", __doc__, "pig animate --checkpoint results/synthetic/subject00/pig/avatar.pt --motion "
                                              "pig/data/motions/demo.npz --output results/synthetic/subject00/pig/animations/demo")
    parser.add_argument("--checkpoint", type=Path, required=True, help="avatar.pt of the fit stage")
    parser.add_argument("--motion", type=Path, default=None,
                        help="motion npz: AMASS (poses (N, 156) SMPL-H or (N, 165) SMPL-X, trans, mocap_framerate), "
                             "THuman4 smpl_params.npz or DNA-style fullpose (N, 55, 3); without it the avatar's first "
                             "training pose is held still (a turntable with the orbit)")
    parser.add_argument("--output", type=Path, required=True, help="folder for animation.webm, animation.json, frames/")
    parser.add_argument("--camera", default=None, help="capture camera id to render from (needs --capture); default: orbit")
    parser.add_argument("--capture", type=Path, default=None, help="preprocessed capture the --camera belongs to")
    parser.add_argument("--lod", type=int, default=None, help="level of detail (0 = coarsest; default: the finest)")
    parser.add_argument("--frames", default=None, help="motion frames START:STOP[:STEP] (default: all)")
    parser.add_argument("--fps", type=_in_range(float, MIN_FPS, MAX_FPS), default=None,
                        help="resample the motion to this frame rate (default: its own)")
    parser.add_argument("--up", default=None, choices=["+x", "-x", "+y", "-y", "+z", "-z"],
                        help="the capture's up axis (default: inferred from the avatar's training poses)")
    parser.add_argument("--orbit-radius", type=float, default=None, help="metres (default: fit the subject in view)")
    parser.add_argument("--orbit-height", type=float, default=Orbit.height, help="metres above the subject's centre")
    parser.add_argument("--orbit-period", type=float, default=Orbit.period_s, help="seconds per revolution")
    parser.add_argument("--size", type=_in_range(int, *SIDE_RANGE), nargs=2, default=(Orbit.width, Orbit.height_px),
                        metavar=("WIDTH", "HEIGHT"),
                        help="orbit camera image size in pixels")
    parser.add_argument("--seconds", type=_in_range(float, 0, MAX_SECONDS, low_open=True), default=None,
                        help="length of a still pose's video (default: one revolution)")
    parser.add_argument("--page", type=Path, default=None,
                        help="also write this HTML file: the video embedded in a page (Snakemake's report shows it)")
    parser.add_argument("--png", action="store_true", help="also write frames/NNNNN.png (RGBA)")
    parser.add_argument("--exr", action="store_true", help="also write frames/NNNNN.exr (R, G, B, A, depth Z)")
    add_preset_argument(parser, "its rasterizer section")
    add_device_argument(parser)
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true", help="replace an --output folder the animate stage did not write")
    args = parser.parse_args(argv)
    orbit = Orbit(radius=args.orbit_radius, height=args.orbit_height, period_s=args.orbit_period, width=args.size[0],
                  height_px=args.size[1])
    if args.page is not None:
        # Not the checkpoint or motion, nor inside the output folder (which a rerun replaces whole).
        check_apart(args.page, [p for p in (args.checkpoint, args.motion, args.output) if p is not None])
        if args.page.exists() and not args.overwrite and not is_video_page(args.page):
            parser.error(f"--page: {args.page} exists and is not a page this stage wrote; pass --overwrite to replace it")
    rasterizer = load_section(load_preset(args.preset), "rasterizer", RasterizerConfig)
    video = animate(args.checkpoint, args.output, args.motion, args.camera, args.capture, args.lod, args.frames, args.fps,
                    args.up, orbit, args.seconds, args.png, args.exr, args.device, rasterizer, args.overwrite)
    if args.page is not None:
        clip = args.motion.stem if args.motion else "turntable"
        write_text(args.page, video_page(video, f"{clip}: {args.checkpoint}"))
    print(video)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
