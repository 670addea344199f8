"""A ring of calibrated cameras with OpenCV lens distortion, and the exact pixel rays of each camera.

Rays come from undistorting the pixel grid with the camera's own coefficients, so the images the
ray caster renders are distorted exactly as `calibration.json` says (the input of paper Sec. 3).
"""
from __future__ import annotations

import cv2
import numpy as np

from pig.data.raw import RawCamera

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


def look_at(position: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, T) for an OpenCV camera (x right, y down, z forward) in a y-up world."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    return R, -R @ position


def make_ring(count: int, width: int, height: int, centre: np.ndarray, extent: float, rng: np.random.Generator,
              distortion: float = 1.0, distance: float = 3.0) -> list[RawCamera]:
    """`count` cameras on a ring around `centre`, at varied heights, each framing a body `extent` metres tall.

    `distortion` scales the random (k1, k2, p1, p2) drawn per camera; k3 stays 0 as in THuman4.
    """
    cameras = []
    heights = np.array([-0.3, 0.5, 0.1, 0.9, -0.1, 0.3])  # relative to the body centre, cycled
    for i in range(count):
        azimuth = 2 * np.pi * i / count + rng.uniform(-0.15, 0.15)
        radius = distance * rng.uniform(0.92, 1.08)
        position = centre + np.array([radius * np.sin(azimuth), heights[i % len(heights)] + rng.uniform(-0.1, 0.1),
                                      radius * np.cos(azimuth)])
        target = centre + rng.uniform(-0.05, 0.05, size=3)
        R, T = look_at(position, target)
        span = np.linalg.norm(target - position)
        focal = 0.5 * min(width, height) * span / (0.62 * extent)  # the body fills ~80% of the short side
        K = np.array([[focal * rng.uniform(0.99, 1.01), 0.0, width / 2 + rng.uniform(-0.02, 0.02) * width],
                      [0.0, focal, height / 2 + rng.uniform(-0.02, 0.02) * height],
                      [0.0, 0.0, 1.0]])
        k1 = rng.choice([-1.0, 1.0]) * rng.uniform(0.03, 0.08)
        k2 = rng.uniform(-0.04, 0.04)
        p1, p2 = rng.choice([-1.0, 1.0], size=2) * rng.uniform(2e-4, 1e-3, size=2)
        dist = distortion * np.array([k1, k2, p1, p2, 0.0])
        cameras.append(RawCamera(f"cam{i:02d}", K, R, T, width, height, dist))
    return cameras


def _undistort_points(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Iterated undistortion to 1e-12: OpenCV 4 names it undistortPointsIter, OpenCV 5 (the GPU
    machine's build) folded the criteria into undistortPoints."""
    if hasattr(cv2, "undistortPointsIter"):
        return cv2.undistortPointsIter(pixels, K, dist, None, None, UNDISTORT_CRITERIA)
    return cv2.undistortPoints(pixels, K, dist, R=None, P=None, criteria=UNDISTORT_CRITERIA)


def pixel_rays(camera: RawCamera, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit world directions (H, W, s*s, 3) through `s x s` sub-pixel samples.

    Pixel centres are at integer coordinates (OpenCV); undistortion is iterated to 1e-12.
    """
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)  # (H*s, W*s)
    pixels = np.stack([uu, vv], axis=-1).reshape(-1, 1, 2).astype(np.float64)
    normalised = _undistort_points(pixels, camera.K, camera.dist).reshape(-1, 2)
    directions = np.concatenate([normalised, np.ones((len(normalised), 1))], axis=1) @ camera.R  # R^T d per row
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    directions = directions.reshape(camera.height, s, camera.width, s, 3).transpose(0, 2, 1, 3, 4)
    return -camera.R.T @ camera.T, directions.reshape(camera.height, camera.width, s * s, 3)
