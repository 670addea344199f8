"""The interface every capture-format reader provides to the preprocess stage.

A reader (THuman4, DNA-Rendering, ...) turns a dataset root into a `RawCapture`: calibrated cameras
in the project's convention (world-to-camera, x_cam = R x_world + T, metres, OpenCV distortion),
per-frame SMPL-X parameters, and lazy image/mask access that names the file on failure.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from pig.body.params import SmplxParams


class CaptureError(ValueError):
    """A capture file is missing, unreadable or inconsistent; the message names the file."""


@dataclass
class RawCamera:
    name: str  # the dataset's own id ("cam00" in THuman4, "0".."59" in DNA-Rendering)
    K: np.ndarray  # (3, 3) pixel intrinsics of the raw (distorted) image
    R: np.ndarray  # (3, 3) world-to-camera rotation
    T: np.ndarray  # (3,) world-to-camera translation
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # OpenCV (k1, k2, p1, p2, k3)
    color_correction: np.ndarray | None = None  # optional per-channel correction (DNA-Rendering)


class RawCapture(Protocol):
    source: Path
    cameras: dict[str, RawCamera]  # in the dataset's order
    frames: list[int]  # frame ids that have body parameters, ascending
    params: SmplxParams  # one row per entry of `frames`, flat-hand-mean convention

    def has_frame(self, camera: str, frame: int) -> bool:
        """False where the dataset lists the image or mask as missing."""

    def read_image(self, camera: str, frame: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB, raw (still distorted); CaptureError naming the file if unreadable."""

    def read_mask(self, camera: str, frame: int) -> np.ndarray:
        """(H, W) uint8 0..255 matte, raw; CaptureError naming the file if unreadable."""
