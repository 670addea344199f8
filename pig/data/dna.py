"""Reader for DNA-Rendering sequences: a main `.smc` (HDF5) of encoded images and an `_annots.smc`
with calibration, masks and SMPL-X fits, as a `RawCapture` (FORMATS.md, "DNA-Rendering"; input to Sec. 4).

Conventions converted here: camera-to-world `RT` -> world-to-camera (R, T); BGR -> RGB; the fits'
`flat_hand_mean=False` hand poses -> the project's flat-hand-mean convention (adds the body model's
`hands_mean`, so the reader needs the body model the fits were made with: `body_model=`).

Layout choices that no real file has confirmed (UNVERIFIED), and how they are handled:
- group attribute `resolution`: two integers in either order (a third entry 3 is allowed); the order
  is taken from the first decoded image of the group, which must match the pair.
- `Color_Calibration`: a 3x3 matrix (the download page: "double (3,3)", BGR) or 3 per-channel gains
  acting on BGR pixel vectors (`bgr' = M bgr`, as the sister RenBody format documents); exposed as the
  equivalent RGB matrix in `RawCamera.color_correction` and applied by `read_image` only with
  `color_correction=True`. The identity (our writer's value for "no correction") reads as None.
  Other shapes are ignored with a warning unless correction was requested.
- `SMPLx/betas`: (N, 10) in the released files (the official reader counts frames by its rows),
  (1, 10) or (10,) accepted too; all frames use row 0, with a warning when rows differ.
- `SMPLx/scale` is ignored, as in the dataset's official loader; a value other than 1 is warned about.

Reads stay inside the two files and bounded: external links and datasets whose data lives in other files
(external raw storage, virtual datasets) are refused, only the datasets the reader needs are read, and each
only after its declared shape and type fit what the capture expects.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import h5py
import numpy as np

from pig.body.params import ParamsError, SmplxParams, from_dna
from pig.body.skeleton import LEFT_HAND, RIGHT_HAND
from pig.data.images import MAX_PIXELS, decode_image
from pig.data.raw import CaptureError, RawCamera
from pig.data.rectify import check_matte
from pig.inputs import require_regular_file
from pig.names import safe_name

if TYPE_CHECKING:
    from pig.body.model import BodyModel

CAMERA_GROUPS = ("Camera_5mp", "Camera_12mp")  # cams 0..47 and 48..59 in the released data
CALIBRATION = "Camera_Parameter"
MASKS = "Mask"
SMPLX = "SMPLx"
ANNOTS_SUFFIX = "_annots"
SMPLX_KEYS = ("betas", "fullpose", "transl", "expression", "scale")  # the datasets of SMPLx that are read
MAX_FRAMES = 1_000_000  # bound on SMPLx rows when no camera group states num_frame
SMPLX_ROW = 400  # values per frame of an SMPLx dataset: fullpose has 165, betas up to 300
# An encoded image holds at most this many bytes a pixel: 16-bit RGBA PNG stored, plus headers.
ENCODED_BYTES_PER_PIXEL = 8


def locate_smc(root: str | Path, sequence: str | None = None) -> tuple[Path, Path]:
    """Find `<seq>.smc` and its `<seq>_annots.smc` from a file, a folder, or `<folder>/<seq>`.

    Accepted: `root/<seq>.smc` with `root/annotations/<seq>_annots.smc` (or beside it), the official
    download's `root/main/<seq>.smc` + `root/annotations/`, or `root` itself naming the main file.
    """
    root = Path(root)
    if sequence is not None:  # it names the files sought below
        safe_name(sequence, "sequence name", f"DNA-Rendering sequence under {root}", CaptureError)
    if root.suffix == ".smc" and root.is_file():
        main = root
    else:
        folder, seq = (root, sequence) if root.is_dir() or sequence else (root.parent, root.name)
        if seq is None:
            found = sorted(p for d in (folder, folder / "main") for p in d.glob("*.smc")
                           if not p.stem.endswith(ANNOTS_SUFFIX))
            if len(found) != 1:
                raise CaptureError(
                    f"{folder}: expected exactly one DNA-Rendering main file <seq>.smc (here or in main/), "
                    f"found {[str(p) for p in found]}; name the sequence explicitly")
            main = found[0]
        else:
            candidates = [folder / f"{seq}.smc", folder / "main" / f"{seq}.smc"]
            main = next((p for p in candidates if p.is_file()), None)
            if main is None:
                raise CaptureError(
                    f"DNA-Rendering sequence {seq!r} not found: put {folder / (seq + '.smc')} and "
                    f"{folder / 'annotations' / (seq + ANNOTS_SUFFIX + '.smc')} there "
                    f"(looked for {[str(p) for p in candidates]})")
    name = f"{main.stem}{ANNOTS_SUFFIX}.smc"
    candidates = [main.parent / "annotations" / name, main.parent.parent / "annotations" / name, main.parent / name]
    annots = next((p for p in candidates if p.is_file()), None)
    if annots is None:
        raise CaptureError(f"{main}: annotation file not found; expected one of {[str(p) for p in candidates]}")
    return main, annots


def required_files(root: str | Path) -> list[Path]:
    """The two files of the sequence at `root` (workflow inputs); CaptureError saying where to put them."""
    return list(locate_smc(root))


def _where(handle: h5py.File, path: str) -> str:
    return f"{handle.filename}:/{path.strip('/')}"


def _check_links(handle: h5py.File, path: str, depth: int = 0) -> None:
    """CaptureError if any link on `path` leads out of the file (an external link), also through soft links."""
    parts = [p for p in path.split("/") if p]
    for end in range(1, len(parts) + 1):
        prefix = "/".join(parts[:end])
        link = handle.get(prefix, getlink=True)
        if isinstance(link, h5py.ExternalLink):
            raise CaptureError(f"{_where(handle, prefix)}: an external link to {link.filename}:{link.path}; links "
                               "out of the file are not followed (a capture's data lives in its own files)")
        if isinstance(link, h5py.SoftLink):
            if depth > 8:
                raise CaptureError(f"{_where(handle, prefix)}: soft links nested too deep")
            _check_links(handle, link.path, depth + 1)


def _check_storage(handle: h5py.File, path: str, dataset: h5py.Dataset) -> None:
    """CaptureError if the dataset's values live outside the file (external raw storage or a virtual dataset)."""
    if dataset.id.get_create_plist().get_external_count() > 0 or dataset.is_virtual:
        raise CaptureError(f"{_where(handle, path)}: the dataset's values are stored in other files (external "
                           "storage or a virtual dataset); they are not read (a capture's data lives in its own files)")


def _node(handle: h5py.File, path: str, kind: type):
    """The group or dataset at `path`, or a CaptureError naming file and internal path; never through a link
    out of the file, nor a dataset stored in other files."""
    _check_links(handle, path)
    node = handle.get(path)
    if node is None:
        parent = path.rsplit("/", 1)[0] if "/" in path else ""
        keys = sorted(handle[parent].keys()) if parent in handle else []
        shown = keys[:12] + (["..."] if len(keys) > 12 else [])
        raise CaptureError(f"{_where(handle, path)}: missing {kind.__name__.lower()}; found {shown}")
    if not isinstance(node, kind):
        raise CaptureError(f"{_where(handle, path)}: expected an HDF5 {kind.__name__.lower()}")
    if isinstance(node, h5py.Dataset):
        _check_storage(handle, path, node)
    return node


def _read(handle: h5py.File, path: str, max_size: int, expected: str) -> np.ndarray:
    """The numeric dataset at `path`, read only if it declares at most `max_size` elements."""
    dataset = _node(handle, path, h5py.Dataset)
    if dataset.dtype.kind not in "biuf":
        raise CaptureError(f"{_where(handle, path)}: expected {expected} (numbers), found {dataset.dtype} values")
    if dataset.size > max_size:
        raise CaptureError(f"{_where(handle, path)}: declares shape {dataset.shape} ({dataset.size:,} values), more "
                           f"than the {max_size:,} expected ({expected}); not read")
    return np.asarray(dataset[()])


def _attr(handle: h5py.File, path: str, name: str):
    node = _node(handle, path, h5py.Group)
    if name not in node.attrs:
        raise CaptureError(f"{_where(handle, path)}: missing attribute '{name}'; found {sorted(node.attrs)}")
    return node.attrs[name]


def _camera_key(group: h5py.Group, cam: int, padded: bool) -> str:
    """The child name of camera `cam`: `"07"` where the group zero-pads, `"7"` elsewhere (either accepted)."""
    preferred, other = (f"{cam:02d}", str(cam)) if padded else (str(cam), f"{cam:02d}")
    return other if preferred not in group and other in group else preferred


def _decode(handle: h5py.File, path: str, flags: int = cv2.IMREAD_COLOR, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Decode the 1-D uint8 encoded image at `path` (BGR for IMREAD_COLOR) to a uint8 array, declaring at most
    `max_pixels` pixels; the encoded bytes are read only if they could be such an image."""
    dataset = _node(handle, path, h5py.Dataset)
    if dataset.dtype != np.uint8 or dataset.ndim != 1:
        raise CaptureError(f"{_where(handle, path)}: expected encoded image bytes (1-D uint8), "
                           f"found {dataset.dtype} array of shape {dataset.shape}")
    limit = ENCODED_BYTES_PER_PIXEL * max_pixels + 65536
    if dataset.size > limit:
        raise CaptureError(f"{_where(handle, path)}: {dataset.size:,} encoded bytes, more than an image of at most "
                           f"{max_pixels:,} pixels takes ({limit:,}); not read")
    image = decode_image(dataset[()], _where(handle, path), flags, max_pixels)
    if image.dtype != np.uint8:
        raise CaptureError(f"{_where(handle, path)}: expected an 8-bit image, found {image.dtype}")
    return image


def matte(image: np.ndarray) -> np.ndarray:
    """(H, W) matte of a decoded mask: the maximum over its colour channels (alpha ignored), as the dataset's loader."""
    if image.ndim == 2:
        return image
    return np.maximum(np.maximum(image[..., 0], image[..., 1]), image[..., 2])  # ~25x faster than .max(axis=2)


def bgr_matrix_to_rgb(matrix: np.ndarray) -> np.ndarray:
    """The matrix acting on RGB vectors that equals `matrix` acting on BGR vectors (reverse rows and columns)."""
    return np.asarray(matrix)[::-1, ::-1].copy()


def _color_correction(value: np.ndarray, where: str, required: bool) -> np.ndarray | None:
    """The RGB correction matrix stored at `where`; None for the identity (no correction)."""
    value = np.asarray(value, dtype=np.float64)
    finite = np.all(np.isfinite(value))
    if value.shape == (3, 3) and finite:
        matrix = value
    elif value.size == 3 and value.ndim <= 2 and finite:
        matrix = np.diag(value.reshape(3))
    else:
        message = f"{where}: expected a finite 3x3 matrix or 3 per-channel gains, found shape {value.shape}"
        if required:
            raise CaptureError(message)
        warnings.warn(message + "; colour correction ignored", stacklevel=3)
        return None
    return None if np.array_equal(matrix, np.eye(3)) else bgr_matrix_to_rgb(matrix)


def _hands_mean(body_model: str | Path | BodyModel) -> np.ndarray:
    from pig.body.model import BodyModel  # here, not at the top: the workflow imports this reader and needs no torch

    model = body_model if isinstance(body_model, BodyModel) else BodyModel.from_file(body_model)
    return model.hands_mean.detach().cpu().double().numpy()


class DnaCapture:
    """One DNA-Rendering sequence as a `RawCapture`; HDF5 files are opened lazily and kept open.

    root/sequence: see `locate_smc`. body_model: SMPL-X npz path or `BodyModel` whose `hands_mean`
    the fits assume (needed for `params`). color_correction: apply `Color_Calibration` in `read_image`.
    """

    def __init__(self, root: str | Path, sequence: str | None = None, *,
                 body_model: str | Path | BodyModel | None = None, color_correction: bool = False):
        self.main_path, self.annots_path = locate_smc(root, sequence)
        self.source = self.main_path
        self.sequence = self.main_path.stem
        self.apply_color_correction = color_correction
        self._handles: dict[str, h5py.File] = {}
        self._frame_keys: dict[tuple[str, str], set[str]] = {}
        main, annots = self._file("main"), self._file("annots")
        self.actor = {k: _plain(v) for k, v in main.attrs.items()}

        smplx = _node(annots, SMPLX, h5py.Group)
        rows = self._stated_frames()
        arrays = {k: _read(annots, f"{SMPLX}/{k}", max(rows, 1) * SMPLX_ROW, f"at most {SMPLX_ROW} values a frame "
                           f"for {rows} frames") for k in SMPLX_KEYS if k in smplx}
        try:
            self._file_params = from_dna(arrays, _where(annots, SMPLX))
        except ParamsError as err:
            raise CaptureError(str(err)) from None
        if "scale" in arrays and not np.allclose(arrays["scale"], 1.0):
            warnings.warn(f"{_where(annots, SMPLX + '/scale')} = {arrays['scale'].ravel()[:1]} is ignored "
                          "(as in the official DNA-Rendering loader)", stacklevel=2)
        num_frames = self._file_params.num_frames
        self.frames = list(range(num_frames))

        self._group_of: dict[str, str] = {}
        self.cameras: dict[str, RawCamera] = {}
        groups = [g for g in CAMERA_GROUPS if g in main]
        if not groups:
            raise CaptureError(f"{_where(main, '/')}: no camera group; expected {list(CAMERA_GROUPS)}, "
                               f"found {sorted(main.keys())}")
        for group in groups:
            self._check_frame_count(group, num_frames)
            cams = self._camera_ids(group)
            width, height = self._group_size(group, cams[0])
            for cam in cams:
                self._group_of[str(cam)] = group
                self.cameras[str(cam)] = self._camera(cam, width, height)
        self.cameras = dict(sorted(self.cameras.items(), key=lambda item: int(item[0])))
        self._hands_mean = None if body_model is None else _hands_mean(body_model)
        _check_gender(self.actor.get("gender"), body_model, self.main_path)

    @property
    def params(self) -> SmplxParams:
        """Per-frame SMPL-X parameters in the flat-hand-mean convention (needs `body_model`)."""
        if self._hands_mean is None:
            raise CaptureError(
                f"{self.annots_path}: DNA-Rendering SMPL-X fits use flat_hand_mean=False; pass the SMPL-X "
                "model they were fitted with (body_model=..., `body_model:` in config/datasets/dna.yaml) "
                "so its hands_mean can be added")
        pose = self._file_params.full_pose.copy()
        for part in (LEFT_HAND, RIGHT_HAND):
            pose[:, part] += self._hands_mean[part]
        return SmplxParams(pose, self._file_params.betas, self._file_params.expression, self._file_params.transl)

    # -- RawCapture ---------------------------------------------------------------------------

    def has_frame(self, camera: str, frame: int) -> bool:
        group = self._group(camera)
        return (str(frame) in self._keys("main", f"{group}/{camera}/color")
                and str(frame) in self._keys("annots", f"{MASKS}/{self._mask_camera(camera)}/mask"))

    def read_image(self, camera: str, frame: int) -> np.ndarray:
        path = f"{self._group(camera)}/{camera}/color/{frame}"
        image = self._sized(_decode(self._file("main"), path, max_pixels=self._pixels(camera)), camera, "main", path)
        cam = self.cameras[camera]
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)  # ~60x faster than a reversed-view copy at 5 MP
        if self.apply_color_correction and cam.color_correction is not None:
            # Per pixel M @ rgb in float32 (OpenCV's uint8 path is fixed-point, off by up to ~0.7).
            corrected = cv2.transform(rgb.astype(np.float32), cam.color_correction.astype(np.float32))
            rgb = np.clip(np.rint(corrected), 0, 255).astype(np.uint8)
        return rgb

    def read_mask(self, camera: str, frame: int) -> np.ndarray:
        self._group(camera)
        path = f"{MASKS}/{self._mask_camera(camera)}/mask/{frame}"
        # IMREAD_UNCHANGED: a one-channel mask is not expanded to three channels only to be reduced again.
        image = _decode(self._file("annots"), path, cv2.IMREAD_UNCHANGED, self._pixels(camera))
        return check_matte(matte(self._sized(image, camera, "annots", path)), _where(self._file("annots"), path))

    # -- helpers ------------------------------------------------------------------------------

    def close(self) -> None:
        for handle in self._handles.values():
            handle.close()
        self._handles.clear()

    def __enter__(self) -> "DnaCapture":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self):  # HDF5 handles do not pickle; reopen in the receiving process
        state = self.__dict__.copy()
        state["_handles"] = {}
        return state

    def _file(self, which: str) -> h5py.File:
        if which not in self._handles:
            path = self.main_path if which == "main" else self.annots_path
            try:
                require_regular_file(path, CaptureError, "a DNA-Rendering .smc (HDF5) file")
                self._handles[which] = h5py.File(path, "r")
            except OSError as err:
                raise CaptureError(f"{path}: not a readable HDF5 (.smc) file: {err}") from None
        return self._handles[which]

    def _keys(self, which: str, path: str) -> set[str]:
        if (which, path) not in self._frame_keys:
            _check_links(self._file(which), path)
            node = self._file(which).get(path)
            self._frame_keys[(which, path)] = set(node.keys()) if isinstance(node, h5py.Group) else set()
        return self._frame_keys[(which, path)]

    def _group(self, camera: str) -> str:
        if camera not in self._group_of:
            raise CaptureError(f"{self.main_path}: no camera {camera!r}; cameras are {list(self.cameras)}")
        return self._group_of[camera]

    def _mask_camera(self, camera: str) -> str:
        masks = self._file("annots").get(MASKS)
        return _camera_key(masks, int(camera), padded=False) if isinstance(masks, h5py.Group) else camera

    def _pixels(self, camera: str) -> int:
        return self.cameras[camera].width * self.cameras[camera].height

    def _stated_frames(self) -> int:
        """The frame count the first camera group's `num_frame` states (checked against SMPLx later), else
        MAX_FRAMES: the bound on the SMPLx rows read."""
        main = self._file("main")
        for group in CAMERA_GROUPS:
            if group in main and "num_frame" in main[group].attrs:
                count = np.asarray(main[group].attrs["num_frame"]).ravel()
                if count.size and np.issubdtype(count.dtype, np.integer) and 0 < count[0] <= MAX_FRAMES:
                    return int(count[0])
        return MAX_FRAMES

    def _sized(self, image: np.ndarray, camera: str, which: str, path: str) -> np.ndarray:
        cam = self.cameras[camera]
        if image.shape[:2] != (cam.height, cam.width):
            raise CaptureError(f"{_where(self._file(which), path)}: image is {image.shape[1]}x{image.shape[0]} "
                               f"(WxH), camera {camera} expects {cam.width}x{cam.height}")
        return image

    def _check_frame_count(self, group: str, num_frames: int) -> None:
        main = self._file("main")
        count = _attr(main, group, "num_frame")
        _attr(main, group, "num_device")
        if int(np.asarray(count).ravel()[0]) != num_frames:
            raise CaptureError(
                f"{_where(main, group)}: attribute num_frame = {int(np.asarray(count).ravel()[0])} but "
                f"{_where(self._file('annots'), SMPLX + '/fullpose')} has {num_frames} frames")

    def _camera_ids(self, group: str) -> list[int]:
        main = self._file("main")
        keys = list(_node(main, group, h5py.Group).keys())
        bad = [k for k in keys if not k.isdigit()]
        if bad or not keys:
            raise CaptureError(f"{_where(main, group)}: expected camera subgroups named by integers, found {keys}")
        return sorted(int(k) for k in keys)

    def _group_size(self, group: str, first_cam: int) -> tuple[int, int]:
        """(width, height) of the group: `resolution` attribute, ordered by the first decoded image."""
        main = self._file("main")
        resolution = np.asarray(_attr(main, group, "resolution")).ravel()
        if resolution.size == 3 and resolution[2] == 3:
            resolution = resolution[:2]
        if resolution.size != 2 or np.any(resolution <= 0):
            raise CaptureError(f"{_where(main, group)}: attribute resolution = {resolution.tolist()}, "
                               "expected two positive integers (height and width in either order)")
        color = f"{group}/{first_cam}/color"
        frames = sorted(_node(main, color, h5py.Group).keys(), key=lambda k: int(k) if k.isdigit() else -1)
        if not frames:
            raise CaptureError(f"{_where(main, color)}: no frames")
        height, width = _decode(main, f"{color}/{frames[0]}", max_pixels=int(np.prod(resolution))).shape[:2]
        if sorted((height, width)) != sorted(int(r) for r in resolution):
            raise CaptureError(f"{_where(main, f'{color}/{frames[0]}')}: image is {width}x{height} (WxH) but "
                               f"{_where(main, group)} attribute resolution is {resolution.tolist()}")
        return width, height

    def _camera(self, cam: int, width: int, height: int) -> RawCamera:
        annots = self._file("annots")
        calib = _node(annots, CALIBRATION, h5py.Group)
        base = f"{CALIBRATION}/{_camera_key(calib, cam, padded=True)}"
        _node(annots, base, h5py.Group)

        def matrix(name: str, sizes: tuple[int, ...]) -> np.ndarray:
            dataset = _node(annots, f"{base}/{name}", h5py.Dataset)
            if dataset.size not in sizes or dataset.dtype.kind not in "biuf":
                raise CaptureError(f"{_where(annots, f'{base}/{name}')}: expected {' or '.join(map(str, sizes))} "
                                   f"finite numbers, found {dataset.dtype} values of shape {dataset.shape}")
            value = np.asarray(dataset[()], dtype=np.float64)
            if value.size not in sizes or not np.all(np.isfinite(value)):
                raise CaptureError(f"{_where(annots, f'{base}/{name}')}: expected {' or '.join(map(str, sizes))} "
                                   f"finite values, found shape {value.shape}")
            return value.reshape(-1)

        K = matrix("K", (9,)).reshape(3, 3)
        dist = matrix("D", (4, 5, 8, 12, 14))
        cam_to_world = matrix("RT", (16,)).reshape(4, 4)
        rotation = cam_to_world[:3, :3]
        if (not np.allclose(cam_to_world[3], [0, 0, 0, 1], atol=1e-6)
                or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) <= 0):
            raise CaptureError(f"{_where(annots, base + '/RT')}: expected a rigid 4x4 camera-to-world transform")
        world_to_cam = np.linalg.inv(cam_to_world)
        correction = None
        if "Color_Calibration" in annots[base]:
            correction = _color_correction(_read(annots, f"{base}/Color_Calibration", 9, "a 3x3 matrix or 3 gains"),
                                           _where(annots, base + "/Color_Calibration"), self.apply_color_correction)
        elif self.apply_color_correction:
            raise CaptureError(f"{_where(annots, base)}: color_correction requested but no Color_Calibration")
        return RawCamera(name=str(cam), K=K, R=world_to_cam[:3, :3], T=world_to_cam[:3, 3], width=width,
                         height=height, dist=dist, color_correction=correction)


def model_gender(body_model) -> str | None:
    """The gender a model file's name states ("female" for SMPLX_FEMALE.npz), else None."""
    if not isinstance(body_model, (str, Path)):
        return None
    named = [t for t in re.split(r"[^a-z]+", Path(body_model).stem.lower()) if t in ("male", "female", "neutral")]
    return named[0] if named else None


def _check_gender(gender, body_model, where: Path) -> None:
    """Warn when the model file's name names another gender than the actor's (fits use gendered models)."""
    named = model_gender(body_model)
    if isinstance(gender, str) and named and gender.lower() in ("male", "female") and named != gender.lower():
        warnings.warn(f"{where}: the actor's gender is {gender!r} but the body model is {body_model}; the official "
                      f"loader fits with SMPLX_{gender.upper()}", stacklevel=3)


def _plain(value):
    """HDF5 attribute -> plain Python value (bytes decoded, 1-element arrays unwrapped)."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(()).item()
    if isinstance(value, np.generic):
        value = value.item()
    return value.decode() if isinstance(value, bytes) else value
