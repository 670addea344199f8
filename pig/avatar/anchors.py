"""Anchors: area-uniform samples on the canonical body surface with fixed attachments, and nested LODs.

Section 3.1 (nested hierarchical anchor representation) and the canonical attachment of Section 3.2:
each anchor keeps a face id, barycentric coordinates and x_init; level l holds the first N_l anchors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Attachment:
    face_ids: np.ndarray  # (N,) int64 triangle of the canonical mesh
    bary: np.ndarray  # (N, 3) barycentric coordinates, rows sum to 1
    x_init: np.ndarray  # (N, 3) canonical surface point
    level_sizes: list[int]  # anchors per level, coarse to fine; the last equals N

    def __len__(self) -> int:
        return self.face_ids.shape[0]


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    corners = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)


def level_sizes(count: int, levels: int) -> list[int]:
    """Nested sizes by halving: level l (0-based, coarse first) holds ceil(N / 2^(L-1-l)) anchors."""
    if levels < 1 or count < 2 ** (levels - 1):
        raise ValueError(f"need levels >= 1 and at least {2 ** max(levels - 1, 0)} anchors for {levels} levels, got {count}")
    return [-(-count // 2 ** (levels - 1 - l)) for l in range(levels)]


def sample_attachment(vertices: np.ndarray, faces: np.ndarray, count: int, levels: int, seed: int) -> Attachment:
    """`count` points area-uniformly on the mesh (faces by area, uniform barycentrics inside).

    The samples are independent and identically distributed, so their order is already a uniform
    random permutation: every prefix is a uniform random subset, and the prefixes of sizes
    `level_sizes` are the nested levels obtained by random halving.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    areas = triangle_areas(vertices, faces)
    if not np.isfinite(areas).all() or areas.sum() <= 0:
        raise ValueError("canonical mesh has no surface area to sample anchors from")
    rng = np.random.default_rng(seed)
    face_ids = rng.choice(len(faces), size=count, p=areas / areas.sum())
    r1, r2 = rng.random(count), rng.random(count)
    # Square-root warp: (1 - sqrt r1, sqrt r1 (1 - r2), sqrt r1 r2) is uniform over the triangle.
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    x_init = (bary[:, :, None] * vertices[faces[face_ids]]).sum(axis=1)
    return Attachment(face_ids=face_ids.astype(np.int64), bary=bary, x_init=x_init, level_sizes=level_sizes(count, levels))
