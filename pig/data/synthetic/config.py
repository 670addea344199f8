"""The `synthetic` section of a compute preset: what the synthetic capture generator (pig.data.synthetic.capture) makes.

Apart from the generator, which needs torch, so that the workflow reads the section when it builds its DAG.
"""
from __future__ import annotations

from dataclasses import dataclass


class SyntheticError(ValueError):
    """The synthetic capture cannot be generated as configured."""


@dataclass
class SyntheticConfig:
    """Preset section `synthetic`."""

    cameras: int = 12
    frames: int = 24
    width: int = 256
    height: int = 256
    seed: int = 0
    duration_s: float = 4.0  # the frames sample this much motion, whatever their number
    supersample: int = 1  # s x s rays per pixel (anti-aliasing)
    distortion: float = 1.0  # scale of the random lens distortion; 0 gives pinhole cameras
    camera_distance: float = 3.0  # metres from the subject
    jpeg_quality: int = 95
    workers: int = 2  # processes rendering frames; 1 renders in this process
    body_model: str | None = None  # an SMPL-X model npz; None uses the procedural stand-in

    def __post_init__(self):
        for name in ("cameras", "frames", "width", "height", "supersample", "workers"):
            if getattr(self, name) < 1:
                raise SyntheticError(f"synthetic.{name} must be at least 1, found {getattr(self, name)}")
        if self.duration_s <= 0 or self.camera_distance <= 0 or self.distortion < 0:
            raise SyntheticError("synthetic.duration_s and camera_distance must be positive, distortion >= 0")
        if not 1 <= self.jpeg_quality <= 100:
            raise SyntheticError(f"synthetic.jpeg_quality must be in 1..100, found {self.jpeg_quality}")
