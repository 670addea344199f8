"""View stage: a fitted avatar in the browser (viser): orbit, timeline, LOD switch, the capture's cameras.

It serves a page on --host:--port and writes nothing; the capture's cameras show its ground truth beside the render.
Only the viewer's own pages connect: other web pages open in the browser are refused (--allow-origin admits one).

The server renders each view (pig.viewer.app): on CUDA at the page's size, on the CPU 180 pixels high stretched over
the page; `--draw browser` sends the splats to the page instead (fast where its WebGL runs on a GPU). Needs
the `viewer` extra (pip install -e '.[viewer]'). Example:

    pig view --checkpoint results/synthetic/s0/pig/avatar.pt --capture results/synthetic/s0/capture
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from pig._cli import add_common_arguments, add_device_argument, run_cli, stage_parser


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("view", __doc__, "pig view --checkpoint results/synthetic/subject00/pig/avatar.pt --capture "
                                           "results/synthetic/subject00/capture --motion pig/data/motions/demo.npz")
    parser.add_argument("--checkpoint", type=Path, required=True, help="avatar.pt of the fit stage")
    parser.add_argument("--motion", type=Path, default=None,
                        help="motion npz for the timeline (AMASS, THuman4 smpl_params.npz or DNA-style fullpose), "
                             "brought into the capture's frame as the animate stage does; default: the training poses")
    parser.add_argument("--capture", type=Path, default=None,
                        help="preprocessed capture of the fit: its cameras to jump to and its ground truth images")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to serve on (default: this machine only); 0.0.0.0 or a LAN address lets other "
                             "machines on the network see and drive the viewer (docs/viewer.md)")
    parser.add_argument("--port", type=int, default=8080, help="port to serve on (default: 8080)")
    parser.add_argument("--allow-origin", action="append", default=[], type=_origin, metavar="ORIGIN",
                        help="also admit pages of this origin (http(s)://HOST[:PORT], e.g. a tunnel's address); "
                             "repeatable. By default only the viewer's own page connects")
    add_device_argument(parser)
    parser.add_argument("--draw", choices=["browser", "server"], default=None,
                        help="where splats are drawn (default: server)")
    parser.add_argument("--render-height", type=int, default=None,
                        help="server drawing: height in pixels of the rendered frames, stretched over the page "
                             "(default: the page's own on CUDA, 180 on the CPU)")
    add_common_arguments(parser)
    args = parser.parse_args(argv)
    try:
        import viser  # noqa: F401
    except ImportError:
        raise OSError("the viewer needs viser: pip install -e '.[viewer]'") from None
    from pig.viewer.app import open_viewer

    viewer = open_viewer(args.checkpoint, args.motion, args.capture, args.host, args.port, args.device, args.draw,
                         args.render_height, tuple(args.allow_origin))
    print(f"viewer on {viewer.url} (Ctrl+C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
    return 0


def _origin(text: str) -> str:
    from pig.viewer.guard import parse_origin

    try:
        parse_origin(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
