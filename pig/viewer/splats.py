"""The avatar's splats in the form viser draws in the browser, and capture cameras as viser camera poses.

Viser's Gaussian splats take centres, 3D covariances R diag(s)^2 R^T, an RGB colour and an opacity per splat;
the colour is the view-independent part of the avatar's SH colour (the DC term, max(C0 sh_0 + 0.5, 0), as the
renderer offsets it), since the browser draws no spherical harmonics. The server-rendered path keeps all of them.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from pig.body.rotation import quaternion_to_matrix

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi)), the degree-0 spherical harmonic


@torch.no_grad()
def browser_splats(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                   sh: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(centres (n, 3), covariances (n, 3, 3), rgb (n, 3) in [0, 1], opacities (n, 1)) float32 numpy arrays of
    splats in the renderer's conventions (quats wxyz, normalised here; linear scales; sh (n, K, 3))."""
    rotation = quaternion_to_matrix(quats)  # normalises
    scaled = rotation * scales[:, None, :]
    covariances = scaled @ scaled.transpose(-1, -2)
    rgb = (SH_C0 * sh[:, 0] + 0.5).clamp(0.0, 1.0)
    return tuple(np.ascontiguousarray(t.detach().float().cpu().numpy())
                 for t in (means, covariances, rgb, opacities.reshape(-1, 1)))


def camera_pose(viewmat: np.ndarray, K: np.ndarray, height: int, distance: float) -> dict[str, np.ndarray | float]:
    """A pinhole camera (world-to-camera `viewmat` (4, 4), OpenCV axes; intrinsics `K`; image `height`) as
    viser's camera state: position, look_at (`distance` metres ahead, the orbit's pivot), up_direction (the
    image's -y in the world) and the vertical field of view in radians. The principal point is not kept: the
    browser's camera looks through the image centre."""
    rotation = np.asarray(viewmat, dtype=np.float64)[:3, :3]
    centre = -rotation.T @ np.asarray(viewmat, dtype=np.float64)[:3, 3]
    return {"position": centre, "look_at": centre + distance * rotation[2], "up_direction": -rotation[1],
            "fov": 2.0 * math.atan(0.5 * height / float(K[1][1]))}
