"""Image regions from the true meshes and PSNR/SSIM restricted to a region.

A pixel's region (background, body, garment) is that of the first true triangle its centre ray meets, cast with
Embree as the synthetic generator's renderer casts its rays (pig.data.synthetic.render), through the pinhole
camera of the preprocessed image; a z-buffer at pixel centres gives the same labels. Only the rays inside the box of
the frame's projected vertices are cast: a ray outside it meets no triangle (each projects inside that box when all
vertices lie in front of the camera), so its label is BACKGROUND without a cast. Ground-truth metrics of a synthetic
capture (issue 13), no paper equation.
"""
from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from concurrent.futures import Future

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
    `rays` (origin, (H, W, 1, 3) directions) may be given from `mesh_caster` and `camera_rays` to reuse them. Only
    the rays of `covered_box` are cast.
    """
    labels = np.full((camera.height, camera.width), BACKGROUND, dtype=np.uint8)
    rows, cols = covered_box(surfaces, camera)
    if rows.start >= rows.stop or cols.start >= cols.stop:
        return labels
    caster = caster if caster is not None else mesh_caster(surfaces)
    origin, directions = rays if rays is not None else camera_rays(camera)
    directions = directions[rows, cols].reshape(-1, 3)
    triangle = np.empty(len(directions), dtype=np.int64)
    for start in range(0, len(directions), CHUNK):
        part = directions[start:start + CHUNK]
        triangle[start:start + CHUNK] = caster.intersects_first(np.broadcast_to(origin, part.shape), part)
    body_faces = len(surfaces[0][1])
    hit = np.where(triangle < 0, BACKGROUND, np.where(triangle < body_faces, BODY, GARMENT))
    labels[rows, cols] = hit.reshape(rows.stop - rows.start, cols.stop - cols.start)
    return labels


BOX_MARGIN = 2  # pixels around the projected vertices' box: far beyond Embree's float32 rounding of a hit's edge
NEAR = 1e-6  # metres: a vertex this close to the camera's plane, or behind it, projects unboundedly


def covered_box(surfaces: list[tuple[np.ndarray, np.ndarray]], camera) -> tuple[slice, slice]:
    """Rows and columns of the pixels whose centre rays can meet `surfaces` (of a pinhole `camera`): the box of the
    projected vertices widened by BOX_MARGIN, within the frame; the whole frame when a vertex lies within NEAR of
    the camera's plane or behind it; empty without vertices."""
    vertices = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 3) for v, _ in surfaces])
    if not len(vertices):
        return slice(0, 0), slice(0, 0)
    local = vertices @ np.asarray(camera.R, dtype=np.float64).T + np.asarray(camera.T, dtype=np.float64)
    if local[:, 2].min() <= NEAR:
        return slice(0, camera.height), slice(0, camera.width)
    projected = local @ np.asarray(camera.K, dtype=np.float64).T
    u, v = projected[:, 0] / projected[:, 2], projected[:, 1] / projected[:, 2]

    def span(low: float, high: float, size: int) -> slice:  # pixel centres at integer coordinates
        first = int(np.clip(math.floor(low) - BOX_MARGIN, 0, size))
        return slice(first, int(np.clip(math.ceil(high) + BOX_MARGIN + 1, first, size)))

    return span(v.min(), v.max(), camera.height), span(u.min(), u.max(), camera.width)


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


class LabelCache:
    """Region labels of views kept by what determines them: a key hashes the frame's true surfaces and the camera
    (K, R, T, size), so another capture, frame or camera never finds them. The least recently used go beyond
    `max_bytes`. Thread-safe; the arrays it returns are read-only."""

    def __init__(self, max_bytes: int):
        self.max_bytes, self.bytes = max_bytes, 0
        self._labels: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def surfaces_key(surfaces: list[tuple[np.ndarray, np.ndarray]]) -> bytes:
        digest = hashlib.sha256()
        for vertices, faces in surfaces:
            for array in (np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)):
                digest.update(repr(array.shape).encode())
                digest.update(np.ascontiguousarray(array).tobytes())
        return digest.digest()

    @staticmethod
    def camera_key(camera) -> bytes:
        digest = hashlib.sha256(f"{camera.width}x{camera.height}".encode())
        for array in (camera.K, camera.R, camera.T):
            digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
        return digest.digest()

    def get(self, key: bytes) -> np.ndarray | None:
        with self._lock:
            labels = self._labels.get(key)
            if labels is not None:
                self._labels.move_to_end(key)
            return labels

    def put(self, key: bytes, labels: np.ndarray) -> None:
        labels = labels.copy()
        labels.flags.writeable = False
        with self._lock:
            if key in self._labels or labels.nbytes > self.max_bytes:
                return
            self._labels[key] = labels
            self.bytes += labels.nbytes
            while self.bytes > self.max_bytes:
                self.bytes -= self._labels.popitem(last=False)[1].nbytes


class RegionLabeller:
    """Region labels of a capture's views from its true meshes (`pig.data.ground_truth.TrueMeshes`); callable from
    several threads at once.

    Keeps one Embree scene per frame asked for (views come camera-major, so every frame recurs) and the pixel
    rays of each camera, each built once however many threads ask; with a `cache` (`LabelCache`), labels found
    there are not cast again (a second evaluation of the same capture in one process casts none).
    """

    def __init__(self, truth, cameras: dict, cache: LabelCache | None = None):
        self.truth, self.cameras, self.cache = truth, cameras, cache
        self._lock = threading.Lock()
        self._surfaces: dict[int, Future] = {}
        self._casters: dict[int, Future] = {}
        self._rays: dict[str, Future] = {}

    def _once(self, store: dict, key, build):
        """`store[key]`, built by the first thread that asks while the others wait for it."""
        with self._lock:
            future = store.get(key)
            owner = future is None
            if owner:
                future = store[key] = Future()
        if owner:
            try:
                future.set_result(build())
            except BaseException as err:
                future.set_exception(err)
        return future.result()

    def _frame(self, frame: int) -> tuple[list, bytes | None]:
        surfaces = self.truth.surfaces(frame)
        return surfaces, LabelCache.surfaces_key(surfaces) if self.cache is not None else None

    @staticmethod
    def _caster(surfaces: list) -> RayMeshIntersector:
        caster = mesh_caster(surfaces)
        # One ray builds and commits the Embree scene here, once, not in threads racing to cast on it first.
        caster.intersects_first(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
        return caster

    def __call__(self, camera: str, frame: int) -> np.ndarray:
        surfaces, surfaces_key = self._once(self._surfaces, frame, lambda: self._frame(frame))
        key = None
        if self.cache is not None:
            key = surfaces_key + LabelCache.camera_key(self.cameras[camera])
            labels = self.cache.get(key)
            if labels is not None:
                return labels
        caster = self._once(self._casters, frame, lambda: self._caster(surfaces))
        rays = self._once(self._rays, camera, lambda: camera_rays(self.cameras[camera]))
        labels = region_labels(surfaces, self.cameras[camera], caster, rays)
        if self.cache is not None:
            self.cache.put(key, labels)
        return labels
