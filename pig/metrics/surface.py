"""Exact nearest points on triangle meshes: the closest point of a triangle (as barycentric coordinates) and the
nearest triangle of a mesh for many query points, found through a KD-tree of triangle centroids with an exact bound.

Serves the ground-truth metrics (geometry error and correspondence drift, pig/metrics/geometry.py); no paper equation.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

PAIR_BUDGET = 1 << 21  # (point, triangle) pairs held at once: memory stays bounded for far-off points


def closest_on_triangles(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric coordinates (..., 3) of the point of each triangle (..., 3, 3) closest to the paired point (..., 3),
    and its distance (...,); float64.

    The closest point is the nearest of four candidates: the projection onto the plane when it falls inside the
    triangle, and the closest point of each edge segment. Zero-area triangles (repeated or collinear corners) have
    no plane candidate and reduce to their edges, so no division by a vanishing area happens. The candidates are
    compared by squared distances from six dot products per pair; the chosen point's distance is computed directly.
    """
    p = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.float64)
    a = tri[..., 0, :]
    e1, e2 = tri[..., 1, :] - a, tri[..., 2, :] - a
    bary = _closest(p - a, e1, e2, *_edge_products(e1, e2))
    return bary, _distance(p - a, e1, e2, bary)


def _distance(ap: np.ndarray, e1: np.ndarray, e2: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """|p - q| for q at `bary` of the triangle (a, a + e1, a + e2), from the offsets: exact to rounding, where the
    squared-distance expansion that chose q loses digits (its error is ~1e-9 of the triangle's size)."""
    return np.linalg.norm(ap - bary[..., 1:2] * e1 - bary[..., 2:3] * e2, axis=-1)


def _edge_products(e1: np.ndarray, e2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return tuple(np.einsum("...k,...k->...", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))


def _closest(ap, e1, e2, d11, d12, d22) -> np.ndarray:
    """Barycentric coordinates of `closest_on_triangles` from the offsets `ap` = p - a and the edges e1 = b - a,
    e2 = c - a with their products."""
    pp = np.einsum("...k,...k->...", ap, ap)
    p1, p2 = np.einsum("...k,...k->...", ap, e1), np.einsum("...k,...k->...", ap, e2)
    shape = np.broadcast_shapes(pp.shape, d11.shape)
    candidates = np.empty((4,) + shape)  # squared distances: edges ab, bc, ca, then the plane
    params = np.empty((4,) + shape)  # t along the edge; for the plane, unused

    def segment(offset2, dot, length2):
        t = np.clip(dot / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        t = np.where(length2 > 0, t, 0.0)
        return offset2 - 2 * t * dot + t * t * length2, t

    candidates[0], params[0] = segment(pp, p1, d11)  # a + t e1
    # From b along c - b: (p - b).(e2 - e1) and |e2 - e1|^2 from the same products.
    candidates[1], params[1] = segment(pp - 2 * p1 + d11, p2 - p1 - d12 + d11, d11 - 2 * d12 + d22)
    candidates[2], params[2] = segment(pp, p2, d22)  # a + t e2, i.e. the edge c-a walked from a
    gram = d11 * d22 - d12 * d12  # = |e1 x e2|^2
    # Relative test: a sliver whose area is at rounding level of its edges is treated as degenerate.
    flat = gram > 1e-12 * d11 * d22
    safe = np.where(flat, gram, 1.0)
    v = (d22 * p1 - d12 * p2) / safe
    w = (d11 * p2 - d12 * p1) / safe
    inside = flat & (v >= 0) & (w >= 0) & (v + w <= 1)
    candidates[3] = np.where(inside, pp - v * p1 - w * p2, np.inf)  # orthogonal residual: |ap|^2 - ap.q
    pick = candidates.argmin(axis=0)
    t = np.take_along_axis(params, pick[None], axis=0)[0]
    bary = np.zeros(shape + (3,))
    for edge, (i, j) in enumerate(((0, 1), (1, 2), (0, 2))):
        on = pick == edge
        bary[..., i] = np.where(on, 1 - t, bary[..., i])
        bary[..., j] = np.where(on, t, bary[..., j])
    on = pick == 3
    bary[on] = np.stack([1 - v - w, v, w], axis=-1)[on]
    return bary


@dataclass
class SurfacePoints:
    """Nearest points of query points on a mesh: triangle ids (n,), barycentric coordinates (n, 3), distances (n,)."""

    face: np.ndarray
    bary: np.ndarray
    distance: np.ndarray


class TriangleMesh:
    """A triangle mesh prepared for nearest-point queries: per-triangle corner, edges and their products (float64),
    and a KD-tree of the centroids."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        if len(self.faces) == 0:
            raise ValueError("TriangleMesh: the mesh has no triangles")
        corners = self.vertices[self.faces]  # (F, 3, 3)
        self.a = corners[:, 0]
        self.e1, self.e2 = corners[:, 1] - self.a, corners[:, 2] - self.a
        self.products = _edge_products(self.e1, self.e2)
        centroids = corners.mean(axis=1)
        # Every point of triangle j lies within radius[j] <= reach of its centroid: the bounds that make the search
        # exact (a triangle is at least |p - centroid| - radius away from p).
        self.radius = np.linalg.norm(corners - centroids[:, None], axis=-1).max(axis=1)
        self.reach = float(self.radius.max())
        self.tree = cKDTree(centroids)

    def _closest(self, points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`closest_on_triangles` of points (..., 3) and the mesh's triangles `faces` (...)."""
        ap, e1, e2 = points - self.a[faces], self.e1[faces], self.e2[faces]
        bary = _closest(ap, e1, e2, *(d[faces] for d in self.products))
        return bary, _distance(ap, e1, e2, bary)

    def nearest(self, points: np.ndarray) -> SurfacePoints:
        """Exact nearest surface point of each of `points` (n, 3).

        The triangle of nearest centroid gives an upper bound u of the distance. Any triangle j nearer than u has
        |p - centroid_j| - radius_j < u, so its centroid lies within u + reach: those triangles whose own bound beats
        u are the candidates, all examined.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        _, first = self.tree.query(points, workers=-1)  # every core: each point's answer is its own
        bary, dist = self._closest(points, first)
        face = first.astype(np.int64)
        radius = dist + self.reach
        sizes = self.tree.query_ball_point(points, radius, return_length=True, workers=-1)
        # Groups of at most PAIR_BUDGET candidate pairs: a far-off point's ball may hold the whole mesh.
        group = np.cumsum(sizes) // PAIR_BUDGET
        for g in np.unique(group):
            chunk = np.flatnonzero(group == g)
            balls = self.tree.query_ball_point(points[chunk], radius[chunk], workers=-1)  # each ball sorted
            owner = np.repeat(chunk, [len(ball) for ball in balls])
            candidate = np.fromiter(itertools.chain.from_iterable(balls), dtype=np.int64, count=len(owner))
            hopeful = (np.linalg.norm(points[owner] - self.tree.data[candidate], axis=1) - self.radius[candidate]
                       < dist[owner]) & (candidate != face[owner])
            owner, candidate = owner[hopeful], candidate[hopeful]
            if not len(owner):
                continue
            pair_bary, pair_dist = self._closest(points[owner], candidate)
            # Owners come in ascending runs: the least distance of each run, then its first pair reaching it.
            new_run = np.r_[True, owner[1:] != owner[:-1]]
            run = np.cumsum(new_run) - 1
            least = np.minimum.reduceat(pair_dist, np.flatnonzero(new_run))
            at_least = np.flatnonzero(pair_dist == least[run])
            first_pair = at_least[np.r_[True, run[at_least][1:] != run[at_least][:-1]]]
            better = first_pair[pair_dist[first_pair] < dist[owner[first_pair]]]
            target = owner[better]
            face[target], bary[target], dist[target] = candidate[better], pair_bary[better], pair_dist[better]
        return SurfacePoints(face, bary, dist)


def surface_positions(vertices: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Points (n, 3) at barycentric coordinates `bary` (n, 3) of triangles `face` (n,) of a mesh (any frame of it)."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)[face]]
    return np.einsum("nk,nkd->nd", bary, corners)
