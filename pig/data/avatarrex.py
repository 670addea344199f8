"""Reader for an AvatarReX subject folder (`calibration_full.json`, a folder per camera serial, `smpl_params.npz`) as
a `RawCapture` (FORMATS.md, "AvatarReX"; data preparation, no paper equation).

As AnimatableGaussians reads it (lizhe00/AnimatableGaussians `dataset/dataset_mv_rgb.py`, `MvRgbDatasetAvatarReX`,
lines 404-437): `calibration_full.json` keyed by camera serial with THuman4's `K`, `R`, `T` (world to camera, used as
given, lines 411-415) and `imgSize` [w, h] (lines 416-417); frames `<serial>/%08d.jpg`, alpha mattes
`<serial>/mask/pha/%08d.jpg` (lines 435-436), foreground above 128 (line 271); an optional `missing_img_files.txt`
(lines 419-431); `smpl_params.npz` with THuman4's keys, read with `use_pca=False`, `flat_hand_mean=True` (line 42).
`distCoeff` is used where the file has it, else zero.
"""
from __future__ import annotations

from pathlib import Path

from pig.body.params import SmplxParams
from pig.data.actorshq import frame_count
from pig.data.frame_sources import FramesCapture, camera_frames, read_missing_list
from pig.data.raw import CaptureError
from pig.data.thuman4 import read_calibration, read_params

CALIBRATION = "calibration_full.json"
PARAMS = "smpl_params.npz"
MISSING = "missing_img_files.txt"
LAYOUT = ("calibration_full.json, <serial>/%08d.jpg, <serial>/mask/pha/%08d.jpg, smpl_params.npz, optionally "
          "missing_img_files.txt")


def required_files(root: str | Path) -> list[Path]:
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"AvatarReX subject folder {root} not found: put the subject there with {LAYOUT}")
    missing = [str(root / name) for name in (CALIBRATION, PARAMS) if not (root / name).exists()]
    if missing:
        raise CaptureError(f"AvatarReX subject folder {root} is incomplete: missing {missing}; expected {LAYOUT}")
    return [root / CALIBRATION, root / PARAMS]


def geometry(root: str | Path, options: dict) -> tuple[dict[str, tuple[int, int]], list[int]]:
    """(camera -> (width, height), frame ids) from calibration_full.json and the parameters' row count, for
    `pig doctor`."""
    cameras = read_calibration(Path(root) / CALIBRATION, dist_optional=True)
    return ({name: (cam.width, cam.height) for name, cam in cameras.items()},
            list(range(frame_count(Path(root) / PARAMS))))


class AvatarReXCapture(FramesCapture):
    """One AvatarReX subject (e.g. `avatarrex_zzr`)."""

    layout = LAYOUT

    def __init__(self, root: str | Path):
        self.source = Path(root)
        required_files(self.source)
        self.cameras = read_calibration(self.source / CALIBRATION, dist_optional=True)
        self.params: SmplxParams = read_params(self.source / PARAMS)
        self.frames = list(range(self.params.num_frames))
        count = len(self.frames)
        images, masks = {}, {}
        for name, cam in self.cameras.items():
            images[name] = camera_frames(self.source / name, r"(\d+)", "%08d.jpg", cam.width, cam.height, count,
                                         f"camera {name}")
            masks[name] = camera_frames(self.source / name / "mask" / "pha", r"(\d+)", "%08d.jpg", cam.width,
                                        cam.height, count, f"camera {name}'s masks")
        self._attach(images, masks, read_missing_list(self.source / MISSING, self.cameras))
