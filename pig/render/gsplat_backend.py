"""Renders Gaussians with gsplat's CUDA rasterizer (colour, alpha, expected depth in one pass).

The GPU path for the splats of Eqs. 8-11 and the loss of Eq. 15, as the paper trains with gsplat;
the conventions (eps2d, near plane, SH offset) are the ones the CPU compositor reproduces.
"""
from __future__ import annotations

from gsplat import rasterization
from torch import Tensor

from .projection import EPS2D, FAR_PLANE, NEAR_PLANE


def render_gsplat(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    backgrounds: Tensor,
    sh_degree: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """(color (C,H,W,3), alpha (C,H,W,1), expected depth (C,H,W,1)); backgrounds is (C, 3). With leading batch
    dimensions (means (K, N, 3), viewmats (K, C, 4, 4), backgrounds (K, C, 3), ...) the results get them too."""
    # gsplat loads (or builds) its CUDA extension at the first call, not at import.
    rendered, alpha, _ = rasterization(
        means,
        quats,
        scales,
        opacities,
        sh,
        viewmats,
        Ks,
        width,
        height,
        near_plane=NEAR_PLANE,
        far_plane=FAR_PLANE,
        eps2d=EPS2D,
        sh_degree=sh_degree,
        packed=False,
        backgrounds=backgrounds,
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    return rendered[..., :3], alpha, rendered[..., 3:]
