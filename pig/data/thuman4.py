"""Reader for a THuman4.0 subject folder (images/, masks/, calibration.json, smpl_params.npz) as a `RawCapture`.

Accepts every variant in FORMATS.md (flat or 3x3 K/R, jpg or png, missing-frame lists with / or \\ separators,
betas with 1 or N rows); data preparation for the paper's experiments, no paper equation.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np

from pig.body.npz import read_npz
from pig.body.params import THUMAN_KEYS, ParamsError, SmplxParams, from_thuman
from pig.data.images import read_image
from pig.data.raw import CaptureError, RawCamera
from pig.data.rectify import check_matte
from pig.inputs import require_regular_file
from pig.names import safe_name

CALIBRATION = "calibration.json"
PARAMS = "smpl_params.npz"
PARAMS_EXPECTED = "SMPL-X parameters (betas, global_orient, transl, body_pose, ...)"
MISSING_LISTS = {"images": "missing_img_files.txt", "masks": "missing_msk_files.txt"}
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
LAYOUT = ("images/camXX/%08d.jpg (or .png), masks/camXX/%08d.jpg (or .png), calibration.json, smpl_params.npz, "
          "optionally missing_img_files.txt / missing_msk_files.txt")
_FRAME_FILE = re.compile(r"^(\d+)$")
_DIST_LENGTHS = (4, 5, 8, 12, 14)  # the lengths OpenCV accepts


def required_files(root: str | Path) -> list[Path]:
    """The files a subject folder must hold; CaptureError saying where to put the data if absent."""
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"THuman4 subject folder {root} not found: put the subject there with {LAYOUT}")
    needed = [root / CALIBRATION, root / PARAMS, root / "images", root / "masks"]
    missing = [str(p) for p in needed if not p.exists()]
    if missing:
        raise CaptureError(f"THuman4 subject folder {root} is incomplete: missing {missing}; expected {LAYOUT}")
    return [root / CALIBRATION, root / PARAMS]


class Thuman4Capture:
    """One THuman4 subject; images and masks are decoded on demand, the file index is built once."""

    def __init__(self, root: str | Path):
        self.source = Path(root)
        required_files(self.source)
        self.cameras = read_calibration(self.source / CALIBRATION)
        self._check_camera_folders()
        self.params: SmplxParams = read_params(self.source / PARAMS)
        self.frames = list(range(self.params.num_frames))
        missing = {kind: self._read_missing(kind) for kind in MISSING_LISTS}
        listed = missing["images"] | missing["masks"]  # a missing image also has no usable mask
        self._files: dict[str, dict[str, dict[int, Path]]] = {"images": {}, "masks": {}}
        for kind in ("images", "masks"):
            for cam in self.cameras:
                files = self._index(self.source / kind / cam)
                self._check_frames(kind, cam, files, {f for c, f in listed if c == cam})
                self._files[kind][cam] = files
        self._missing = listed

    def has_frame(self, camera: str, frame: int) -> bool:
        self._camera(camera)
        return ((camera, frame) not in self._missing and frame in self._files["images"][camera]
                and frame in self._files["masks"][camera])

    def read_image(self, camera: str, frame: int) -> np.ndarray:
        path = self._path("images", camera, frame)
        image = read_image(path, cv2.IMREAD_COLOR, self._pixels(camera))
        self._check_size(image, camera, path)
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def read_mask(self, camera: str, frame: int) -> np.ndarray:
        path = self._path("masks", camera, frame)
        mask = read_image(path, cv2.IMREAD_GRAYSCALE, self._pixels(camera))
        self._check_size(mask, camera, path)
        return check_matte(mask, str(path))

    def _camera(self, camera: str) -> RawCamera:
        if camera not in self.cameras:
            raise CaptureError(f"{self.source / CALIBRATION}: unknown camera {camera!r}; cameras are {list(self.cameras)}")
        return self.cameras[camera]

    def _path(self, kind: str, camera: str, frame: int) -> Path:
        self._camera(camera)
        path = self._files[kind][camera].get(frame)
        if path is None or (camera, frame) in self._missing:
            raise CaptureError(f"{self.source / kind / camera}: no usable file for frame {frame} "
                               f"(absent or listed as missing)")
        return path

    def _pixels(self, camera: str) -> int:
        """The bound on an image's declared size before decoding: the camera's own."""
        return self.cameras[camera].width * self.cameras[camera].height

    def _check_size(self, image: np.ndarray, camera: str, path: Path) -> None:
        cam = self.cameras[camera]
        if image.shape[:2] != (cam.height, cam.width):
            raise CaptureError(f"{path}: image is {image.shape[1]}x{image.shape[0]} (WxH), but {CALIBRATION} "
                               f"gives imgSize [{cam.width}, {cam.height}] for {camera}")

    def _check_camera_folders(self) -> None:
        """A camera folder without calibration is an error, not skipped: the split holds out cameras by their
        position in the calibration, so a silently dropped camera would shift which cameras are held out."""
        for kind in ("images", "masks"):
            uncalibrated = sorted(p.name for p in (self.source / kind).iterdir()
                                  if p.is_dir() and not p.name.startswith(".") and p.name not in self.cameras)
            if uncalibrated:
                raise CaptureError(
                    f"{self.source / kind / uncalibrated[0]}: camera folder not listed in {self.source / CALIBRATION} "
                    f"(uncalibrated folder(s) in {kind}/: {uncalibrated}; calibrated cameras: {list(self.cameras)}); "
                    f"add the camera to {CALIBRATION} or move the folder out of {kind}/")

    def _index(self, folder: Path) -> dict[int, Path]:
        """Frame id -> file of one camera folder; two files for one frame are an error."""
        if not folder.is_dir():
            raise CaptureError(f"{folder}: camera folder not found, but {self.source / CALIBRATION} lists camera "
                               f"{folder.name!r}; add the folder or remove the camera from {CALIBRATION} "
                               f"(expected {LAYOUT})")
        files: dict[int, Path] = {}
        for entry in folder.iterdir():
            match = _FRAME_FILE.match(entry.stem)
            if entry.suffix.lower() not in IMAGE_SUFFIXES or not match:
                continue
            frame = int(match.group(1))
            if frame in files:
                raise CaptureError(f"{folder}: two files for frame {frame}: {files[frame].name} and {entry.name}")
            files[frame] = entry
        return files

    def _check_frames(self, kind: str, camera: str, files: dict[int, Path], listed: set[int]) -> None:
        """Every parameter frame must have a file or be listed missing; no file may lack parameters."""
        folder = self.source / kind / camera
        count = len(self.frames)
        extra = sorted(f for f in files if f >= count)
        if extra:
            raise CaptureError(f"{folder}: {len(extra)} frame(s) from {extra[0]} on have no body parameters: "
                               f"{PARAMS} has {count} frames (0..{count - 1}); frame counts disagree")
        absent = sorted(set(self.frames) - set(files) - listed)
        if absent:
            raise CaptureError(f"{folder}: {len(absent)} of the {count} frames in {PARAMS} have no file and are not "
                               f"listed in {MISSING_LISTS['images']} / {MISSING_LISTS['masks']} (first: {absent[:5]}); "
                               "frame counts disagree")

    def _read_missing(self, kind: str) -> set[tuple[str, int]]:
        """(camera, frame) pairs listed in a missing-files list; paths may use / or \\ separators."""
        path = self.source / MISSING_LISTS[kind]
        if not path.exists():
            return set()
        require_regular_file(path, CaptureError, "a list of missing files, one path a line")
        pairs = set()
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            line = line.strip()
            if not line:
                continue
            parts = [p for p in line.replace("\\", "/").split("/") if p]
            stem = parts[-1].rsplit(".", 1)[0]
            if len(parts) < 2 or parts[-2] not in self.cameras or not _FRAME_FILE.match(stem):
                raise CaptureError(f"{path}:{number}: expected a path ending in <camera>/<frame>.jpg with a camera "
                                   f"from {CALIBRATION}, found {line!r}")
            pairs.add((parts[-2], int(stem)))
        return pairs


def read_params(path: Path) -> SmplxParams:
    """SMPL-X parameters in THuman4's `smpl_params.npz` form (also ActorsHQ's and AvatarReX's); a bad file is a
    CaptureError naming it."""
    try:
        return from_thuman(read_npz(path, ParamsError, PARAMS_EXPECTED, keys=THUMAN_KEYS), str(path))
    except ParamsError as err:
        raise CaptureError(str(err)) from None


def read_calibration(path: Path, dist_optional: bool = False) -> dict[str, RawCamera]:
    """calibration.json -> cameras in file order; K and R flat (9) or 3x3, T of 3, imgSize [W, H]; `distCoeff`
    zeros where absent if `dist_optional` (AvatarReX's calibration_full.json)."""
    try:
        require_regular_file(path, CaptureError, "a calibration JSON file")
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: calibration file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CaptureError(f"{path}: not valid JSON: {err}") from None
    if not isinstance(data, dict) or not data:
        raise CaptureError(f"{path}: expected a non-empty mapping camera id -> {{K, R, T, imgSize, distCoeff}}")
    # Checked before any camera is used: each id names the folders images/<id>/ and masks/<id>/ read here and
    # written by the preprocess stage.
    names = [safe_name(name, "camera id", str(path), CaptureError) for name in data]
    return {name: camera_entry(name, data[name], path, dist_optional) for name in names}


def _numbers(value) -> np.ndarray | None:
    """float64 array of a JSON number or (nested) list of numbers; None for strings, null, mappings, ragged lists."""
    try:
        array = np.asarray(value)
    except ValueError:  # ragged nesting
        return None
    return array.astype(np.float64) if array.dtype.kind in "iuf" else None


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _matrix(entry: dict, key: str, size: int, where: str) -> np.ndarray:
    if key not in entry:
        raise CaptureError(f"{where}: missing key '{key}'; found {sorted(entry)}")
    value = _numbers(entry[key])
    if value is None:
        raise CaptureError(f"{where}: '{key}' must be {size} numbers, found {_shown(entry[key])}")
    if value.size != size:
        raise CaptureError(f"{where}: '{key}' has shape {value.shape}, expected {size} numbers")
    if not np.all(np.isfinite(value)):
        raise CaptureError(f"{where}: '{key}' contains NaN or infinite values")
    return value.reshape(-1)


def camera_entry(name: str, entry, path: Path, dist_optional: bool = False) -> RawCamera:
    """One camera of a calibration file (`path`, for messages) from THuman4's keys, checked."""
    where = f"{path}: camera '{name}'"
    if not isinstance(entry, dict):
        raise CaptureError(f"{where}: expected a mapping with K, R, T, imgSize, distCoeff")
    K = _matrix(entry, "K", 9, where).reshape(3, 3)
    R = _matrix(entry, "R", 9, where).reshape(3, 3)
    T = _matrix(entry, "T", 3, where)
    if "distCoeff" not in entry and dist_optional:
        entry = {**entry, "distCoeff": [0.0] * 5}
    if "distCoeff" not in entry:
        raise CaptureError(f"{where}: missing key 'distCoeff' (OpenCV distortion, length 5); found {sorted(entry)}")
    dist = _numbers(entry["distCoeff"])
    if dist is None or dist.size not in _DIST_LENGTHS or not np.all(np.isfinite(dist)):
        raise CaptureError(f"{where}: 'distCoeff' must hold {' or '.join(map(str, _DIST_LENGTHS))} finite numbers "
                           f"(OpenCV distortion), found {_shown(entry['distCoeff'])}")
    dist = dist.reshape(-1)
    size = _matrix(entry, "imgSize", 2, where)
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise CaptureError(f"{where}: 'imgSize' must be [width, height] in pixels, found {entry['imgSize']!r}")
    if not np.allclose(K[2], [0, 0, 1]):
        hint = " (it looks transposed: store K row by row)" if np.allclose(K[:, 2], [0, 0, 1]) else ""
        raise CaptureError(f"{where}: 'K' must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], found {K.tolist()}{hint}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CaptureError(f"{where}: 'K' focal lengths must be positive, found fx={K[0, 0]}, fy={K[1, 1]}")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        raise CaptureError(f"{where}: 'R' is not a rotation matrix (R R^T differs from I by "
                           f"{np.abs(R @ R.T - np.eye(3)).max():.3g})")
    if np.linalg.det(R) < 0:
        raise CaptureError(f"{where}: 'R' is a reflection (det = {np.linalg.det(R):.3f}), expected a rotation")
    return RawCamera(name=name, K=K, R=R, T=T, width=int(size[0]), height=int(size[1]), dist=dist)
