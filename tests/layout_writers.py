"""Test writers: a THuman4-layout subject (the synthetic one) rewritten in the EasyMocap, ActorsHQ and AvatarReX
layouts, with frame folders or one lossless video (FFV1 in .mkv) a camera, for the readers to read back.

Images and masks are written losslessly (PNG or FFV1) so that a reader must give back the very pixels. The
conversions run the other way from the readers': world to camera -> ActorsHQ's camera to world and normalised
intrinsics, standard SMPL-X -> EasyMocap's Rh / Th about the origin with hand PCA coefficients.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from pig.body.model import BodyModel
from pig.data.thuman4 import Thuman4Capture

FOURCC = "FFV1"


def _write_frames(folder: Path, frames: dict[int, np.ndarray], name, video: bool) -> None:
    """Frames as PNG files named `name(frame)` in `folder`, or as one FFV1 video `folder.mkv` (frame i at i)."""
    if video:
        folder.parent.mkdir(parents=True, exist_ok=True)
        first = next(iter(frames.values()))
        writer = cv2.VideoWriter(str(folder.with_name(folder.name + ".mkv")), cv2.VideoWriter_fourcc(*FOURCC), 30,
                                 (first.shape[1], first.shape[0]))
        assert writer.isOpened()
        for frame in range(len(frames)):
            image = frames[frame]
            writer.write(image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
        writer.release()
        return
    folder.mkdir(parents=True, exist_ok=True)
    for frame, image in frames.items():
        assert cv2.imwrite(str(folder / name(frame)), image)


def _images(capture: Thuman4Capture, camera: str) -> dict[int, np.ndarray]:
    return {f: cv2.cvtColor(capture.read_image(camera, f), cv2.COLOR_RGB2BGR) for f in capture.frames}


def _masks(capture: Thuman4Capture, camera: str) -> dict[int, np.ndarray]:
    return {f: capture.read_mask(camera, f) for f in capture.frames}


def _thuman_params(capture: Thuman4Capture) -> dict[str, np.ndarray]:
    p = capture.params
    pose = p.full_pose.reshape(p.num_frames, -1)
    return {"betas": p.betas[None], "global_orient": pose[:, :3], "body_pose": pose[:, 3:66],
            "jaw_pose": pose[:, 66:69], "left_hand_pose": pose[:, 75:120], "right_hand_pose": pose[:, 120:165],
            "expression": p.expression, "transl": p.transl}


def write_actorshq(capture: Thuman4Capture, sequence: Path, scale: str = "4x", video: bool = False) -> Path:
    """`sequence/<scale>/{calibration.csv, rgbs, masks}` and `sequence/smpl_params.npz`; the cameras must have no
    distortion (ActorsHQ's frames are undistorted)."""
    folder = sequence / scale
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "calibration.csv", "w", newline="") as handle:
        out = csv.writer(handle)
        out.writerow(["name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py"])
        for name, cam in capture.cameras.items():
            assert not np.any(cam.dist), "ActorsHQ holds no distortion"
            to_world = cam.R.T
            centre = -cam.R.T @ cam.T
            rvec = Rotation.from_matrix(to_world).as_rotvec()
            w, h = cam.width, cam.height
            values = [*rvec, *centre, cam.K[0, 0] / w, cam.K[1, 1] / h, cam.K[0, 2] / w, cam.K[1, 2] / h]
            out.writerow([name, w, h, *(repr(float(v)) for v in values)])
    for name in capture.cameras:
        _write_frames(folder / "rgbs" / name, _images(capture, name), lambda f: f"{name}_rgb{f:06d}.png", video)
        _write_frames(folder / "masks" / name, _masks(capture, name), lambda f: f"{name}_mask{f:06d}.png", video)
    np.savez(sequence / "smpl_params.npz", **_thuman_params(capture))
    return sequence


def write_avatarrex(capture: Thuman4Capture, root: Path, video: bool = False) -> Path:
    """`root/{calibration_full.json, <serial>/%08d.png, <serial>/mask/pha/%08d.png, smpl_params.npz}` with the
    cameras renamed to serial numbers."""
    root.mkdir(parents=True, exist_ok=True)
    serials = {name: str(22010700 + i) for i, name in enumerate(capture.cameras)}
    calibration = {serials[name]: {"K": cam.K.tolist(), "R": cam.R.tolist(), "T": cam.T.tolist(),
                                   "imgSize": [cam.width, cam.height], "distCoeff": cam.dist.tolist()}
                   for name, cam in capture.cameras.items()}
    (root / "calibration_full.json").write_text(json.dumps(calibration))
    for name, serial in serials.items():
        _write_frames(root / serial, _images(capture, name), lambda f: f"{f:08d}.png", video)
        _write_frames(root / serial / "mask" / "pha", _masks(capture, name), lambda f: f"{f:08d}.png", video)
    np.savez(root / "smpl_params.npz", **_thuman_params(capture))
    return root


def _opencv_matrix(key: str, value: np.ndarray) -> list[str]:
    value = np.atleast_2d(value)
    data = ", ".join(repr(float(v)) for v in value.reshape(-1))
    return [f"{key}: !!opencv-matrix", f"  rows: {value.shape[0]}", f"  cols: {value.shape[1]}", "  dt: d",
            f"  data: [{data}]"]


def easymocap_fit(capture: Thuman4Capture, model: BodyModel, components: int) -> list[dict]:
    """Per frame, EasyMocap's parameters of the capture's body: Rh = global orient, Th about the origin, poses in
    its short form with `components` hand PCA values a hand (least squares on the model's rows), or the 165 form
    (components 0)."""
    p = capture.params
    n = p.num_frames
    with torch.no_grad():
        _, joints = model.rest_shape(n, torch.from_numpy(p.betas)[None], torch.from_numpy(p.expression))
    j0 = joints[:, 0].double().numpy()
    rotations = Rotation.from_rotvec(p.full_pose[:, 0]).as_matrix()
    Th = p.transl - np.einsum("nij,nj->ni", rotations, j0) + j0
    fits = []
    for i in range(n):
        pose = p.full_pose[i].reshape(-1).copy()
        pose[:3] = 0
        if components:
            comps = model.hands_components.double().numpy()[:, :components]
            left = np.linalg.lstsq(comps[0].T, pose[75:120], rcond=None)[0]
            right = np.linalg.lstsq(comps[1].T, pose[120:165], rcond=None)[0]
            pose = np.concatenate([pose[:66], left, right, pose[66:75]])
        fits.append({"id": 0, "Rh": [p.full_pose[i, 0].tolist()], "Th": [Th[i].tolist()], "poses": [pose.tolist()],
                     "shapes": [p.betas.tolist()], "expression": [p.expression[i].tolist()]})
    return fits


def write_easymocap(capture: Thuman4Capture, root: Path, model: BodyModel, components: int = 6,
                    video: bool = False, sizes: bool = True, rotation_matrix: bool = True) -> Path:
    """`root/{intri.yml, extri.yml, images/<cam>/%06d.png, mask-schp/<cam>/%06d_0.png (0/1), smplx/%06d.json}`; `sizes`:
    write H_/W_; `rotation_matrix`: write Rot_ beside the Rodrigues R_ (as EasyMocap's write_camera does)."""
    root.mkdir(parents=True, exist_ok=True)
    names = list(capture.cameras)
    intri = ["%YAML:1.0", "---", "names:", *[f'  - "{name}"' for name in names]]
    extri = ["%YAML:1.0", "---", "names:", *[f'  - "{name}"' for name in names]]
    for name, cam in capture.cameras.items():
        intri += _opencv_matrix(f"K_{name}", cam.K) + _opencv_matrix(f"dist_{name}", cam.dist[None])
        if sizes:
            intri += [f"H_{name}: {cam.height}", f"W_{name}: {cam.width}"]
        extri += _opencv_matrix(f"R_{name}", Rotation.from_matrix(cam.R).as_rotvec()[:, None])
        if rotation_matrix:
            extri += _opencv_matrix(f"Rot_{name}", cam.R)
        extri += _opencv_matrix(f"T_{name}", cam.T[:, None])
    (root / "intri.yml").write_text("\n".join(intri) + "\n")
    (root / "extri.yml").write_text("\n".join(extri) + "\n")
    for name in names:
        _write_frames(root / "images" / name, _images(capture, name), lambda f: f"{f:06d}.png", video)
        masks = {f: (m > 128).astype(np.uint8) for f, m in _masks(capture, name).items()}  # SCHP-like labels 0/1
        _write_frames(root / "mask-schp" / name, masks, lambda f: f"{f:06d}_0.png", video)
    (root / "smplx").mkdir(exist_ok=True)
    for frame, fit in zip(capture.frames, easymocap_fit(capture, model, components)):
        (root / "smplx" / f"{frame:06d}.json").write_text(json.dumps([fit]))
    return root
