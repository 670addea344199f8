"""Exact solve of (I + lambda L) x = b for the 6-neighbour lattice Laplacian with free boundary.

The grid-level system of the Sobolev preconditioner (Eq. 4): the DCT-II diagonalises L exactly.

The Neumann ("free") lattice Laplacian is a Kronecker sum of 1-D path-graph Laplacians, whose
eigenvectors are the orthonormal DCT-II basis with eigenvalues 4 sin^2(pi k / (2 n)). Edges have unit
weight (a graph Laplacian, not scaled by the cell size): `lambda` alone sets the smoothing in cells.
Two exact ways to apply the transform, both pure torch (CPU and CUDA): "fft" (Makhoul's reordering
on torch.fft, O(n log n) per line) and "matmul" (the dense n x n DCT matrix per axis). At our sizes
(n <= 88) "matmul" is faster (benchmarks/NOTES.md), since the FFT path is bound by memory passes.
"""
from __future__ import annotations

import math

import torch


def dct_ii(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Orthonormal DCT-II along `dim` (scipy.fft.dct(type=2, norm="ortho"))."""
    x = x.movedim(dim, -1)
    n = x.shape[-1]
    # Makhoul: even samples ascending then odd samples descending make one real FFT of length n
    # suffice; with W_k = exp(-i pi k / 2n) V_k, X_k = 2 Re W_k and X_{n-k} = -2 Im W_k.
    v = x.index_select(-1, _makhoul_order(n, x.device))
    w = torch.fft.rfft(v, dim=-1) * _twiddle(n, -1.0, x)
    out = torch.cat([w.real, -w.imag[..., 1 : (n + 1) // 2].flip(-1)], dim=-1)
    return (out * (2.0 * _ortho_scale(n, x))).movedim(-1, dim)


def dct_iii(y: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Orthonormal DCT-III along `dim`: the inverse of `dct_ii`."""
    y = y.movedim(dim, -1)
    n = y.shape[-1]
    y = y / (2.0 * _ortho_scale(n, y))
    # Half spectrum V_k = exp(i pi k / 2n) (X_k - i X_{n-k}), k = 0..n//2, with X_n = 0.
    padded = torch.cat([y, torch.zeros_like(y[..., :1])], dim=-1)
    mirrored = padded.index_select(-1, torch.arange(n, n - n // 2 - 1, -1, device=y.device))
    spectrum = torch.complex(y[..., : n // 2 + 1], -mirrored) * _twiddle(n, 1.0, y)
    v = torch.fft.irfft(spectrum, n=n, dim=-1)
    inverse_order = torch.argsort(_makhoul_order(n, y.device))
    return v.index_select(-1, inverse_order).movedim(-1, dim)


def _makhoul_order(n: int, device) -> torch.Tensor:
    return torch.cat([torch.arange(0, n, 2, device=device), torch.arange(1, n, 2, device=device).flip(0)])


def _twiddle(n: int, sign: float, like: torch.Tensor) -> torch.Tensor:
    k = torch.arange(n // 2 + 1, device=like.device, dtype=like.dtype)
    return torch.polar(torch.ones_like(k), sign * math.pi * k / (2 * n))


def _ortho_scale(n: int, like: torch.Tensor) -> torch.Tensor:
    scale = torch.full((n,), math.sqrt(1.0 / (2 * n)), device=like.device, dtype=like.dtype)
    scale[0] = math.sqrt(1.0 / (4 * n))
    return scale


def path_laplacian_eigenvalues(n: int, device=None, dtype=torch.float64) -> torch.Tensor:
    """Eigenvalues 4 sin^2(pi k / 2n), k = 0..n-1, of the free-boundary path-graph Laplacian, in DCT order."""
    k = torch.arange(n, device=device, dtype=torch.float64)
    return (4.0 * torch.sin(math.pi * k / (2 * n)) ** 2).to(dtype)


def lattice_laplacian_apply(x: torch.Tensor) -> torch.Tensor:
    """L x on the last three axes: sum over the 6 neighbours of (x_i - x_j), free boundary."""
    out = torch.zeros_like(x)
    for dim in (-3, -2, -1):
        if x.shape[dim] == 1:  # no edges along this axis
            continue
        diff = x.diff(dim=dim)  # x_{i+1} - x_i along `dim`
        zero = torch.zeros_like(diff.narrow(dim, 0, 1))
        out = out + torch.cat([zero, diff], dim=dim) - torch.cat([diff, zero], dim=dim)
    return out


def dct_matrix(n: int, device=None, dtype=torch.float64) -> torch.Tensor:
    """The orthonormal DCT-II matrix C (n, n): dct_ii(x) = C @ x, and C.T is its inverse."""
    k = torch.arange(n, dtype=torch.float64)[:, None]
    i = torch.arange(n, dtype=torch.float64)[None, :]
    c = torch.cos(math.pi * k * (2 * i + 1) / (2 * n)) * math.sqrt(2.0 / n)
    c[0] /= math.sqrt(2.0)
    return c.to(device=device, dtype=dtype)


def _transform_matmul(x: torch.Tensor, mx: torch.Tensor, my: torch.Tensor, mz: torch.Tensor) -> torch.Tensor:
    """Apply mx, my, mz along the last three axes, with matmuls only (no permutes)."""
    nx, ny, nz = x.shape[-3:]
    x = x @ mz.T
    x = my @ x
    return (mx @ x.reshape(*x.shape[:-3], nx, ny * nz)).reshape(x.shape)


class LatticeSystem:
    """A = I + lambda L on a grid of `shape` (3 ints); tensors (..., X, Y, Z) are solved channel-wise.

    `solve(b)` is exact (up to floating point) for any lambda >= 0 and any shape, including 1 x 1 x 1;
    `method` picks the DCT implementation ("matmul" or "fft", same result). The `slot` argument of
    `solve` exists for interface parity with the iterative KNN solver and is ignored.
    """

    def __init__(self, shape: tuple[int, int, int] | list[int], lam: float, method: str = "matmul"):
        shape = tuple(int(s) for s in shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"LatticeSystem: expected a grid shape of 3 positive sizes, found {shape}")
        if not math.isfinite(lam) or lam < 0:
            raise ValueError(f"LatticeSystem: expected a finite lambda >= 0, found {lam}")
        if method not in ("matmul", "fft"):
            raise ValueError(f"LatticeSystem: expected method 'matmul' or 'fft', found {method!r}")
        self.shape = shape
        self.lam = float(lam)
        self.method = method
        self._cache: dict[tuple, tuple[torch.Tensor, ...]] = {}

    def _check(self, b: torch.Tensor) -> None:
        if tuple(b.shape[-3:]) != self.shape:
            raise ValueError(f"LatticeSystem: expected a tensor ending in grid shape {self.shape}, found {tuple(b.shape)}")

    def _operators(self, device, dtype) -> tuple[torch.Tensor, ...]:
        """(1 / (1 + lambda (mu_x + mu_y + mu_z)), Cx, Cy, Cz), built in float64, cached per device and dtype."""
        key = (torch.device(device), dtype)
        if key not in self._cache:
            mx, my, mz = (path_laplacian_eigenvalues(n) for n in self.shape)
            eig = mx[:, None, None] + my[None, :, None] + mz[None, None, :]
            inverse = 1.0 / (1.0 + self.lam * eig)
            self._cache[key] = tuple(t.to(device=device, dtype=dtype) for t in (inverse, *(dct_matrix(n) for n in self.shape)))
        return self._cache[key]

    def solve(self, b: torch.Tensor, slot: str | None = None) -> torch.Tensor:
        """x = (I + lambda L)^-1 b over the last three axes."""
        self._check(b)
        if self.lam == 0.0:
            return b.clone()
        inverse, cx, cy, cz = self._operators(b.device, b.dtype)
        if self.method == "matmul":
            return _transform_matmul(_transform_matmul(b, cx, cy, cz) * inverse, cx.T, cy.T, cz.T)
        coeffs = dct_ii(dct_ii(dct_ii(b, -3), -2), -1) * inverse
        return dct_iii(dct_iii(dct_iii(coeffs, -3), -2), -1)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """(I + lambda L) x over the last three axes (the 7-point stencil)."""
        self._check(x)
        return x + self.lam * lattice_laplacian_apply(x)
