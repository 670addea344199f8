"""Symmetrised k-nearest-neighbour graph on canonical anchors and its graph Laplacian L_knn.

The fixed coupling graph of the anchor preconditioner (Eq. 5), built once on the initial anchors.

Edges have unit weight (no distance weighting), so duplicate points are simply neighbours; the graph
is the union of each point's k nearest others (i ~ j if j is among i's k nearest or i among j's).
k is capped at N - 1; a single point, or k = 0, gives the empty graph (L = 0). Disconnected parts
are allowed: I + lambda L stays symmetric positive definite for any lambda >= 0.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


def knn_adjacency(points: np.ndarray, k: int) -> sp.csr_matrix:
    """Symmetric 0/1 adjacency (N, N) of the k-nearest-neighbour graph of `points` (N, D)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or not np.isfinite(points).all():
        raise ValueError(f"knn_adjacency: expected finite points of shape (N, D), found shape {points.shape}")
    if k < 0:
        raise ValueError(f"knn_adjacency: expected k >= 0, found {k}")
    n = points.shape[0]
    k_eff = min(k, n - 1)
    if k_eff <= 0:
        return sp.csr_matrix((n, n), dtype=np.float64)
    _, idx = cKDTree(points).query(points, k=k_eff + 1)
    # Drop each point itself from its own list; among tied duplicates the tree may not list it
    # first (or at all), in which case the farthest candidate goes instead.
    own = idx == np.arange(n)[:, None]
    own[~own.any(axis=1), -1] = True
    neighbours = idx[~own].reshape(n, k_eff)
    rows = np.repeat(np.arange(n), k_eff)
    directed = sp.csr_matrix((np.ones(n * k_eff), (rows, neighbours.ravel())), shape=(n, n))
    sym = directed.maximum(directed.T).tocsr()
    sym.data[:] = 1.0
    return sym


def graph_laplacian(adjacency: sp.spmatrix) -> sp.csr_matrix:
    """L = D - W for a symmetric weight matrix W."""
    adjacency = sp.csr_matrix(adjacency, dtype=np.float64)
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    return (sp.diags(degree) - adjacency).tocsr()


def knn_laplacian(points: np.ndarray, k: int) -> sp.csr_matrix:
    """Laplacian of the symmetrised KNN graph of `points` (N, D)."""
    return graph_laplacian(knn_adjacency(points, k))
