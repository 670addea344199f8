"""Ground-truth images of the synthetic subject: Embree ray casting of the posed meshes through distorted pixel rays.

Each hit is shaded Lambertian + ambient with an albedo looked up at the hit's canonical position;
independent of the project's Gaussian renderer, so it can serve as ground truth for the paper's loss (Eq. 15).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from pig.data.raw import RawCamera

from .rig import pixel_rays
from .texture import ValueNoise, body_albedo, garment_albedo

LIGHTS = (  # (direction towards the light, strength): a key light above front-left and a weak fill
    (np.array([0.4, 0.8, 0.6]) / np.linalg.norm([0.4, 0.8, 0.6]), 0.75),
    (np.array([-0.5, 0.3, -0.6]) / np.linalg.norm([-0.5, 0.3, -0.6]), 0.3),
)
AMBIENT = 0.3


@dataclass
class SceneAppearance:
    """What does not change between frames: topology, canonical positions and the material parameters."""

    body_faces: np.ndarray  # (F, 3)
    garment_faces: np.ndarray  # (Fg, 3), indices into the garment vertices
    body_canonical: np.ndarray  # (V, 3) rest positions relative to the pelvis joint (texture space)
    garment_canonical: np.ndarray  # (Vg, 3) rest positions relative to the skirt's waist centre
    body_palette: np.ndarray  # (4, 3)
    garment_palette: np.ndarray  # (3, 3)
    background: np.ndarray  # (2, 3): colour at the top and at the bottom of every image
    seed: int

    @property
    def faces(self) -> np.ndarray:
        return np.concatenate([self.body_faces, self.garment_faces + len(self.body_canonical)])


def render_frame(appearance: SceneAppearance, body: np.ndarray, garment: np.ndarray, cameras: list[RawCamera],
                 supersample: int = 1, stats: dict[str, float] | None = None):
    """Yield (camera, rgb (H, W, 3) float in [0, 1], mask (H, W) bool) for each camera, for one posed frame.

    `stats`, if given, accumulates seconds per part (scene: mesh, Embree's BVH and normals; rays, intersect,
    shade, compose) and the views whose rays were computed or found cached (rays_computed, rays_cached)."""
    parts = _Parts(stats)
    vertices = np.concatenate([body, garment])
    mesh = trimesh.Trimesh(vertices, appearance.faces, process=False)
    caster = RayMeshIntersector(mesh)
    caster.intersects_first(np.empty((0, 3)), np.empty((0, 3)))  # builds Embree's BVH now: a part of the scene's time
    normals = _area_weighted_normals(vertices, appearance.faces)
    noise = ValueNoise(appearance.seed)
    parts.lap("scene")
    for camera in cameras:
        origin, directions, computed = _cached_rays(camera, supersample)
        parts.count("rays_computed" if computed else "rays_cached")
        parts.lap("rays")
        shape = directions.shape[:-1]
        directions = directions.reshape(-1, 3)
        colour = np.zeros((len(directions), 3), dtype=np.float32)
        hit = np.zeros(len(directions), dtype=bool)
        for start in range(0, len(directions), CHUNK):  # bounded memory at any resolution
            part = slice(start, start + CHUNK)
            rays = directions[part].astype(np.float64)
            triangle = caster.intersects_first(np.broadcast_to(origin, rays.shape), rays)
            hit[part] = triangle >= 0
            found = triangle >= 0
            parts.lap("intersect")
            colour[part][found] = _shade(appearance, vertices, normals, triangle[found], origin, rays[found], noise)
            parts.lap("shade")
        rows = np.linspace(0, 1, camera.height, dtype=np.float32)[:, None, None, None]
        background = appearance.background[0] * (1 - rows) + appearance.background[1] * rows
        colour = np.where(hit.reshape(shape)[..., None], colour.reshape(shape + (3,)), background)
        coverage = hit.reshape(shape).mean(axis=-1)
        rgb, mask = np.clip(colour.mean(axis=2), 0, 1), coverage >= 0.5
        parts.lap("compose")
        yield camera, rgb, mask
        parts.restart()  # the caller's time with the view is not this function's


class _Parts:
    """Seconds between laps, added to a dict under the part's name (nothing when there is no dict)."""

    def __init__(self, stats: dict[str, float] | None):
        self.stats, self.last = stats, time.perf_counter()

    def lap(self, name: str) -> None:
        if self.stats is not None:
            now = time.perf_counter()
            self.stats[name] = self.stats.get(name, 0.0) + now - self.last
            self.last = now

    def count(self, name: str) -> None:
        if self.stats is not None:
            self.stats[name] = self.stats.get(name, 0) + 1

    def restart(self) -> None:
        self.last = time.perf_counter()


CHUNK = 1 << 19  # rays per Embree call
RAY_CACHE_BYTES = 256 << 20  # cameras are fixed over frames: keep this much of their rays
_RAYS: dict = {}


def _cached_rays(camera: RawCamera, supersample: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """(origin, float32 directions, whether they were computed now rather than found cached)."""
    key = (camera.name, camera.K.tobytes(), camera.R.tobytes(), camera.T.tobytes(), camera.dist.tobytes(),
           camera.width, camera.height, supersample)
    if key in _RAYS:
        return *_RAYS[key], False
    origin, directions = pixel_rays(camera, supersample)
    rays = (origin, directions.astype(np.float32))
    if sum(d.nbytes for _, d in _RAYS.values()) + rays[1].nbytes > RAY_CACHE_BYTES:
        _RAYS.clear()  # work items group cameras to fit (pig.data.synthetic.capture._tasks): older groups are done
    _RAYS[key] = rays
    return *rays, True


def _area_weighted_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals from the sum of adjacent face normals weighted by face area."""
    corners = vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # length = 2 * area
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def _shade(appearance, vertices, normals, triangle, origin, directions, noise) -> np.ndarray:
    corners = vertices[appearance.faces[triangle]]  # (n, 3, 3)
    # Ray-plane intersection gives the exact hit on the triangle Embree reported.
    face_normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    depth = np.einsum("ij,ij->i", face_normal, corners[:, 0] - origin) / np.einsum("ij,ij->i", face_normal, directions)
    points = origin + depth[:, None] * directions
    # Clipped: a ray grazing an edge must not extrapolate normals or texture off the triangle.
    bary = np.clip(trimesh.triangles.points_to_barycentric(corners, points), 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    corner_ids = appearance.faces[triangle]
    normal = np.einsum("ij,ijk->ik", bary, normals[corner_ids])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    # Two-sided: the inside of the skirt is seen through its open hem.
    normal *= -np.sign(np.einsum("ij,ij->i", normal, directions))[:, None]
    light = np.full(len(points), AMBIENT)
    for direction, strength in LIGHTS:
        light += strength * np.maximum(normal @ direction, 0.0)

    num_body = len(appearance.body_canonical)
    on_body = triangle < len(appearance.body_faces)
    albedo = np.empty((len(points), 3))
    body_ids = corner_ids[on_body]
    canonical = np.einsum("ij,ijk->ik", bary[on_body], appearance.body_canonical[body_ids])
    albedo[on_body] = body_albedo(canonical, noise, appearance.body_palette)
    garment_ids = corner_ids[~on_body] - num_body
    gb = bary[~on_body]
    canonical = np.einsum("ij,ijk->ik", gb, appearance.garment_canonical[garment_ids])
    albedo[~on_body] = garment_albedo(canonical, noise, appearance.garment_palette)
    return albedo * light[:, None]
