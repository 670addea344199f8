"""Reader for an EasyMocap sequence (`intri.yml`, `extri.yml`, `images/`, masks, `smplx/%06d.json`) as a `RawCapture`
(FORMATS.md, "EasyMocap"; data preparation, no paper equation).

Cameras as zju3dv/EasyMocap reads them (`easymocap/mytools/camera_utils.py`, `read_camera`, lines 108-148): `names`
in intri.yml (an entry that reads as no string is a number, lines 49-55), `K_<cam>`, `dist_<cam>` or else `D_<cam>`
(lines 142-146), optional `H_<cam>`, `W_<cam>` (lines 121-127); in extri.yml the Rodrigues `R_<cam>` (lines
128-131; `write_camera` also stores the matrix as `Rot_<cam>`, lines 179-181, read here where `R_` is absent) and
`T_<cam>`, world to camera (`P = K [R | T]`, line 139). Frames `images/<cam>/%06d.jpg`. Masks
`<masks>/<cam>/%06d.png` or `%06d_<person>.png`, the person any value above 0, as EasyMocap's own loader reads them
(`easymocap/neuralbody/dataset/mvbase.py`, lines 113-138), in `mask-schp/` by default, where its configuration for
custom data looks (`config/neuralbody/dataset/neuralbody_custom.yml`, lines 12 and 31); a reader option. The body
fit `smplx/%06d.json` is converted to standard SMPL-X by `pig.body.easymocap`. Frames with images but no fit are
left out (a fit of part of a sequence); a fit without images is an error.
"""
from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from pig.body.params import ParamsError, SmplxParams
from pig.data.frame_sources import (FramesCapture, FrameFiles, bounded_file, camera_frames, relative_folder,
                                     video_in_place_of, video_size)
from pig.data.images import declared_size
from pig.data.raw import CaptureError, RawCamera
from pig.data.thuman4 import camera_entry
from pig.names import safe_name

if TYPE_CHECKING:
    from pig.body.model import BodyModel

INTRI, EXTRI = "intri.yml", "extri.yml"
LAYOUT = ("intri.yml, extri.yml (OpenCV FileStorage), images/<cam>/%06d.jpg, mask-schp/<cam>/%06d.png, "
          "smplx/%06d.json")
MAX_YAML_BYTES = 16 * 2**20
MAX_JSON_BYTES = 16 * 2**20  # a frame's fits: a few kB a person
_FRAME = r"(\d+)"


def required_files(root: str | Path) -> list[Path]:
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"EasyMocap sequence folder {root} not found: put the sequence there with {LAYOUT}")
    missing = [str(root / name) for name in (INTRI, EXTRI) if not (root / name).exists()]
    if missing:
        raise CaptureError(f"EasyMocap sequence folder {root} is incomplete: missing {missing}; expected {LAYOUT}")
    return [root / INTRI, root / EXTRI]


class _Storage:
    """An OpenCV FileStorage read node by node, each matrix only after its declared size is checked."""

    def __init__(self, path: Path):
        self.path = path
        bounded_file(path, "an OpenCV FileStorage YAML file", f"file not found; expected {LAYOUT}", MAX_YAML_BYTES,
                     "a calibration holds")
        try:
            self.storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except cv2.error as err:
            raise CaptureError(f"{path}: not a readable OpenCV FileStorage file ({err.msg.strip()})") from None
        if not self.storage.isOpened():
            raise CaptureError(f"{path}: not a readable OpenCV FileStorage file")

    def names(self) -> list[str]:
        node = self.storage.getNode("names")
        if node.empty() or not node.isSeq():
            raise CaptureError(f"{self.path}: expected a list `names` of camera names")
        names = []
        for i in range(node.size()):
            item = node.at(i)
            value = item.string() if item.isString() else (str(int(item.real())) if item.isReal() or item.isInt()
                                                           else None)
            if value != "none":  # EasyMocap skips it too
                names.append(safe_name(value, "camera name", f"{self.path}: `names`", CaptureError))
        if not names:
            raise CaptureError(f"{self.path}: `names` lists no camera")
        return names

    def matrix(self, key: str, sizes: tuple[int, ...], optional: bool = False) -> np.ndarray | None:
        node = self.storage.getNode(key)
        if node.empty() or node.isNone():
            if optional:
                return None
            raise CaptureError(f"{self.path}: missing matrix `{key}`")
        if not node.isMap() or node.getNode("rows").empty() or node.getNode("cols").empty():
            raise CaptureError(f"{self.path}: `{key}` is not an OpenCV matrix (!!opencv-matrix with rows, cols, data)")
        declared = int(node.getNode("rows").real()) * int(node.getNode("cols").real())
        if declared not in sizes:
            raise CaptureError(f"{self.path}: `{key}` declares {declared} values, expected "
                               f"{' or '.join(map(str, sizes))}")
        value = node.mat()
        if value is None or value.size not in sizes or not np.all(np.isfinite(value)):
            raise CaptureError(f"{self.path}: `{key}` must hold {' or '.join(map(str, sizes))} finite numbers")
        return value.astype(np.float64).reshape(-1)

    def integer(self, key: str) -> int | None:
        node = self.storage.getNode(key)
        if node.empty() or node.isNone():
            return None
        value = node.real()
        if not (node.isInt() or node.isReal()) or value < 1 or value != round(value) or value > 1e6:
            raise CaptureError(f"{self.path}: `{key}` must be an image size in pixels, found {value}")
        return int(value)


def read_cameras(root: Path, image_size) -> dict[str, RawCamera]:
    """Cameras of intri.yml and extri.yml in the order of intri.yml's `names`; `image_size(camera)` gives
    (width, height) where intri.yml has no `W_<cam>`, `H_<cam>`."""
    intri, extri = _Storage(root / INTRI), _Storage(root / EXTRI)
    cameras = {}
    for name in intri.names():
        K = intri.matrix(f"K_{name}", (9,)).reshape(3, 3)
        dist = intri.matrix(f"dist_{name}", (4, 5, 8, 12, 14), optional=True)
        if dist is None:
            dist = intri.matrix(f"D_{name}", (4, 5, 8, 12, 14), optional=True)
        if dist is None:
            raise CaptureError(f"{intri.path}: camera {name} has neither `dist_{name}` nor `D_{name}` (OpenCV "
                               "distortion; write zeros for none)")
        width, height = intri.integer(f"W_{name}"), intri.integer(f"H_{name}")
        if width is None or height is None:
            width, height = image_size(name)
        rvec = extri.matrix(f"R_{name}", (3,), optional=True)
        rot = extri.matrix(f"Rot_{name}", (9,), optional=True)
        if rvec is None and rot is None:
            raise CaptureError(f"{extri.path}: camera {name} has neither `R_{name}` (Rodrigues) nor `Rot_{name}`")
        R = cv2.Rodrigues(rvec)[0] if rvec is not None else rot.reshape(3, 3)
        if rvec is not None and rot is not None and np.abs(R - rot.reshape(3, 3)).max() > 1e-4:
            raise CaptureError(f"{extri.path}: `R_{name}` (Rodrigues) and `Rot_{name}` are different rotations "
                               f"(by {np.abs(R - rot.reshape(3, 3)).max():.3g}); fix one")
        T = extri.matrix(f"T_{name}", (3,))
        entry = {"K": K.tolist(), "R": R.tolist(), "T": T.tolist(), "imgSize": [width, height],
                 "distCoeff": dist.tolist()}
        cameras[name] = camera_entry(name, entry, intri.path)
    return cameras


def read_fit(path: Path, person: int | None) -> dict[str, np.ndarray]:
    """One frame's fit of one person: {Rh, Th, poses, shapes, expression} as flat float64 arrays."""
    bounded_file(path, "an EasyMocap fit (JSON)", "file not found", MAX_JSON_BYTES, "a frame's fits")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CaptureError(f"{path}: not valid JSON: {err}") from None
    if isinstance(data, dict) and "annots" in data:  # some EasyMocap apps wrap the list
        data = data["annots"]
    if not isinstance(data, list) or not all(isinstance(entry, dict) for entry in data) or not data:
        raise CaptureError(f"{path}: expected a non-empty list of {{id, Rh, Th, poses, shapes, expression}}")
    ids = [entry.get("id", 0) for entry in data]
    if person is None:
        if len(data) > 1:
            raise CaptureError(f"{path}: holds {len(data)} people (ids {ids}); name one with the reader option "
                               "`person` in the dataset YAML")
        entry = data[0]
    else:
        matches = [entry for entry in data if entry.get("id", 0) == person]
        if len(matches) != 1:
            raise CaptureError(f"{path}: {len(matches)} people with id {person}; ids are {ids}")
        entry = matches[0]
    if "handl" in entry or "handr" in entry:
        raise CaptureError(f"{path}: holds 'handl' / 'handr', the hand poses of EasyMocap's newer body models, which "
                           "this reader does not take; export the fits with 'poses' holding the hands (the 87-value "
                           "SMPL-X form, or the full 165)")
    fit = {}
    for key, size in (("Rh", 3), ("Th", 3), ("poses", None), ("shapes", None), ("expression", None)):
        if key not in entry:
            if key == "expression":
                continue
            raise CaptureError(f"{path}: missing '{key}'; found {sorted(entry)}")
        try:
            value = np.asarray(entry[key], dtype=np.float64)
        except (TypeError, ValueError):
            raise CaptureError(f"{path}: '{key}' must be a list of numbers") from None
        if value.ndim == 2 and value.shape[0] == 1:
            value = value[0]
        if value.ndim != 1 or (size is not None and value.size != size) or value.size > 400 or \
                not np.all(np.isfinite(value)):
            raise CaptureError(f"{path}: '{key}' must be {size or 'a row of'} finite numbers (or [[...]]), found "
                               f"shape {value.shape}")
        fit[key] = value
    fit.setdefault("expression", np.zeros(0))
    from pig.body.easymocap import hand_components_of  # torch on reading only: the workflow's DAG imports this module

    try:
        hand_components_of(fit["poses"].size, str(path))  # a length of no SMPL-X form, named with its file
    except ParamsError as err:
        raise CaptureError(str(err)) from None
    return fit


class EasyMocapCapture(FramesCapture):
    """One EasyMocap sequence. body_model: the SMPL-X npz the fit was made with (its hand components turn the
    hand PCA into joint rotations). Options: `masks` (folder), `params` (folder of the fits), `person` (the id to
    read where a frame holds several), `flat_hand_mean` (EasyMocap's `use_flat_mean`; True in its SMPL-X layer)."""

    layout = LAYOUT
    nonzero_masks = True

    def __init__(self, root: str | Path, body_model: str | Path | BodyModel | None = None, masks: str = "mask-schp",
                 params: str = "smplx", person: int | None = None, flat_hand_mean: bool = True):
        self.source = Path(root)
        for option, value in (("masks", masks), ("params", params)):
            relative_folder(value, f"reader option {option}", f"EasyMocap sequence {root}")
        required_files(self.source)
        if body_model is None:
            raise CaptureError(f"{self.source}: EasyMocap fits need the SMPL-X model they were made with "
                               "(`body_model` in the dataset YAML or --body-model)")
        import torch  # on reading only: the workflow's DAG imports this module (for `required_files`) without torch

        from pig.body.model import BodyModel

        model = body_model if isinstance(body_model, BodyModel) else BodyModel.from_file(body_model, torch.float64)
        json_files = _json_files(self.source / params)
        if not json_files:
            raise CaptureError(f"{self.source / params}: no fits %06d.json; expected {LAYOUT}")
        self.frames = sorted(json_files)
        self.params = _convert([read_fit(json_files[f], person) for f in self.frames], model, flat_hand_mean,
                               self.source / params)
        self.cameras = read_cameras(self.source, lambda camera: first_image_size(self.source, camera))
        count = self.frames[-1] + 1
        images, masks_ = {}, {}
        for name, cam in self.cameras.items():
            images[name] = camera_frames(self.source / "images" / name, _FRAME, "%06d.jpg", cam.width, cam.height,
                                         count, f"camera {name}", exact=False)
            masks_[name] = camera_frames(self.source / masks / name, rf"(\d+)(?:_{person or 0})?",
                                         f"%06d.png or %06d_{person or 0}.png", cam.width, cam.height,
                                         count, f"camera {name}'s masks", exact=False)
        self._attach(images, masks_, set(), extra_frames=True)


def first_image_size(root: Path, camera: str) -> tuple[int, int]:
    """(width, height) from the header of a camera's first image, or from its video."""
    folder = root / "images" / camera
    video = video_in_place_of(folder)
    if video is not None:
        return video_size(video)
    files = FrameFiles(folder, _FRAME, "%06d.jpg").files if folder.is_dir() else {}
    if not files:
        raise CaptureError(f"{folder}: no images to take the size of camera {camera} from (intri.yml has no "
                           f"W_{camera}, H_{camera}); expected {LAYOUT}")
    path = files[min(files)]
    with open(path, "rb") as handle:
        size = declared_size(handle.read(1 << 20))
    if size is None:
        raise CaptureError(f"{path}: no image size in its header (intri.yml has no W_{camera}, H_{camera})")
    return size


def geometry(root: str | Path, options: dict) -> tuple[dict[str, tuple[int, int]], list[int]]:
    """(camera -> (width, height), frame ids with a fit) from the calibration and the fits' names alone, for
    `pig doctor`; `options`: the dataset's reader options."""
    root = Path(root)
    cameras = read_cameras(root, lambda camera: first_image_size(root, camera))
    frames = sorted(_json_files(root / options.get("params", "smplx")))
    return {name: (cam.width, cam.height) for name, cam in cameras.items()}, frames


def _json_files(folder: Path) -> dict[int, Path]:
    files: dict[int, Path] = {}
    if not folder.is_dir():
        raise CaptureError(f"{folder}: folder of EasyMocap fits not found; expected {LAYOUT}")
    for path in folder.iterdir():
        if path.suffix == ".json" and re.fullmatch(_FRAME, path.stem):
            frame = int(path.stem)
            if frame in files:
                raise CaptureError(f"{folder}: two fits for frame {frame}: {files[frame].name} and {path.name}")
            files[frame] = path
    return files


def _convert(fits: list[dict], model: BodyModel, flat_hand_mean: bool, folder: Path) -> SmplxParams:
    from pig.body.easymocap import to_standard  # torch on reading only, as above

    for key in ("poses", "shapes", "expression"):
        lengths = sorted({fit[key].size for fit in fits})
        if len(lengths) > 1:
            raise CaptureError(f"{folder}: '{key}' has {lengths} values in different frames; expected one length")
    shapes = np.stack([fit["shapes"] for fit in fits])
    if np.abs(shapes - shapes[0]).max() > 1e-6:
        warnings.warn(f"{folder}: 'shapes' differ between frames (by up to {np.abs(shapes - shapes[0]).max():.3g}); "
                      "using the first frame's for every frame")
    expression = np.stack([fit["expression"] for fit in fits])
    try:
        return to_standard(np.stack([fit["Rh"] for fit in fits]), np.stack([fit["Th"] for fit in fits]),
                           np.stack([fit["poses"] for fit in fits]), shapes[0],
                           expression if expression.size else np.zeros((len(fits), 10)), model, flat_hand_mean,
                           f"{folder}/%06d.json")
    except ParamsError as err:
        raise CaptureError(str(err)) from None
