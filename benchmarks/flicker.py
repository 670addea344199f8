"""Temporal flicker of rendered novel-pose video: the mean absolute frame-to-frame change of the renders against that of
the ground truth, per camera and LOD, from a render stage output and its capture.

A novel pose takes the time embedding of its nearest training timestep, which can jump between neighbouring frames
of a smooth motion. Per camera, over consecutive split frames t, t+1 (both scored on the black background with the
ground truth masked, as the evaluation does):
  render change  = mean |R(t+1) - R(t)|,   truth change = mean |G(t+1) - G(t)|,
  excess         = mean |(R(t+1) - R(t)) - (G(t+1) - G(t))|  (change the truth does not have),
and the largest per-step render/truth ratio (a jump shows there). Prints one row per LOD.

    python benchmarks/flicker.py --capture results/synthetic/subject00/capture \
        --renders results/synthetic/subject00/pig/renders/novel_pose
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from pig.data.capture import Capture
from pig.data.render_store import RenderReader


def level_flicker(capture: Capture, level_dir: Path, cameras: list[str], frames: list[int]) -> dict[str, float]:
    render_steps, truth_steps, excess, ratios = [], [], [], []
    reader = RenderReader(level_dir)  # chunks, or per-view PNGs
    for cam in cameras:
        previous = None
        for frame in frames:
            if not reader.has(cam, frame) or not capture.has(cam, frame):
                previous = None
                continue
            render = reader.image(cam, frame)
            truth = capture.image(cam, frame) * capture.mask(cam, frame)[..., None]
            if previous is not None:
                d_render, d_truth = render - previous[0], truth - previous[1]
                render_steps.append(np.abs(d_render).mean())
                truth_steps.append(np.abs(d_truth).mean())
                excess.append(np.abs(d_render - d_truth).mean())
                ratios.append(render_steps[-1] / max(truth_steps[-1], 1e-12))
            previous = (render, truth)
    if not render_steps:
        raise ValueError(f"{level_dir}: no two consecutive frames rendered for cameras {cameras}")
    return {"steps": len(render_steps), "render_change": float(np.mean(render_steps)), "truth_change": float(np.mean(truth_steps)),
            "excess": float(np.mean(excess)), "max_ratio": float(np.max(ratios))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--capture", type=Path, required=True)
    parser.add_argument("--renders", type=Path, required=True, help="renders/novel_pose of the render stage")
    parser.add_argument("--split", default="novel_pose")
    parser.add_argument("--cameras", nargs="*", default=None, help="default: the split's cameras")
    args = parser.parse_args(argv)
    capture = Capture.load(args.capture)
    split = capture.split[args.split]
    cameras = args.cameras or split["cameras"]
    frames = sorted(int(f) for f in split["frames"])
    levels = sorted(p for p in args.renders.glob("lod*") if p.is_dir())
    if not levels:
        print(f"flicker: no lod*/ folders under {args.renders}", file=sys.stderr)
        return 1
    print(f"{args.split}: {len(cameras)} cameras x {len(frames)} frames ({frames[0]}..{frames[-1]})\n")
    print("| LOD | steps | render change | truth change | render / truth | excess change | largest step ratio |")
    print("|---|---|---|---|---|---|---|")
    for level_dir in levels:
        r = level_flicker(capture, level_dir, cameras, frames)
        print(f"| {level_dir.name} | {r['steps']} | {r['render_change']:.5f} | {r['truth_change']:.5f} | "
              f"{r['render_change'] / r['truth_change']:.3f} | {r['excess']:.5f} | {r['max_ratio']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
