"""Solvers for (I + lambda L_knn) x = b on anchor tensors (N, C): a reused sparse factorisation and warm-started CG.

The anchor-level system of the KNN preconditioner (Eq. 5); both expose solve(b, slot) and apply(x).

`FactorizedSystem` factorises A once with SuperLU (scipy.sparse.linalg.splu; symmetric mode,
no pivoting off the diagonal, minimum-degree ordering on A + A^T, which suits an SPD matrix) and
reuses it for every solve. It is exact to rounding in float64. SuperLU runs on the CPU: a CUDA or
float32 right-hand side is copied to the CPU in float64, solved, and copied back (one host round
trip per solve; the 100k x 3 solve itself takes about 0.04 s, benchmarks/NOTES.md).

`CGSystem` is Jacobi-preconditioned conjugate gradients in torch on a sparse CSR matrix, on the
right-hand side's device, every column solved at once. Each `slot` (e.g. "forward", "backward")
keeps its last solution as the next warm start, since successive optimisation steps solve nearby
systems. It stops when every column's relative residual |b - A x| / |b| <= tol, or after max_iter
iterations; `last_iterations` and `last_residual` record the latest solve, and reaching the cap
emits a `CGNotConverged` warning naming the residual reached.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import torch


class CGNotConverged(RuntimeWarning):
    """Conjugate gradients stopped at its iteration cap above the requested tolerance."""


def _system_matrix(laplacian: sp.spmatrix, lam: float) -> sp.csr_matrix:
    if not math.isfinite(lam) or lam < 0:
        raise ValueError(f"KNN system: expected a finite lambda >= 0, found {lam}")
    laplacian = sp.csr_matrix(laplacian, dtype=np.float64)
    if laplacian.shape[0] != laplacian.shape[1]:
        raise ValueError(f"KNN system: expected a square Laplacian, found shape {laplacian.shape}")
    return (sp.identity(laplacian.shape[0], format="csr") + lam * laplacian).tocsr()


def _as_columns(b: torch.Tensor, n: int, who: str) -> torch.Tensor:
    if b.shape[0] != n:
        raise ValueError(f"{who}: expected a tensor with {n} rows (one per anchor), found shape {tuple(b.shape)}")
    return b.reshape(n, -1)


class FactorizedSystem:
    """A = I + lambda L, factorised once with SuperLU; `solve` is exact to rounding."""

    def __init__(self, laplacian: sp.spmatrix, lam: float):
        self.matrix = _system_matrix(laplacian, lam)
        self.lam = float(lam)
        self.size = self.matrix.shape[0]
        self._lu = sla.splu(
            self.matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        self._torch_matrix: dict[tuple, torch.Tensor] = {}

    def solve(self, b: torch.Tensor, slot: str | None = None) -> torch.Tensor:
        """x = A^-1 b for b (N, ...), computed on the CPU in float64."""
        columns = _as_columns(b, self.size, "FactorizedSystem.solve")
        rhs = columns.detach().to("cpu", torch.float64).numpy()
        x = self._lu.solve(np.ascontiguousarray(rhs))
        return torch.from_numpy(np.asarray(x).reshape(rhs.shape)).to(device=b.device, dtype=b.dtype).reshape(b.shape)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """A x for x (N, ...) on x's device."""
        return _sparse_apply(self.matrix, self._torch_matrix, x, "FactorizedSystem.apply")


class CGSystem:
    """A = I + lambda L solved by warm-started Jacobi-preconditioned CG (see module docstring)."""

    def __init__(self, laplacian: sp.spmatrix, lam: float, tol: float = 1e-5, max_iter: int = 200):
        if not tol > 0 or max_iter < 1:
            raise ValueError(f"CGSystem: expected tol > 0 and max_iter >= 1, found tol={tol}, max_iter={max_iter}")
        self.matrix = _system_matrix(laplacian, lam)
        self.lam = float(lam)
        self.size = self.matrix.shape[0]
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.last_iterations = 0
        self.last_residual = 0.0
        self._torch_matrix: dict[tuple, torch.Tensor] = {}
        self._inverse_diagonal: dict[tuple, torch.Tensor] = {}
        self._warm: dict[str | None, torch.Tensor] = {}

    def reset(self) -> None:
        """Forget the warm starts (the next solves start from zero)."""
        self._warm.clear()

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """A x for x (N, ...) on x's device."""
        return _sparse_apply(self.matrix, self._torch_matrix, x, "CGSystem.apply")

    def solve(self, b: torch.Tensor, slot: str | None = None) -> torch.Tensor:
        """x ~= A^-1 b for b (N, ...), warm-started from the previous solution of the same `slot`."""
        b_cols = _as_columns(b, self.size, "CGSystem.solve").detach()
        key = (b.device, b.dtype)
        matrix = _torch_csr(self.matrix, self._torch_matrix, key)
        if key not in self._inverse_diagonal:
            self._inverse_diagonal[key] = torch.from_numpy(1.0 / self.matrix.diagonal()).to(device=b.device, dtype=b.dtype)[:, None]
        inv_diag = self._inverse_diagonal[key]

        b_norm = b_cols.norm(dim=0)
        active = b_norm > 0  # a zero column has the exact solution zero
        warm = self._warm.get(slot)
        x = warm.clone() if warm is not None and warm.shape == b_cols.shape and warm.dtype == b.dtype and warm.device == b.device else torch.zeros_like(b_cols)
        x = x * active
        r = b_cols - matrix @ x
        z = inv_diag * r
        p = z.clone()
        rz = (r * z).sum(dim=0)
        safe_norm = torch.where(active, b_norm, torch.ones_like(b_norm))
        iterations = 0
        residual = (r.norm(dim=0) / safe_norm).max()
        while residual.item() > self.tol and iterations < self.max_iter:
            ap = matrix @ p
            pap = (p * ap).sum(dim=0)
            # Columns that already converged exactly have p = 0; keep them fixed instead of dividing 0 by 0.
            alpha = torch.where(pap > 0, rz / torch.where(pap > 0, pap, torch.ones_like(pap)), torch.zeros_like(pap))
            x = x + alpha * p
            r = r - alpha * ap
            z = inv_diag * r
            rz_new = (r * z).sum(dim=0)
            beta = torch.where(rz > 0, rz_new / torch.where(rz > 0, rz, torch.ones_like(rz)), torch.zeros_like(rz))
            p = z + beta * p
            rz = rz_new
            iterations += 1
            residual = (r.norm(dim=0) / safe_norm).max()
        self.last_iterations = iterations
        self.last_residual = float(residual)
        if self.last_residual > self.tol:
            warnings.warn(
                f"CGSystem: stopped at the iteration cap ({self.max_iter}) with relative residual "
                f"{self.last_residual:.3g} > tol {self.tol:.3g} (N={self.size}, lambda={self.lam})",
                CGNotConverged,
                stacklevel=2,
            )
        self._warm[slot] = x
        return x.reshape(b.shape).clone()


def _torch_csr(matrix: sp.csr_matrix, cache: dict, key: tuple) -> torch.Tensor:
    if key not in cache:
        device, dtype = key
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)
            cache[key] = torch.sparse_csr_tensor(
                torch.from_numpy(matrix.indptr.astype(np.int64)),
                torch.from_numpy(matrix.indices.astype(np.int64)),
                torch.from_numpy(matrix.data),
                size=matrix.shape,
                check_invariants=True,
            ).to(device=device, dtype=dtype)
    return cache[key]


def _sparse_apply(matrix: sp.csr_matrix, cache: dict, x: torch.Tensor, who: str) -> torch.Tensor:
    columns = _as_columns(x, matrix.shape[0], who)
    return (_torch_csr(matrix, cache, (x.device, x.dtype)) @ columns).reshape(x.shape)
