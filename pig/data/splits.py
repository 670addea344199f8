"""Evaluation protocol splits: train / novel-view / novel-pose camera and frame lists of one subject.

Configured by the dataset YAML's `split:` section (FORMATS.md protocols; the paper's Section "Datasets");
no paper equation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

from pig.data.raw import CaptureError

SPLITS = ("train", "novel_view", "novel_pose")


@dataclass
class SplitConfig:
    # Cameras held out for novel view; None: `novel_view_count` cameras evenly spaced over the camera order.
    novel_view_cameras: list[str] | None = None
    novel_view_count: int = 2
    # Subject -> cameras left out of training only (none in the paper's protocols; see config/datasets/thuman4.yaml).
    drop_train_cameras: dict[str, list[str]] = field(default_factory=dict)
    # Inclusive [first, last] frame ids; None: all frames before the novel-pose tail.
    train_frames: list[int] | None = None
    # Inclusive [first, last] frame ids; None: the last `novel_pose_fraction` of the frames.
    novel_pose_frames: list[int] | None = None
    novel_pose_fraction: float = 0.25
    # Cameras rendered for novel pose; None: all cameras.
    novel_pose_cameras: list[str] | None = None


def make_split(cameras: list[str], frames: list[int], cfg: SplitConfig, subject: str,
               where: str = "split") -> dict[str, dict[str, list]]:
    """{"train"|"novel_view"|"novel_pose": {"cameras": [...], "frames": [...]}} in capture order.

    Frame ranges are clipped to the frames the capture has; an empty split, overlapping train and
    novel-pose frames, or a camera id not in `cameras` is an error naming `where`.
    """
    def known(ids: list[str], key: str) -> list[str]:
        unknown = [c for c in ids if c not in cameras]
        if unknown:
            raise CaptureError(f"{where}: '{key}' names camera(s) {unknown} that are not in the calibration; "
                               f"cameras are {cameras}")
        return [c for c in cameras if c in ids]

    def in_range(bounds: list[int], key: str) -> list[int]:
        if len(bounds) != 2 or bounds[0] > bounds[1]:
            raise CaptureError(f"{where}: '{key}' must be [first, last] frame ids, found {bounds}")
        chosen = [f for f in frames if bounds[0] <= f <= bounds[1]]
        if not chosen:
            raise CaptureError(f"{where}: '{key}' {bounds} contains none of the capture's frames "
                               f"({frames[0]}..{frames[-1]})" if frames else f"{where}: the capture has no frames")
        return chosen

    if cfg.novel_view_cameras is not None:
        novel_view = known(cfg.novel_view_cameras, "novel_view_cameras")
    else:
        if not 0 <= cfg.novel_view_count < len(cameras):
            raise CaptureError(f"{where}: 'novel_view_count' {cfg.novel_view_count} must leave at least one of the "
                               f"{len(cameras)} cameras for training")
        step = len(cameras) / max(cfg.novel_view_count, 1)
        novel_view = [cameras[int((i + 0.5) * step)] for i in range(cfg.novel_view_count)]
    dropped = known(cfg.drop_train_cameras.get(subject, []), f"drop_train_cameras.{subject}")
    train_cameras = [c for c in cameras if c not in novel_view and c not in dropped]

    if cfg.novel_pose_frames is not None:
        novel_pose_frames = in_range(cfg.novel_pose_frames, "novel_pose_frames")
    else:
        if not 0 <= cfg.novel_pose_fraction < 1:
            raise CaptureError(f"{where}: 'novel_pose_fraction' must be in [0, 1), found {cfg.novel_pose_fraction}")
        tail = math.ceil(len(frames) * cfg.novel_pose_fraction)
        novel_pose_frames = frames[len(frames) - tail:] if tail else []
    if cfg.train_frames is not None:
        train_frames = in_range(cfg.train_frames, "train_frames")
    else:
        train_frames = [f for f in frames if f not in set(novel_pose_frames)]
    overlap = sorted(set(train_frames) & set(novel_pose_frames))
    if overlap:
        raise CaptureError(f"{where}: train and novel-pose frames overlap (first: {overlap[:5]})")
    novel_pose_cameras = cameras if cfg.novel_pose_cameras is None else known(cfg.novel_pose_cameras,
                                                                              "novel_pose_cameras")
    split = {
        "train": {"cameras": train_cameras, "frames": train_frames},
        "novel_view": {"cameras": novel_view, "frames": train_frames},
        "novel_pose": {"cameras": novel_pose_cameras, "frames": novel_pose_frames},
    }
    # Each split's settings, named in the error when it comes out empty.
    settings = {"train": ("train_frames", "novel_pose_frames", "novel_pose_fraction", "drop_train_cameras",
                          "novel_view_cameras", "novel_view_count"),
                "novel_view": ("novel_view_cameras", "novel_view_count"),
                "novel_pose": ("novel_pose_frames", "novel_pose_fraction", "novel_pose_cameras")}
    for name in SPLITS:
        part = split[name]
        if not (part["cameras"] and part["frames"]):
            given = ", ".join(f"{key}: {getattr(cfg, key)!r}" for key in settings[name])
            raise CaptureError(
                f"{where}: the {name} split is empty ({len(part['cameras'])} cameras, {len(part['frames'])} frames; "
                f"{given}); train, novel_view and novel_pose each need at least one camera and frame; the capture "
                f"has cameras {brief(cameras)} and frames {brief(frames)}")
    return split


def require_views(split: dict[str, dict[str, list]], has_view: Callable[[str, int], bool], where: str,
                  source) -> None:
    """CaptureError naming `where` and the capture `source` if a split has no (camera, frame) with an image."""
    for name in SPLITS:
        part = split[name]
        if not any(has_view(c, f) for c in part["cameras"] for f in part["frames"]):
            raise CaptureError(f"{where}: none of the {name} split's images exist in {source} (cameras "
                               f"{brief(part['cameras'])}, frames {brief(part['frames'])}: all absent or listed as "
                               "missing)")


def brief(ids: list) -> str:
    """A list of ids for a message: in full when short, else its ends and its length."""
    if len(ids) <= 8:
        return str(list(ids))
    return f"[{ids[0]!r}, {ids[1]!r}, ..., {ids[-1]!r}] ({len(ids)})"
