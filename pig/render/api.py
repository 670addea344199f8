"""Entry point that renders 3D Gaussians into one or more cameras: colour, alpha, expected depth.

Renders the splats of Eqs. 8-11 for the loss of Eq. 15 with gsplat's CUDA rasterizer on a GPU
or, with the same conventions, the pure-PyTorch compositor anywhere else (differentiable).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple, Sequence

import torch
from torch import Tensor

from .cpu_compositor import DEFAULT_MAX_PAIRS, composite
from .gsplat_backend import render_gsplat
from .projection import project_splats

Backend = Literal["auto", "gsplat", "cpu"]


class RenderError(ValueError):
    """Inputs to the renderer have the wrong shape, dtype, device or value."""


class RenderResult(NamedTuple):
    color: Tensor  # (C, H, W, 3), composited on the background
    alpha: Tensor  # (C, H, W, 1)
    depth: Tensor  # (C, H, W, 1) expected camera-space z: sum w z / max(alpha, 1e-10)


@dataclass
class RasterizerConfig:
    """Preset section `rasterizer`: which backend renders and the CPU compositor's band size."""

    backend: Literal["auto", "gsplat", "cpu"] = "auto"
    max_pairs: int = DEFAULT_MAX_PAIRS


def render_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    background: Tensor | Sequence[float],
    sh_degree: int | None = None,
    backend: Backend = "auto",
    max_pairs: int = DEFAULT_MAX_PAIRS,
) -> RenderResult:
    """Render N Gaussians into C cameras, differentiably in means, quats, scales, opacities, sh.

    means (N,3) world; quats (N,4) wxyz (normalised here); scales (N,3) linear; opacities (N,)
    in (0,1); sh (N,K,3), K=(d+1)^2, evaluated up to `sh_degree` (default d) on directions from
    the camera centre, colour = max(SH + 0.5, 0); viewmats (C,4,4) world-to-camera; Ks (C,3,3);
    background (3,) or (C,3). backend "gsplat" needs CUDA float32 tensors; "cpu" is the
    pure-PyTorch compositor (runs on the tensors' device); "auto" picks gsplat for CUDA tensors.
    `max_pairs` bounds the compositor's memory (pairs per band); gsplat ignores it.
    """
    _check_gaussians(means, quats, scales, opacities, sh)
    c = _check_cameras(viewmats, Ks, width, height, means)
    degree = _sh_degree(sh, sh_degree)
    backgrounds = _backgrounds(background, c, means)
    chosen = _choose_backend(backend, means)
    if chosen == "gsplat":
        color, alpha, depth = render_gsplat(
            means, quats, scales, opacities, sh, viewmats, Ks, width, height, backgrounds, degree
        )
        return RenderResult(color, alpha, depth)

    splats = project_splats(means, quats, scales, opacities, sh, viewmats, Ks, width, height, degree)
    features, alpha = composite(splats, c, width, height, max_pairs)
    color = features[..., :3] + (1.0 - alpha) * backgrounds[:, None, None, :]
    depth = features[..., 3:] / alpha.clamp(min=1e-10)  # gsplat's "ED" normalisation
    return RenderResult(color, alpha, depth)


def render_timesteps(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    background: Tensor | Sequence[float],
    backend: Backend = "auto",
    max_pairs: int = DEFAULT_MAX_PAIRS,
) -> RenderResult:
    """`render_gaussians` for K sets of Gaussians (K, N, ...) each into its own C cameras (K, C, 4, 4) / (K, C, 3, 3):
    results (K, C, H, W, .). gsplat renders all K x C images in one call; the CPU compositor one set at a time."""
    if means.ndim != 3 or viewmats.ndim != 4 or viewmats.shape[0] != means.shape[0] or Ks.shape[:2] != viewmats.shape[:2]:
        raise RenderError(f"render_timesteps: expected means (K, N, 3), viewmats (K, C, 4, 4) and Ks (K, C, 3, 3), got "
                          f"{tuple(means.shape)}, {tuple(viewmats.shape)} and {tuple(Ks.shape)}")
    if means.shape[0] == 0:
        raise RenderError("render_timesteps: expected at least one set of Gaussians, got K = 0")
    # Indexing set k below would drop extra sets silently, or fail without naming the tensor.
    for name, tensor in {"quats": quats, "scales": scales, "opacities": opacities, "sh": sh}.items():
        if tensor.ndim == 0 or tensor.shape[0] != means.shape[0]:
            raise RenderError(f"{name}: expected {means.shape[0]} sets (K, N, ...) like means, got {tuple(tensor.shape)}")
    for k in range(means.shape[0]):  # the checks of one set are those of every set
        _check_gaussians(means[k], quats[k], scales[k], opacities[k], sh[k])
        _check_cameras(viewmats[k], Ks[k], width, height, means)
    count, c = viewmats.shape[:2]
    if _choose_backend(backend, means) == "gsplat":
        degree = _sh_degree(sh[0], None)
        backgrounds = _backgrounds(background, c, means).expand(count, c, 3).contiguous()
        return RenderResult(*render_gsplat(means, quats, scales, opacities, sh, viewmats, Ks, width, height, backgrounds, degree))
    outs = [render_gaussians(means[k], quats[k], scales[k], opacities[k], sh[k], viewmats[k], Ks[k], width, height, background,
                             backend=backend, max_pairs=max_pairs) for k in range(count)]
    return RenderResult(*(torch.stack(parts) for parts in zip(*outs)))


def _choose_backend(backend: str, means: Tensor) -> str:
    if backend not in ("auto", "gsplat", "cpu"):
        raise RenderError(f"backend must be 'auto', 'gsplat' or 'cpu', got {backend!r}")
    if backend == "auto":
        return "gsplat" if means.is_cuda else "cpu"
    if backend == "gsplat":
        if not means.is_cuda:
            raise RenderError(
                f"backend 'gsplat' needs CUDA tensors (gsplat has no CPU path), got device {means.device}; "
                "use backend='cpu' or 'auto'"
            )
        if means.dtype != torch.float32:
            raise RenderError(f"backend 'gsplat' needs float32 tensors, got {means.dtype}")
    return backend


def _check_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor) -> None:
    if means.ndim != 2 or means.shape[1] != 3:
        raise RenderError(f"means: expected shape (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    expected = {"quats": (quats, (n, 4)), "scales": (scales, (n, 3)), "opacities": (opacities, (n,))}
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise RenderError(f"{name}: expected shape {shape} for N={n} Gaussians, got {tuple(tensor.shape)}")
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
        raise RenderError(f"sh: expected shape ({n}, K, 3), got {tuple(sh.shape)}")
    for name, tensor in {"quats": quats, "scales": scales, "opacities": opacities, "sh": sh}.items():
        if tensor.dtype != means.dtype or tensor.device != means.device:
            raise RenderError(
                f"{name}: expected {means.dtype} on {means.device} like means, got {tensor.dtype} on {tensor.device}"
            )


def _check_cameras(viewmats: Tensor, Ks: Tensor, width: int, height: int, means: Tensor) -> int:
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise RenderError(f"viewmats: expected shape (C, 4, 4), got {tuple(viewmats.shape)}")
    c = viewmats.shape[0]
    if tuple(Ks.shape) != (c, 3, 3):
        raise RenderError(f"Ks: expected shape ({c}, 3, 3) for C={c} cameras, got {tuple(Ks.shape)}")
    for name, tensor in {"viewmats": viewmats, "Ks": Ks}.items():
        if tensor.dtype != means.dtype or tensor.device != means.device:
            raise RenderError(
                f"{name}: expected {means.dtype} on {means.device} like means, got {tensor.dtype} on {tensor.device}"
            )
    for name, size in {"width": width, "height": height}.items():
        if isinstance(size, bool) or not isinstance(size, int) or size <= 0:
            raise RenderError(f"{name}: expected a positive int, got {size!r}")
    return c


def _sh_degree(sh: Tensor, sh_degree: int | None) -> int:
    k = sh.shape[1]
    full = math.isqrt(k) - 1
    if sh_degree is None:
        if (full + 1) ** 2 != k or full > 3:
            raise RenderError(f"sh: K={k} is not (d+1)^2 for a degree d in 0..3; pass sh_degree explicitly")
        return full
    if not 0 <= sh_degree <= 3 or (sh_degree + 1) ** 2 > k:
        raise RenderError(f"sh_degree={sh_degree}: expected 0..3 with (sh_degree+1)^2 <= K={k}")
    return sh_degree


def _backgrounds(background: Tensor | Sequence[float], c: int, means: Tensor) -> Tensor:
    bg = torch.as_tensor(background, dtype=means.dtype, device=means.device)
    if tuple(bg.shape) == (3,):
        return bg.expand(c, 3).contiguous()
    if tuple(bg.shape) != (c, 3):
        raise RenderError(f"background: expected shape (3,) or ({c}, 3), got {tuple(bg.shape)}")
    return bg
