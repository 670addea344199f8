"""Reader for an ActorsHQ sequence at one scale (`calibration.csv`, `rgbs/`, `masks/`) with SMPL-X parameters in
THuman4's `smpl_params.npz` form, as a `RawCapture` (FORMATS.md, "ActorsHQ"; data preparation, no paper equation).

As AnimatableGaussians reads it (lizhe00/AnimatableGaussians `dataset/dataset_mv_rgb.py`, `MvRgbDatasetActorsHQ`,
lines 466-500): a CSV row per camera, `name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py`; the Rodrigues rotation and the
translation are camera to world (the reader inverts the 4 x 4, line 483); the intrinsics are fractions of the
image, `fx * w`, `fy * h`, `px * w`, `py * h` (lines 487-490); frames `rgbs/<cam>/<cam>_rgb%06d.jpg`, masks
`masks/<cam>/<cam>_mask%06d.png` (lines 498-499), foreground above 128 (line 271); `smpl_params.npz` in the sequence
folder (line 253). No distortion: the released frames are undistorted.
"""
from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import cv2
import numpy as np

from pig.body.npz import read_npz
from pig.body.params import ParamsError, SmplxParams
from pig.data.frame_sources import FramesCapture, bounded_file, camera_frames
from pig.data.raw import CaptureError, RawCamera
from pig.data.thuman4 import camera_entry, read_params
from pig.names import safe_name

CALIBRATION = "calibration.csv"
PARAMS = "smpl_params.npz"
COLUMNS = ("name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py")
SCALES = ("1x", "2x", "4x")
LAYOUT = ("<sequence>/<scale>/calibration.csv (name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py), "
          "<scale>/rgbs/<cam>/<cam>_rgb%06d.jpg, <scale>/masks/<cam>/<cam>_mask%06d.png, and smpl_params.npz in "
          "<sequence>/ or <scale>/ (scale 1x, 2x or 4x)")
MAX_CSV_BYTES = 16 * 2**20  # ActorsHQ's 160 cameras take about 30 kB


def scale_folder(root: str | Path, scale: str | None = None) -> Path:
    """The folder holding calibration.csv: `root` itself, or `root/<scale>` (default: the one of 4x, 2x, 1x present,
    in that order: AnimatableGaussians trains on 4x)."""
    root = Path(root)
    if scale is not None:
        if scale not in SCALES:
            raise CaptureError(f"ActorsHQ reader option scale: {scale!r} is not one of {list(SCALES)}")
        folder = root / scale
    elif (root / CALIBRATION).exists():
        folder = root
    else:
        folder = next((root / s for s in reversed(SCALES) if (root / s / CALIBRATION).exists()), root / "4x")
    if not (folder / CALIBRATION).exists():
        raise CaptureError(f"ActorsHQ sequence {root}: {folder / CALIBRATION} not found; expected {LAYOUT}")
    return folder


def params_file(folder: Path) -> Path:
    for path in (folder / PARAMS, folder.parent / PARAMS):
        if path.exists():
            return path
    raise CaptureError(f"ActorsHQ sequence {folder}: {PARAMS} not found in {folder} or {folder.parent} "
                       f"(SMPL-X parameters in THuman4's form); expected {LAYOUT}")


def required_files(root: str | Path) -> list[Path]:
    """The calibration and parameters of the sequence (at the first of 4x, 2x, 1x present, where `root` holds
    several scales)."""
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"ActorsHQ sequence folder {root} not found: put the sequence there as {LAYOUT}")
    folder = scale_folder(root)
    return [folder / CALIBRATION, params_file(folder)]


def read_calibration(path: Path) -> dict[str, RawCamera]:
    """calibration.csv -> world-to-camera cameras in file order."""
    bounded_file(path, "ActorsHQ's calibration.csv", "calibration file not found", MAX_CSV_BYTES, "a calibration holds")
    rows = list(csv.reader(io.StringIO(path.read_text(errors="replace"))))
    if not rows or tuple(c.strip() for c in rows[0]) != COLUMNS:
        found = ",".join(rows[0]) if rows else "nothing"
        raise CaptureError(f"{path}: expected the header {','.join(COLUMNS)}, found {found}")
    cameras: dict[str, RawCamera] = {}
    for number, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(COLUMNS):
            raise CaptureError(f"{path}:{number}: {len(row)} values, expected {len(COLUMNS)} ({','.join(COLUMNS)})")
        name = safe_name(row[0].strip(), "camera name", f"{path}:{number}", CaptureError)
        if name in cameras:
            raise CaptureError(f"{path}:{number}: camera {name} is listed twice")
        try:
            values = {key: float(value) for key, value in zip(COLUMNS[1:], row[1:])}
        except ValueError:
            raise CaptureError(f"{path}:{number}: expected numbers after the camera name, found {row[1:]}") from None
        w, h = values["w"], values["h"]
        if not (w >= 1 and h >= 1 and w == round(w) and h == round(h)):
            raise CaptureError(f"{path}:{number}: w, h must be the image size in pixels, found {w}, {h}")
        to_world, _ = cv2.Rodrigues(np.array([values["rx"], values["ry"], values["rz"]]))
        centre = np.array([values["tx"], values["ty"], values["tz"]])
        K = [[values["fx"] * w, 0.0, values["px"] * w], [0.0, values["fy"] * h, values["py"] * h], [0.0, 0.0, 1.0]]
        entry = {"K": K, "R": to_world.T.tolist(), "T": (-to_world.T @ centre).tolist(), "imgSize": [w, h],
                 "distCoeff": [0.0] * 5}
        cameras[name] = camera_entry(name, entry, path)  # finiteness, positive focal lengths
    if not cameras:
        raise CaptureError(f"{path}: no cameras listed")
    return cameras


def geometry(root: str | Path, options: dict) -> tuple[dict[str, tuple[int, int]], list[int]]:
    """(camera -> (width, height), frame ids) from calibration.csv and the parameters' row count, for `pig doctor`."""
    folder = scale_folder(root, options.get("scale"))
    cameras = read_calibration(folder / CALIBRATION)
    sizes = {name: (cam.width, cam.height) for name, cam in cameras.items()}
    return sizes, list(range(frame_count(params_file(folder))))


def frame_count(path: Path) -> int:
    """Frames of a THuman4-form smpl_params.npz, from its `global_orient` alone."""
    try:
        return len(read_npz(path, ParamsError, "SMPL-X parameters", keys=("global_orient",))["global_orient"])
    except (KeyError, ParamsError) as err:
        raise CaptureError(f"{path}: no readable 'global_orient' ({err})") from None


class ActorsHQCapture(FramesCapture):
    """One ActorsHQ sequence at one scale; `root` is the sequence folder (`Actor01/Sequence1`) or its scale folder."""

    layout = LAYOUT

    def __init__(self, root: str | Path, scale: str | None = None):
        self.source = Path(root)
        if not self.source.is_dir():
            raise CaptureError(f"ActorsHQ sequence folder {root} not found: put the sequence there as {LAYOUT}")
        folder = scale_folder(self.source, scale)
        self.cameras = read_calibration(folder / CALIBRATION)
        self.params: SmplxParams = read_params(params_file(folder))
        self.frames = list(range(self.params.num_frames))
        count = len(self.frames)
        images, masks = {}, {}
        for name, cam in self.cameras.items():
            images[name] = camera_frames(folder / "rgbs" / name, re.escape(name) + r"_rgb(\d+)",
                                         f"{name}_rgb%06d.jpg", cam.width, cam.height, count, f"camera {name}")
            masks[name] = camera_frames(folder / "masks" / name, re.escape(name) + r"_mask(\d+)",
                                        f"{name}_mask%06d.png", cam.width, cam.height, count, f"camera {name}'s masks")
        self._attach(images, masks, set())
