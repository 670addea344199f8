"""Image regions from the true meshes and PSNR/SSIM restricted to a region.

A pixel's region (background, body, garment) is that of the first true triangle its centre ray meets, cast with
Embree as the synthetic generator's renderer casts its rays (pig.data.synthetic.render), through the pinhole
camera of the preprocessed image; a z-buffer at pixel centres gives the same labels. Ground-truth metrics of a
synthetic capture (issue 13), no paper equation.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from pig.data.raw import RawCamera
from pig.data.synthetic.rig import pixel_rays
from pig.metrics.ssim import RADIUS

BACKGROUND, BODY, GARMENT = 0, 1, 2
REGIONS = {"background": BACKGROUND, "body": BODY, "garment": GARMENT}
CHUNK = 1 << 19  # rays per Embree call: bounded memory at any resolution


def region_labels(surfaces: list[tuple[np.ndarray, np.ndarray]], camera, caster: RayMeshIntersector | None = None,
                  rays: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(H, W) uint8 labels of one view: BACKGROUND where the pixel-centre ray meets nothing, else BODY or GARMENT.

    `surfaces` is [(body vertices, faces), (garment vertices, faces)] of one frame; `camera` has K, R, T (world to
    camera, x_cam = R x + T), width and height and no lens distortion (pig.data.capture.Camera). `caster` and
    `rays` (origin, (H, W, 1, 3) directions) may be given from `mesh_caster` and `camera_rays` to reuse them.
    """
    caster = caster if caster is not None else mesh_caster(surfaces)
    origin, directions = rays if rays is not None else camera_rays(camera)
    directions = directions.reshape(-1, 3)
    triangle = np.empty(len(directions), dtype=np.int64)
    for start in range(0, len(directions), CHUNK):
        part = directions[start:start + CHUNK]
        triangle[start:start + CHUNK] = caster.intersects_first(np.broadcast_to(origin, part.shape), part)
    body_faces = len(surfaces[0][1])
    labels = np.where(triangle < 0, BACKGROUND, np.where(triangle < body_faces, BODY, GARMENT))
    return labels.astype(np.uint8).reshape(camera.height, camera.width)


def mesh_caster(surfaces: list[tuple[np.ndarray, np.ndarray]]) -> RayMeshIntersector:
    """Embree intersector of the body and garment of one frame; body triangles come first."""
    offsets = np.cumsum([0] + [len(v) for v, _ in surfaces[:-1]])
    vertices = np.concatenate([np.asarray(v, dtype=np.float64) for v, _ in surfaces])
    faces = np.concatenate([np.asarray(f, dtype=np.int64).reshape(-1, 3) + o for (_, f), o in zip(surfaces, offsets)])
    return RayMeshIntersector(trimesh.Trimesh(vertices, faces, process=False))


def camera_rays(camera) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit directions (H, W, 1, 3) through the pixel centres of a pinhole camera."""
    return pixel_rays(RawCamera(camera.name, np.asarray(camera.K, float), np.asarray(camera.R, float),
                                np.asarray(camera.T, float), camera.width, camera.height))


def _region_means(values: torch.Tensor, labels: torch.Tensor, regions: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image and region, the mean (B, regions) of `values` (B, H, W) over the pixels of each label in `labels`
    (B, H, W), summed in float64 in one pass, and the pixel counts (B, regions)."""
    index = labels.reshape(labels.shape[0], -1).long()
    sums = values.new_zeros((labels.shape[0], regions), dtype=torch.float64)
    sums.scatter_add_(1, index, values.reshape(index.shape).double())
    counts = torch.zeros_like(sums).scatter_add_(1, index, torch.ones_like(sums[:, :1]).expand(index.shape))
    return sums / counts.clamp_min(1), counts


def region_psnr(x: torch.Tensor, y: torch.Tensor, labels: torch.Tensor, regions: int = len(REGIONS),
                data_range: float = 1.0) -> torch.Tensor:
    """PSNR (B, regions) of images (B, C, H, W) over each region's pixels (all channels) of `labels` (B, H, W)
    (values 0..regions-1); NaN where a region has no pixel, +inf where it is identical."""
    mse, counts = _region_means((x - y).pow(2).mean(1), labels, regions)
    values = 10 * torch.log10(data_range**2 / mse)
    return torch.where(counts > 0, values, torch.full_like(values, math.nan))


def region_ssim(ssim_values: torch.Tensor, labels: torch.Tensor, regions: int = len(REGIONS)) -> torch.Tensor:
    """Mean (B, regions) of an SSIM map (B, C, H-10, W-10) from pig.metrics.ssim.ssim_map over each region's
    pixels of `labels` (B, H, W), channels averaged first. The map covers the interior only (the window's 5-pixel
    border is cropped, as for the full-frame SSIM): region pixels on that border do not count; NaN where none remain."""
    inner = labels[:, RADIUS:labels.shape[1] - RADIUS, RADIUS:labels.shape[2] - RADIUS]
    means, counts = _region_means(ssim_values.mean(1), inner, regions)
    return torch.where(counts > 0, means, torch.full_like(means, math.nan))


class RegionLabeller:
    """Region labels of a capture's views from its true meshes (`pig.data.ground_truth.TrueMeshes`).

    Keeps one Embree scene per frame asked for (views come camera-major, so every frame recurs) and the pixel
    rays of each camera; labels themselves are cheap to recast.
    """

    def __init__(self, truth, cameras: dict):
        self.truth, self.cameras = truth, cameras
        self._casters: dict[int, RayMeshIntersector] = {}
        self._rays: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, camera: str, frame: int) -> np.ndarray:
        surfaces = self.truth.surfaces(frame)
        if frame not in self._casters:
            self._casters[frame] = mesh_caster(surfaces)
        if camera not in self._rays:
            self._rays[camera] = camera_rays(self.cameras[camera])
        return region_labels(surfaces, self.cameras[camera], self._casters[frame], self._rays[camera])
