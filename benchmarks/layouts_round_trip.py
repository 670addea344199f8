"""Round-trip figures of the EasyMocap, ActorsHQ and AvatarReX readers: the synthetic subject written into each
layout (tests/layout_writers.py: PNG frames or one FFV1 video a camera) and read back, against the THuman4 reading.

Per layout and storage: the largest camera differences (K in pixels, R, T in metres), body differences (pose in
radians, translation in metres, posed vertices in metres), the largest shift of the projected body (pixels),
image pixels that differ and mask pixels that differ after the threshold, and the reader's time per view (image and
mask; a video's frames in order).

    python benchmarks/layouts_round_trip.py [--cameras 4] [--frames 6] [--size 96]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from layout_writers import write_actorshq, write_avatarrex, write_easymocap  # noqa: E402
from pig.body.model import BodyModel  # noqa: E402
from pig.data.actorshq import ActorsHQCapture  # noqa: E402
from pig.data.avatarrex import AvatarReXCapture  # noqa: E402
from pig.data.easymocap import EasyMocapCapture  # noqa: E402
from pig.data.synthetic import SyntheticConfig, generate_capture  # noqa: E402
from pig.data.thuman4 import Thuman4Capture  # noqa: E402


def _vertices(model, params):
    with torch.no_grad():
        return model(torch.from_numpy(params.full_pose), torch.from_numpy(params.betas)[None],
                     torch.from_numpy(params.expression), torch.from_numpy(params.transl)).vertices.numpy()


def _project(points, cam):
    return cv2.projectPoints(points, cv2.Rodrigues(cam.R)[0], cam.T, cam.K, cam.dist)[0][:, 0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--size", type=int, default=96)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="layouts_"))
    subjects = {}
    for distortion in (0.0, 1.0):
        cfg = SyntheticConfig(cameras=args.cameras, frames=args.frames, width=args.size, height=args.size, workers=1,
                              distortion=distortion)
        raw = generate_capture(work / f"subject{distortion}", cfg, progress=False)
        subjects[distortion] = (raw, Thuman4Capture(raw))
    model = BodyModel.from_file(subjects[0.0][0] / "body_model.npz", dtype=torch.float64)
    cases = [("easymocap 165", 1.0, lambda t, r, v: EasyMocapCapture(write_easymocap(t, r, model, 0, v), model), 128),
             ("easymocap 87 (PCA 6)", 1.0, lambda t, r, v: EasyMocapCapture(write_easymocap(t, r, model, 6, v), model),
              128),
             ("actorshq", 0.0, lambda t, r, v: ActorsHQCapture(write_actorshq(t, r, video=v)), None),
             ("avatarrex", 1.0, lambda t, r, v: AvatarReXCapture(write_avatarrex(t, r, video=v)), None)]
    print(f"synthetic subject: {args.cameras} cameras x {args.frames} frames at {args.size} x {args.size}")
    print("| layout | storage | K px | R | T m | pose rad | transl m | vertices m | projection px | image px differ | "
          "mask px differ | ms/view |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, distortion, make, threshold in cases:
        raw, thuman = subjects[distortion]
        truth = _vertices(model, thuman.params)
        for video in (False, True):
            capture = make(thuman, work / f"{name.split()[0]}{distortion}{video}{len(name)}", video)
            cams = list(zip(capture.cameras.values(), thuman.cameras.values()))
            cam_diff = {key: max(np.abs(getattr(a, key) - getattr(b, key)).max() for a, b in cams)
                        for key in ("K", "R", "T")}
            posed = _vertices(model, capture.params)
            shift = max(np.abs(_project(posed[i], a) - _project(truth[i], b)).max()
                        for a, b in cams for i in range(len(capture.frames)))
            images = masks = 0
            seconds = 0.0
            for (cam, _), (ref, _) in zip(capture.cameras.items(), thuman.cameras.items()):
                for frame in capture.frames:
                    start = time.perf_counter()
                    image, mask = capture.read_image(cam, frame), capture.read_mask(cam, frame)
                    seconds += time.perf_counter() - start
                    images += int((image != thuman.read_image(ref, frame)).any(axis=2).sum())
                    ref_mask = thuman.read_mask(ref, frame)
                    differ = (mask > 128) != (ref_mask > 128) if threshold else mask != ref_mask
                    masks += int(differ.sum())
            ms = 1000 * seconds / (len(cams) * len(capture.frames))
            pose = np.abs(capture.params.full_pose - thuman.params.full_pose).max()
            transl = np.abs(capture.params.transl - thuman.params.transl).max()
            print(f"| {name} | {'FFV1 video' if video else 'PNG frames'} | {cam_diff['K']:.1e} | {cam_diff['R']:.1e} | "
                  f"{cam_diff['T']:.1e} | {pose:.1e} | {transl:.1e} | {np.abs(posed - truth).max():.1e} | "
                  f"{shift:.1e} | "
                  f"{images} | {masks} | {ms:.2f} |")


if __name__ == "__main__":
    main()
