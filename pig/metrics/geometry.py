"""Geometry error and correspondence drift of an avatar's splats against the true meshes, in millimetres.

- Accuracy per region: each splat centre's distance to the nearest true surface (exact point-to-triangle), the
  splat assigned to the region (body, garment) of that surface; the opacity-weighted mean sum(o d) / sum(o) over
  the region's splats of all measured frames, so that splats that render nothing do not count.
- Completeness per region: from SURFACE_SAMPLES area-uniform samples of the region's true surface to the nearest
  splat centre among the splats of opacity >= MIN_OPACITY; the plain mean over the samples of all measured frames.
- Drift: each splat (anchor) is tied at the first frame to its nearest true surface point (triangle + barycentric
  coordinates), which is followed through the frames on the true mesh of each frame; per frame the mean distance
  between the splats and their tied points, nothing subtracted (the first frame's value is its accuracy, unweighted).
Ground-truth metrics of a synthetic capture (issue 13); no paper equation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pig.metrics.surface import TriangleMesh, surface_positions

REGION_NAMES = ("body", "garment")  # the order of the surfaces everywhere here
SURFACE_SAMPLES = 5000  # samples per true surface and frame: the completeness over 4 frames varies 0.4 % with the seed
MIN_OPACITY = 0.005  # 3DGS prunes splats below this opacity: they render nothing, so they do not complete a surface
MM = 1000.0  # world units are metres


@dataclass
class SurfaceMatch:
    """Nearest true surface point of each of n points: region index (n,), triangle of that region's mesh (n,),
    barycentric coordinates (n, 3) and distance (n,)."""

    region: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    distance: np.ndarray


def match_to_surfaces(points: np.ndarray, surfaces: list[tuple[np.ndarray, np.ndarray]]) -> SurfaceMatch:
    """Nearest point on the union of `surfaces` [(vertices, faces), ...] for each of `points` (n, 3)."""
    counts = [len(faces) for _, faces in surfaces]
    if sum(counts) == 0:
        raise ValueError("match_to_surfaces: the true surfaces have no triangles")
    vertex_offsets = np.cumsum([0] + [len(v) for v, _ in surfaces[:-1]])
    vertices = np.concatenate([np.asarray(v, dtype=np.float64) for v, _ in surfaces])
    faces = np.concatenate([np.asarray(f, dtype=np.int64).reshape(-1, 3) + o
                            for (_, f), o in zip(surfaces, vertex_offsets)])
    nearest = TriangleMesh(vertices, faces).nearest(points)
    face_offsets = np.cumsum([0] + counts)
    region = np.searchsorted(face_offsets, nearest.face, side="right") - 1
    return SurfaceMatch(region, nearest.face - face_offsets[region], nearest.bary, nearest.distance)


def tied_positions(match: SurfaceMatch, surfaces: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Positions (n, 3) of the tied points of `match` on `surfaces` of another frame (same topology)."""
    out = np.empty((len(match.region), 3))
    for index, (vertices, faces) in enumerate(surfaces):
        rows = match.region == index
        out[rows] = surface_positions(vertices, faces, match.face[rows], match.bary[rows])
    return out


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` points (count, 3) uniform over the area of a mesh; (0, 3) when it has no area."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64).reshape(-1, 3)]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    total = areas.sum()
    if not total > 0:
        return np.zeros((0, 3))
    chosen = rng.choice(len(areas), size=count, p=areas / total)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1  # reflect into the triangle: uniform over its area
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    c = corners[chosen]
    return c[:, 0] + u[:, None] * (c[:, 1] - c[:, 0]) + v[:, None] * (c[:, 2] - c[:, 0])


@dataclass
class GeometrySums:
    """Running sums over frames, per region: sum(o d), sum(o) of accuracy; sum(d), count of completeness."""

    weighted_distance: np.ndarray
    weight: np.ndarray
    sample_distance: np.ndarray
    samples: np.ndarray

    @classmethod
    def zeros(cls, regions: int) -> "GeometrySums":
        return cls(*(np.zeros(regions) for _ in range(4)))

    def add_frame(self, match: SurfaceMatch, opacities: np.ndarray, centres: np.ndarray,
                  surfaces: list[tuple[np.ndarray, np.ndarray]], rng: np.random.Generator) -> None:
        """Add one frame: `match` of its splat `centres` (n, 3) with `opacities` (n,) to its `surfaces`."""
        weights = np.asarray(opacities, dtype=np.float64)
        regions = len(self.weight)
        self.weighted_distance += np.bincount(match.region, weights * match.distance, minlength=regions)
        self.weight += np.bincount(match.region, weights, minlength=regions)
        visible = centres[weights >= MIN_OPACITY]
        tree = cKDTree(visible) if len(visible) else None
        for index, (vertices, faces) in enumerate(surfaces):
            samples = sample_surface(vertices, faces, SURFACE_SAMPLES, rng)
            if len(samples) and tree is not None:
                self.sample_distance[index] += tree.query(samples, workers=-1)[0].sum()
                self.samples[index] += len(samples)

    def accuracy(self) -> np.ndarray:
        """Opacity-weighted mean distance per region (metres); NaN for a region no (visible) splat is nearest to."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.weight > 0, self.weighted_distance / self.weight, math.nan)

    def completeness(self) -> np.ndarray:
        """Mean sample-to-splat distance per region (metres); NaN for an empty surface or no visible splat."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.samples > 0, self.sample_distance / self.samples, math.nan)


def measured_rows(frames: int, count: int) -> np.ndarray:
    """Indices of `count` frames evenly spaced over `frames`, the first and the last included (all if fewer)."""
    return np.unique(np.round(np.linspace(0, frames - 1, max(1, min(count, frames)))).astype(int))


def drift_per_frame(centres: np.ndarray, tie: SurfaceMatch, surfaces_of_frames) -> np.ndarray:
    """Mean distance (F,) between the splat `centres` (F, n, 3) of each frame and their tied points (`tie`, made at
    the first frame) on that frame's surfaces; `surfaces_of_frames` yields each frame's surfaces in order."""
    return np.array([np.linalg.norm(centres[t] - tied_positions(tie, surfaces), axis=1).mean()
                     for t, surfaces in enumerate(surfaces_of_frames)])


def ground_truth_geometry(track, truth, geometry_frames: int, seed: int = 0) -> dict[str, float]:
    """The summary's geometry keys (mm) of a `pig.data.ground_truth.SplatTrack` against `TrueMeshes`:
    accuracy_mm_{body,garment} and completeness_mm_{body,garment} over `geometry_frames` frames of the track
    evenly spaced with its first and last (each costs an exact nearest-surface query per splat), drift_mm (mean
    over all the track's frames of the per-frame drift) and drift_mm_last (its last frame)."""
    if geometry_frames < 1:
        raise ValueError(f"evaluate.geometry_frames must be at least 1, found {geometry_frames}")
    truth.require_frames(track.frames, "the render stage's splat track")
    rng = np.random.default_rng(seed)
    sums = GeometrySums.zeros(len(REGION_NAMES))
    tie = None
    for row in measured_rows(len(track.frames), geometry_frames):
        surfaces = truth.surfaces(int(track.frames[row]))
        match = match_to_surfaces(track.centres[row], surfaces)
        if row == 0:
            tie = match
        sums.add_frame(match, track.opacities[row], track.centres[row], surfaces, rng)
    drift = drift_per_frame(track.centres, tie, (truth.surfaces(int(f)) for f in track.frames))
    out = {}
    for index, name in enumerate(REGION_NAMES):
        out[f"accuracy_mm_{name}"] = float(sums.accuracy()[index] * MM)
        out[f"completeness_mm_{name}"] = float(sums.completeness()[index] * MM)
    out.update(drift_mm=float(drift.mean() * MM), drift_mm_last=float(drift[-1] * MM))
    return out
