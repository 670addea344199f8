"""Solvers for (I + lambda L_knn) x = b on anchor tensors (N, C): a reused sparse factorisation and warm-started CG.

The anchor-level system of the KNN preconditioner (Eq. 5); both expose solve(b, slot) and apply(x).

Both compute in float64 whatever the tensors' dtype, and return the right-hand side's dtype. A float32
residual cannot resolve this system at large lambda: A x = x + lambda L x is a small difference of terms
of size lambda |L| |x|, and a float32 1 + lambda d_i loses the identity. (Float32 CG on 100k anchors
stopped as converged 7e-4 |b| off at lambda = 1e6, tol 1e-5, and at lambda = 1e8 ran to its cap 2e4 |b|
off, neither with a warning.) `apply` is matrix-free, x + lambda (L x) with the sparse Laplacian L, so
the identity is never rounded into lambda L's diagonal. Every eigenvalue of A is at least 1, so the
error of any x is bounded by its residual: |x - A^-1 b| <= |b - A x|.

`FactorizedSystem` factorises A once with SuperLU (scipy.sparse.linalg.splu; symmetric mode,
no pivoting off the diagonal, minimum-degree ordering on A + A^T, which suits an SPD matrix) and
reuses it for every solve; its error against a dense float64 solve is about 1e-16 lambda |b|, below
1e-7 |b| up to lambda = 1e8 (tests/test_knn_precond.py). SuperLU runs on the CPU: a CUDA or float32
right-hand side is copied to the CPU in float64, solved, and copied back (one host round trip per
solve; the 100k x 3 solve itself takes about 0.04 s, benchmarks/NOTES.md).

`CGSystem` is Jacobi-preconditioned conjugate gradients in torch on the right-hand side's device, every
column solved at once. Its iterations multiply by L through a padded table of L's rows (a gather, which
torch.compile fuses with the rest of the iteration when `compiled`); the residual is read back to the host
every `check_every` iterations, each read a synchronisation (a stop can come up to check_every - 1
iterations late, never early). Each `slot` (e.g. "forward", "backward") keeps its last solution as the next warm
start, since successive optimisation steps solve nearby systems. It stops when every column's relative
residual |b - A x| / |b| <= tol, where the residual that CG updates is confirmed by recomputing b - A x
(CG restarts from there if rounding made them drift apart); so each column's error is at most tol |b|,
plus the rounding of the returned dtype. It gives up after max_iter iterations: `last_iterations` and
`last_residual` record the latest solve, and reaching the cap emits a `CGNotConverged` warning naming
the residual reached. At large lambda CG needs about as many iterations as L's own condition number
asks (100k anchors, tol 1e-5: 58 at lambda = 8, ~1500 at 1e6, ~1800 at 1e8), and float64 rounding of
A x keeps the reachable relative residual above roughly 1e-15 lambda (1e-7 to 1e-6 at lambda = 1e8; a
smaller tol ends in the warning). With `graphs` on a CUDA device, each block of check_every iterations (and
the residual the check reads) is captured once per right-hand-side shape as a CUDA graph and replayed: the
iterations are a few tiny kernels each, so launching them from Python cost more than running them. With `lagged`
(`precond.cg_lagged`) a solve reads nothing back: it runs a number of blocks chosen from the same slot's previous
solve, whose residuals were copied to the host without blocking (CGSystem._solve_lagged); the tolerance is then
reached a few solves after a change, not within each (tests/test_host_syncs.py). Float64
costs 1.1-1.3x the float32 solve time (100k anchors, lambda = 8, one CPU thread, same process).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import torch

from pig.cuda_graphs import capture


class CGNotConverged(RuntimeWarning):
    """Conjugate gradients stopped at its iteration cap above the requested tolerance."""


def _as_columns(b: torch.Tensor, n: int, who: str) -> torch.Tensor:
    if b.shape[0] != n:
        raise ValueError(f"{who}: expected a tensor with {n} rows (one per anchor), found shape {tuple(b.shape)}")
    return b.reshape(n, -1)


class _KnnSystem:
    """A = I + lambda L for a sparse graph Laplacian L, applied matrix-free in float64."""

    def __init__(self, laplacian: sp.spmatrix, lam: float, who: str):
        if not math.isfinite(lam) or lam < 0:
            raise ValueError(f"{who}: expected a finite lambda >= 0, found {lam}")
        laplacian = sp.csr_matrix(laplacian, dtype=np.float64)
        if laplacian.shape[0] != laplacian.shape[1]:
            raise ValueError(f"{who}: expected a square Laplacian, found shape {laplacian.shape}")
        self.laplacian = laplacian
        self.lam = float(lam)
        self.size = laplacian.shape[0]
        self._who = who
        self._torch_laplacian: dict[torch.device, torch.Tensor] = {}

    def _laplacian_on(self, device: torch.device) -> torch.Tensor:
        if device not in self._torch_laplacian:
            lap = self.laplacian
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)
                self._torch_laplacian[device] = torch.sparse_csr_tensor(
                    torch.from_numpy(lap.indptr.astype(np.int64)),
                    torch.from_numpy(lap.indices.astype(np.int64)),
                    torch.from_numpy(lap.data),
                    size=lap.shape,
                    check_invariants=True,
                ).to(device)
        return self._torch_laplacian[device]

    def _apply64(self, x: torch.Tensor) -> torch.Tensor:
        """A x for float64 columns x (N, C)."""
        if self.lam == 0.0:
            return x.clone()
        return torch.addmm(x, self._laplacian_on(x.device), x, alpha=self.lam)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """A x for x (N, ...) on x's device, computed in float64, returned in x's dtype."""
        columns = _as_columns(x, self.size, f"{self._who}.apply")
        return self._apply64(columns.to(torch.float64)).to(x.dtype).reshape(x.shape)


class FactorizedSystem(_KnnSystem):
    """A = I + lambda L, factorised once with SuperLU; `solve` is exact to float64 rounding."""

    def __init__(self, laplacian: sp.spmatrix, lam: float):
        super().__init__(laplacian, lam, "FactorizedSystem")
        matrix = (sp.identity(self.size, format="csc") + self.lam * self.laplacian).tocsc()
        self._lu = sla.splu(matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    def solve(self, b: torch.Tensor, slot: str | None = None) -> torch.Tensor:
        """x = A^-1 b for b (N, ...), computed on the CPU in float64."""
        columns = _as_columns(b, self.size, "FactorizedSystem.solve")
        rhs = columns.detach().to("cpu", torch.float64).numpy()
        x = self._lu.solve(np.ascontiguousarray(rhs))
        return torch.from_numpy(np.asarray(x).reshape(rhs.shape)).to(device=b.device, dtype=b.dtype).reshape(b.shape)


def _cg_iteration(x, r, p, rz, columns, values, inv_diag, lam: float):
    """One Jacobi-preconditioned CG iteration on (x, residual r, direction p, r.z) for A = I + lam L, L given by its
    padded rows; float64 columns solved at once. Out of place, so that torch.compile fuses the gather, products and
    reductions into a few kernels (the eager iteration launches a dozen); one iteration, not an unrolled block,
    keeps the compilation short."""
    ap = p + lam * (values[..., None] * p[columns]).sum(dim=1)
    pap = (p * ap).sum(dim=0)
    # Columns that already converged exactly have p = 0; keep them fixed instead of dividing 0 by 0.
    alpha = torch.where(pap > 0, rz / torch.where(pap > 0, pap, torch.ones_like(pap)), torch.zeros_like(pap))
    x = x + alpha * p
    r = r - alpha * ap
    z = inv_diag * r
    rz_new = (r * z).sum(dim=0)
    beta = torch.where(rz > 0, rz_new / torch.where(rz > 0, rz, torch.ones_like(rz)), torch.zeros_like(rz))
    return x, r, z + beta * p, rz_new


class _CGBlockGraph:
    """A CUDA graph of `steps` CG iterations on static (x, r, p, rz) buffers, ending in the relative residual
    max |r| / |b| that the host check reads; captured once for one right-hand-side shape."""

    def __init__(self, iterate, shape: tuple[int, int], steps: int, rows, inv_diag: torch.Tensor, lam: float):
        device = inv_diag.device
        self.x, self.r, self.p = (torch.zeros(shape, dtype=torch.float64, device=device) for _ in range(3))
        self.rz = torch.zeros(shape[1], dtype=torch.float64, device=device)
        self.norm = torch.ones(shape[1], dtype=torch.float64, device=device)
        self.residual = torch.zeros((), dtype=torch.float64, device=device)
        self.graph, _ = capture(lambda: self._run(iterate, steps, rows, inv_diag, lam), device)

    def _run(self, iterate, steps, rows, inv_diag, lam) -> None:
        x, r, p, rz = self.x, self.r, self.p, self.rz
        for _ in range(steps):
            x, r, p, rz = iterate(x, r, p, rz, *rows, inv_diag, lam)
        for buffer, value in ((self.x, x), (self.r, r), (self.p, p), (self.rz, rz)):
            buffer.copy_(value)
        self.residual.copy_((r.norm(dim=0) / self.norm).max())

    def run(self, x, r, p, rz, norm) -> tuple[torch.Tensor, ...]:
        for buffer, value in ((self.x, x), (self.r, r), (self.p, p), (self.rz, rz), (self.norm, norm)):
            buffer.copy_(value)
        self.graph.replay()
        return self.x, self.r, self.p, self.rz, self.residual


class CGSystem(_KnnSystem):
    """A = I + lambda L solved by warm-started Jacobi-preconditioned CG in float64 (see module docstring)."""

    def __init__(self, laplacian: sp.spmatrix, lam: float, tol: float = 1e-5, max_iter: int = 200, check_every: int = 1,
                 compiled: bool = False, graphs: bool = False, lagged: bool = False):
        if not tol > 0 or max_iter < 1 or check_every < 1:
            raise ValueError(f"CGSystem: expected tol > 0, max_iter >= 1 and check_every >= 1, found tol={tol}, "
                             f"max_iter={max_iter}, check_every={check_every}")
        super().__init__(laplacian, lam, "CGSystem")
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.check_every = int(check_every)
        self.last_iterations = 0
        self.last_residual = 0.0
        self._inverse_diagonal = 1.0 / (1.0 + self.lam * self.laplacian.diagonal())
        self._inverse_diagonal_on: dict[torch.device, torch.Tensor] = {}
        self._warm: dict[str | None, torch.Tensor] = {}
        self._rows: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}
        self._iterate = torch.compile(_cg_iteration, dynamic=False) if compiled else _cg_iteration
        self.graphs = graphs
        self._graphs: dict[tuple, _CGBlockGraph] = {}
        self.lagged = lagged
        self._blocks: dict[str | None, int] = {}  # lagged: each slot's blocks of check_every iterations per solve
        self._pending: dict[str | None, _LaggedRead] = {}  # lagged: each slot's last residuals, on their way to the host

    def _rows_on(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """L's rows as a padded table: column indices (N, D) and values (N, D), padding pointing at the row with 0."""
        if device not in self._rows:
            lap = self.laplacian
            counts = np.diff(lap.indptr)
            width = max(int(counts.max(initial=0)), 1)
            rows = np.repeat(np.arange(self.size), counts)
            slots = np.arange(lap.nnz) - np.repeat(lap.indptr[:-1], counts)
            columns = np.repeat(np.arange(self.size)[:, None], width, axis=1)
            values = np.zeros((self.size, width))
            columns[rows, slots], values[rows, slots] = lap.indices, lap.data
            self._rows[device] = (torch.from_numpy(columns).to(device), torch.from_numpy(values).to(device))
        return self._rows[device]

    def _block_graph(self, rhs: torch.Tensor, steps: int, inv_diag: torch.Tensor) -> _CGBlockGraph | None:
        """The captured block of `steps` iterations for this right-hand side's shape (CUDA with `graphs` only)."""
        if not (self.graphs and rhs.is_cuda):
            return None
        key = (rhs.device, tuple(rhs.shape), steps)
        if key not in self._graphs:
            self._graphs[key] = _CGBlockGraph(self._iterate, tuple(rhs.shape), steps, self._rows_on(rhs.device), inv_diag,
                                              self.lam)
        return self._graphs[key]

    def _run_block(self, rhs, steps: int, x, r, p, rz, inv_diag, safe_norm) -> tuple[torch.Tensor, ...]:
        """`steps` CG iterations on (x, r, p, rz), replayed as a CUDA graph where there is one, and the relative
        residual max |r| / |b| after them (on the device)."""
        graph = self._block_graph(rhs, steps, inv_diag)
        if graph is not None:
            return graph.run(x, r, p, rz, safe_norm)
        for _ in range(steps):
            x, r, p, rz = self._iterate(x, r, p, rz, *self._rows_on(rhs.device), inv_diag, self.lam)
        return x, r, p, rz, (r.norm(dim=0) / safe_norm).max()

    def reset(self) -> None:
        """Forget the warm starts (the next solves start from zero) and the lagged block counts."""
        self._warm.clear()
        self._blocks.clear()
        self._pending.clear()

    def solve(self, b: torch.Tensor, slot: str | None = None) -> torch.Tensor:
        """x ~= A^-1 b for b (N, ...), warm-started from the previous solution of the same `slot`."""
        rhs = _as_columns(b, self.size, "CGSystem.solve").detach().to(torch.float64)
        if b.device not in self._inverse_diagonal_on:
            self._inverse_diagonal_on[b.device] = torch.from_numpy(self._inverse_diagonal).to(b.device)[:, None]
        inv_diag = self._inverse_diagonal_on[b.device]

        b_norm = rhs.norm(dim=0)
        active = b_norm > 0  # a zero column has the exact solution zero
        safe_norm = torch.where(active, b_norm, torch.ones_like(b_norm))
        warm = self._warm.get(slot)
        x = warm.clone() if warm is not None and warm.shape == rhs.shape and warm.device == rhs.device else torch.zeros_like(rhs)
        x = x * active
        if self.lagged:
            return self._solve_lagged(b, rhs, x, inv_diag, safe_norm, active, slot)
        iterations = 0
        while True:
            # The true residual decides convergence; the recursively updated one only ends each CG run.
            r = rhs - self._apply64(x)
            residual = (r.norm(dim=0) / safe_norm).max()
            value = residual.item()
            if value <= self.tol or iterations >= self.max_iter:
                break
            z = inv_diag * r
            p = z.clone()
            rz = (r * z).sum(dim=0)
            while iterations < self.max_iter:
                steps = min(self.check_every, self.max_iter - iterations)
                x, r, p, rz, block_residual = self._run_block(rhs, steps, x, r, p, rz, inv_diag, safe_norm)
                iterations += steps
                # Each check waits for the device; a block of iterations between checks keeps its queue full.
                if block_residual.item() <= self.tol:
                    break
            x = x.clone()  # a graph's buffer is overwritten by the next solve
        self.last_iterations = iterations
        self.last_residual = value  # the value read above: float(residual) would wait for the device again
        if self.last_residual > self.tol:
            warnings.warn(
                f"CGSystem: stopped at the iteration cap ({self.max_iter}) with relative residual "
                f"{self.last_residual:.3g} > tol {self.tol:.3g} (N={self.size}, lambda={self.lam})",
                CGNotConverged,
                stacklevel=2,
            )
        self._warm[slot] = x
        return x.to(b.dtype, copy=True).reshape(b.shape)

    def _block_limit(self) -> int:
        return -(-self.max_iter // self.check_every)

    def _solve_lagged(self, b: torch.Tensor, rhs: torch.Tensor, x: torch.Tensor, inv_diag: torch.Tensor,
                      safe_norm: torch.Tensor, active: torch.Tensor, slot: str | None) -> torch.Tensor:
        """One CG run of a block count chosen from this slot's previous solve, without reading the device: that
        solve's residuals (after each block, and the true one at its end) were copied to the host without blocking
        and are read now, a step later, when the copy has long landed (waited for if not: the count must not depend
        on timing, or a fit's iterates would differ from run to run). The count doubles (up to max_iter's)
        when the last true residual missed tol, and drops by one when the recursive residual had reached tol a
        block before the end; the first solve of a slot runs one block. The host never learns which columns are
        zero: a zero column keeps the slot's previous warm start, and an all-zero right-hand side reports NaN
        residuals, which leave the count as it is."""
        blocks = self._blocks.get(slot, 1)
        pending = self._pending.pop(slot, None)
        if pending is not None:
            *history, final = pending.values()
            if final > self.tol:
                if blocks == self._block_limit():  # the previous solve, at the cap, missed tol
                    warnings.warn(f"CGSystem: a lagged solve stopped at the iteration cap ({self.max_iter}) with "
                                  f"relative residual {final:.3g} > tol {self.tol:.3g} (N={self.size}, lambda={self.lam})",
                                  CGNotConverged, stacklevel=3)
                blocks = min(2 * blocks, self._block_limit())
            elif any(value <= self.tol for value in history[:-1]):
                blocks -= 1
            self.last_residual = final
        self._blocks[slot] = blocks
        r = rhs - self._apply64(x)
        z = inv_diag * r
        p = z.clone()
        rz = (r * z).sum(dim=0)
        history = torch.empty(blocks + 1, dtype=torch.float64, device=rhs.device)
        for k in range(blocks):
            steps = min(self.check_every, self.max_iter - k * self.check_every)
            x, r, p, rz, block_residual = self._run_block(rhs, steps, x, r, p, rz, inv_diag, safe_norm)
            history[k].copy_(block_residual)
        x = x.clone()  # a graph's buffer is overwritten by the next solve
        history[blocks].copy_(((rhs - self._apply64(x)).norm(dim=0) / safe_norm).max())
        self._pending[slot] = _LaggedRead(torch.where(active.any(), history, math.nan))
        self.last_iterations = min(blocks * self.check_every, self.max_iter)
        warm = self._warm.get(slot)
        self._warm[slot] = x if warm is None or warm.shape != x.shape or warm.device != x.device else torch.where(active, x, warm)
        return x.to(b.dtype, copy=True).reshape(b.shape)


class _LaggedRead:
    """A device tensor's values on their way to the host without the host waiting: on CUDA a non-blocking copy into
    pinned memory and an event recorded after it, which `values` waits for (by the next solve, a step later, it has
    landed); on the CPU the same copy, done at once. Only the CUDA path's asynchrony is not exercised on the CPU."""

    def __init__(self, values: torch.Tensor):
        buffer = torch.empty(values.shape, dtype=values.dtype, pin_memory=values.is_cuda)
        buffer.copy_(values, non_blocking=True)
        self.host = buffer.numpy()  # a view: read with numpy, no torch op
        self.event = None
        if values.is_cuda:
            self.event = torch.cuda.Event()
            self.event.record()

    def values(self) -> list[float]:
        if self.event is not None:
            self.event.synchronize()
        return self.host.tolist()

