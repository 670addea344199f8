"""Loader of a preprocessed capture (the preprocess stage's output): cameras, SMPL-X parameters, splits, frames.

Images and masks are decoded on first use and kept in memory as uint8 (bounded LRU cache) for the
fit stage's random access; data preparation, no paper equation. An image is `{frame:08d}.png` or, lossy,
`.jpg` (the training views since preprocess writes JPEG); a mask is `{frame:08d}.png`.
"""
from __future__ import annotations

import hashlib
import json
import os
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from pig.body.model import BodyModel
from pig.body.params import ParamsError, SmplxParams
from pig.data.images import read_image
from pig.data.raw import CaptureError
from pig.data.rectify import composite
from pig.data.splits import SPLITS
from pig.inputs import require_regular_file
from pig.names import safe_name
from pig.progress import progress_bar

CAMERA_KEYS = ("K", "R", "T", "width", "height")
IMAGE_SUFFIXES = (".png", ".jpg")
LOSSY_SUFFIXES = (".jpg",)
MASK_SUFFIX = ".png"


@dataclass
class Camera:
    name: str
    K: np.ndarray  # (3, 3) pinhole intrinsics of the preprocessed image (pixel centres at integers)
    R: np.ndarray  # (3, 3) world-to-camera rotation
    T: np.ndarray  # (3,) world-to-camera translation, x_cam = R x_world + T
    width: int
    height: int

    def viewmat(self) -> np.ndarray:
        """(4, 4) world-to-camera matrix."""
        out = np.eye(4)
        out[:3, :3] = self.R
        out[:3, 3] = self.T
        return out

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, -R^T T."""
        return -self.R.T @ self.T


class Capture:
    """A preprocessed capture directory; see `load`."""

    def __init__(self, root: Path, cameras: dict[str, Camera], frames: list[int], params: SmplxParams,
                 split: dict, background: np.ndarray, cache_mb: float):
        self.root = root
        self.cameras = cameras
        self.frames = frames
        self._rows = {f: i for i, f in enumerate(frames)}
        self.params = params
        self.split = split
        self.background = background  # (3,) float32 RGB the images are composited on
        self._background_u8 = np.round(background * 255).astype(np.uint8)
        self._files = {c: {"images": _frame_files(root / "images" / c, IMAGE_SUFFIXES),
                           "masks": _frame_files(root / "masks" / c, (MASK_SUFFIX,))} for c in cameras}
        self._available = {c: files["images"].keys() & files["masks"].keys() for c, files in self._files.items()}
        self._cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._cache_bytes = 0
        self._cache_limit = int(cache_mb * 2**20)
        self._lock = threading.Lock()

    @classmethod
    def load(cls, root: str | Path, cache_mb: float = 4096) -> "Capture":
        """Read cameras.json, smplx.npz, split.json and report.json of `root`; images are read lazily."""
        root = Path(root)
        if not root.is_dir():
            raise CaptureError(f"preprocessed capture {root} not found (run the preprocess stage: "
                               "python -m pig.stages.preprocess --input RAW --output DIR)")
        # Each camera id names a folder read here and written by the render stage: checked before any is used.
        cameras = {safe_name(name, "camera id", str(root / "cameras.json"), CaptureError):
                   _camera(name, entry, root / "cameras.json") for name, entry in _json(root / "cameras.json").items()}
        try:
            params, frames = SmplxParams.load(root / "smplx.npz")
        except ParamsError as err:
            raise CaptureError(str(err)) from None
        if len(set(frames.tolist())) != len(frames):
            raise CaptureError(f"{root / 'smplx.npz'}: 'frames' has repeated frame ids")
        split = _json(root / "split.json")
        frame_set = set(frames.tolist())
        for name in SPLITS:
            part = split.get(name)
            if not isinstance(part, dict) or not {"cameras", "frames"} <= set(part):
                raise CaptureError(f"{root / 'split.json'}: expected '{name}': {{cameras: [...], frames: [...]}}")
            if not part["cameras"] or not part["frames"]:
                raise CaptureError(f"{root / 'split.json'}: split '{name}' is empty ({len(part['cameras'])} cameras, "
                                   f"{len(part['frames'])} frames); rerun preprocess, which refuses such a split")
            unknown = [c for c in part["cameras"] if c not in cameras]
            if unknown:
                raise CaptureError(f"{root / 'split.json'}: split '{name}' names camera(s) {unknown} not in "
                                   f"cameras.json ({list(cameras)})")
            absent = [f for f in part["frames"] if f not in frame_set]
            if absent:
                raise CaptureError(f"{root / 'split.json'}: split '{name}' names frame(s) {absent[:5]} "
                                   "that smplx.npz has no parameters for")
        report = _json(root / "report.json")
        background = np.asarray(report.get("background", [0, 0, 0]), dtype=np.float32) / 255
        return cls(root, cameras, frames.tolist(), params, split, background, cache_mb)

    def fingerprint(self) -> dict[str, str]:
        """SHA-256 of each part of the capture's content: cameras, SMPL-X parameters (with frame ids), split,
        background, body model file, and the image and mask files by name and size. Cheap for thousands of
        images (their bytes are not read) and equal for a rerun of preprocess on the same data."""
        cameras = hashlib.sha256()
        for name in sorted(self.cameras):
            cam = self.cameras[name]
            cameras.update(f"{name} {cam.width} {cam.height}\n".encode())
            for array in (cam.K, cam.R, cam.T):
                cameras.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
        smplx = hashlib.sha256(np.asarray(self.frames, dtype=np.int64).tobytes())
        for array in (self.params.full_pose, self.params.betas, self.params.expression, self.params.transl):
            smplx.update(repr(array.shape).encode())
            smplx.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
        with open(self.root / "body_model.npz", "rb") as file:
            body_model = hashlib.file_digest(file, "sha256")
        files = hashlib.sha256()
        for kind in ("images", "masks"):
            for name in sorted(self.cameras):
                folder = self.root / kind / name
                entries = sorted(os.scandir(folder), key=lambda e: e.name) if folder.is_dir() else []
                for entry in entries:
                    if entry.name.endswith(IMAGE_SUFFIXES if kind == "images" else MASK_SUFFIX):
                        files.update(f"{kind}/{name}/{entry.name} {entry.stat().st_size}\n".encode())
        return {
            "cameras": cameras.hexdigest(),
            "smplx": smplx.hexdigest(),
            "split": hashlib.sha256(json.dumps(self.split, sort_keys=True).encode()).hexdigest(),
            "background": hashlib.sha256(self.background.astype(np.float64).tobytes()).hexdigest(),
            "body_model": body_model.hexdigest(),
            "images": files.hexdigest(),
        }

    def has(self, camera: str, frame: int) -> bool:
        """Whether the capture holds an image and mask of `camera` at `frame` (missing raw frames do not)."""
        return frame in self._available.get(camera, ())

    def views(self, split: str) -> list[tuple[str, int]]:
        """The (camera, frame) pairs of a split that have images, camera-major."""
        if split not in self.split:
            raise CaptureError(f"{self.root / 'split.json'}: no split {split!r}; splits are {list(self.split)}")
        part = self.split[split]
        return [(c, f) for c in part["cameras"] for f in part["frames"] if self.has(c, f)]

    def frame_index(self, frame: int) -> int:
        """Row of `params` for a frame id."""
        if frame not in self._rows:
            raise CaptureError(f"{self.root / 'smplx.npz'}: no parameters for frame {frame}")
        return self._rows[frame]

    def image(self, camera: str, frame: int, background=None) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1] on the preprocess background, or recomposited on `background` (3,)."""
        image = self.image_u8(camera, frame).astype(np.float32) / 255
        if background is not None:
            mask = self.mask(camera, frame)
            image = np.where(mask[..., None], image, np.asarray(background, dtype=np.float32))
        return image

    def image_u8(self, camera: str, frame: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB on the preprocess background, read-only (shared with the cache)."""
        return self._read("images", camera, frame)

    def mask(self, camera: str, frame: int) -> np.ndarray:
        """(H, W) bool foreground mask."""
        return self._read("masks", camera, frame) > 127

    def body_model(self, dtype: torch.dtype = torch.float32) -> BodyModel:
        """The body model the capture's parameters were checked with (body_model.npz)."""
        return BodyModel.from_file(self.root / "body_model.npz", dtype=dtype)

    def preload(self, pairs: list[tuple[str, int]] | None = None, workers: int = 2) -> None:
        """Decode images and masks of `pairs` (default: all) into the cache with a thread pool."""
        if pairs is None:
            pairs = [(c, f) for c in self.cameras for f in self.frames if self.has(c, f)]
        jobs = [(kind, c, f) for c, f in pairs for kind in ("images", "masks")]
        with ThreadPoolExecutor(workers) as pool:
            for _ in progress_bar(pool.map(lambda job: self._read(*job), jobs), total=len(jobs), desc="load capture",
                                  unit="img"):
                pass

    def _read(self, kind: str, camera: str, frame: int) -> np.ndarray:
        key = (kind, camera, frame)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        if camera not in self.cameras:
            raise CaptureError(f"{self.root / 'cameras.json'}: unknown camera {camera!r}; cameras are {list(self.cameras)}")
        if not self.has(camera, frame):
            names = "png or .jpg" if kind == "images" else MASK_SUFFIX[1:]
            raise CaptureError(f"{self.root / kind / camera / f'{frame:08d}'}.{names}: not in the capture (camera "
                               f"{camera} has no image and mask for frame {frame})")
        path = self.root / kind / camera / self._files[camera][kind][frame]
        flag = cv2.IMREAD_COLOR if kind == "images" else cv2.IMREAD_GRAYSCALE
        cam = self.cameras[camera]
        data = read_image(path, flag, cam.width * cam.height)
        if data.shape[:2] != (cam.height, cam.width):
            raise CaptureError(f"{path}: image is {data.shape[1]}x{data.shape[0]}, cameras.json says "
                               f"{cam.width}x{cam.height}")
        if kind == "images":
            data = cv2.cvtColor(data, cv2.COLOR_BGR2RGB)
            if path.suffix in LOSSY_SUFFIXES:  # compression ringing crosses the silhouette: restore the background
                data = composite(data, self._read("masks", camera, frame) > 127, self._background_u8)
        data.setflags(write=False)  # shared by every caller of the cache
        with self._lock:
            self._cache[key] = data
            self._cache_bytes += data.nbytes
            while self._cache_bytes > self._cache_limit and len(self._cache) > 1:
                _, old = self._cache.popitem(last=False)
                self._cache_bytes -= old.nbytes
        return data


def _frame_files(folder: Path, suffixes: tuple[str, ...]) -> dict[int, str]:
    """Frame id -> file name of the frames in `folder`; CaptureError if a frame has two files."""
    files: dict[int, str] = {}
    if not folder.is_dir():
        return files
    for entry in os.scandir(folder):
        stem, suffix = os.path.splitext(entry.name)
        if suffix not in suffixes or not stem.isdigit():
            continue
        frame = int(stem)
        if frame in files:
            raise CaptureError(f"{folder}: frame {frame} has two files, {files[frame]} and {entry.name}; a capture "
                               "holds one per frame (rerun preprocess into a new folder)")
        files[frame] = entry.name
    return files


def _json(path: Path) -> dict:
    try:
        require_regular_file(path, CaptureError, "a JSON file of the preprocessed capture")
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: file not found (an incomplete preprocessed capture? rerun preprocess)") from None
    except json.JSONDecodeError as err:
        raise CaptureError(f"{path}: not valid JSON: {err}") from None
    if not isinstance(data, dict):
        raise CaptureError(f"{path}: expected a JSON object")
    return data


def _camera(name: str, entry, path: Path) -> Camera:
    if not isinstance(entry, dict) or not set(CAMERA_KEYS) <= set(entry):
        raise CaptureError(f"{path}: camera {name!r} must have keys {list(CAMERA_KEYS)}")
    shapes = {"K": (3, 3), "R": (3, 3), "T": (3,)}
    arrays = {}
    for key, shape in shapes.items():
        value = np.asarray(entry[key], dtype=np.float64)
        if value.shape != shape or not np.all(np.isfinite(value)):
            raise CaptureError(f"{path}: camera {name!r} '{key}' must be finite with shape {shape}, found {value.shape}")
        arrays[key] = value
    return Camera(name, arrays["K"], arrays["R"], arrays["T"], int(entry["width"]), int(entry["height"]))
