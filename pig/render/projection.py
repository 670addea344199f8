"""Projects 3D Gaussians to image-space splats (mean, conic, opacity, colour, depth) per camera.

The EWA splatting step of 3DGS as gsplat does it, for the CPU compositor that renders the splats of
Eqs. 8-11 into the images of the loss (Eq. 15); reuses gsplat's pure-PyTorch projection and SH helpers.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from gsplat.cuda._torch_impl import _persp_proj, _quat_scale_to_covar_preci, _spherical_harmonics, _world_to_cam
from torch import Tensor

# gsplat.rasterization's defaults, which both backends use.
EPS2D = 0.3
NEAR_PLANE = 0.01
FAR_PLANE = 1e10
ALPHA_THRESHOLD = 1.0 / 255.0  # a (Gaussian, pixel) pair with smaller alpha is skipped
TRANSMITTANCE_FLOOR = 1e-4  # a pixel stops at the first pair that would take T to or below this
# gsplat's box half-extent in standard deviations (its CUDA projection kernel).
MAX_EXTENT_SIGMA = 3.33


@dataclass
class Splats:
    """Visible (camera, Gaussian) pairs, sorted by depth (ties by Gaussian index)."""

    camera: Tensor  # (M,) long
    gaussian: Tensor  # (M,) long
    means2d: Tensor  # (M, 2) pixel coordinates, pixel centres at +0.5
    conics: Tensor  # (M, 3) inverse blurred 2D covariance (a, b, c) of [[a, b], [b, c]]
    opacities: Tensor  # (M,)
    features: Tensor  # (M, 4) rgb colour and camera-space depth z
    radii: Tensor  # (M, 2) long, half-size in pixels of the box holding every alpha >= 1/255


def project_splats(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    sh_degree: int,
) -> Splats:
    """Project N Gaussians into C cameras; keep the pairs gsplat would rasterize (its culling rules)."""
    with torch.no_grad():
        depth_all = torch.einsum("cj,nj->cn", viewmats[:, 2, :3], means) + viewmats[:, 2, 3:4]
        # gsplat's kernel culls z < near, z > far and opacity < 1/255 (never visible anyway).
        valid = (depth_all >= NEAR_PLANE) & (depth_all <= FAR_PLANE) & (opacities >= ALPHA_THRESHOLD)[None]
        cam, gid = valid.nonzero(as_tuple=True)

    # Gather before projecting: invalid pairs (behind the camera) never enter the graph, so their
    # divisions by z cannot put NaN into the backward pass.
    # index_select gathers: the values of advanced indexing, cheaper under the CPU fit's deterministic kernels.
    covars, _ = _quat_scale_to_covar_preci(_take(quats, gid), _take(scales, gid), compute_preci=False)
    means_c, covars_c = _world_to_cam(_take(means, gid)[:, None], covars[:, None], _take(viewmats, cam)[:, None])
    means2d, cov2d = _persp_proj(means_c[:, 0], covars_c[:, 0], _take(Ks, cam), width, height)
    means2d, cov2d, depth = means2d[:, 0], cov2d[:, 0], means_c[:, 0, 0, 2]

    cov2d = cov2d + EPS2D * torch.eye(2, dtype=cov2d.dtype, device=cov2d.device)
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    conics = torch.stack(
        [cov2d[:, 1, 1] / det, -0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0]) / det, cov2d[:, 0, 0] / det], dim=-1
    )
    opac = _take(opacities, gid)

    with torch.no_grad():
        # Opacity-aware box (gsplat, after arXiv:2402.00525 B.2): outside it alpha < 1/255.
        extent = torch.sqrt(2.0 * torch.log(opac / ALPHA_THRESHOLD)).clamp(max=MAX_EXTENT_SIGMA)
        radii = torch.ceil(extent[:, None] * torch.sqrt(torch.stack([cov2d[:, 0, 0], cov2d[:, 1, 1]], -1)))
        inside = (
            (det > 0)
            & (means2d[:, 0] + radii[:, 0] > 0)
            & (means2d[:, 0] - radii[:, 0] < width)
            & (means2d[:, 1] + radii[:, 1] > 0)
            & (means2d[:, 1] - radii[:, 1] < height)
        )
        keep = inside.nonzero(as_tuple=True)[0]
        keep = _take(keep, torch.sort(_take(depth, keep), stable=True).indices)

    cam, gid = _take(cam, keep), _take(gid, keep)
    num_bases = (sh_degree + 1) ** 2
    campos = torch.linalg.inv(viewmats)[:, :3, 3]
    colors = _spherical_harmonics(sh_degree, _take(means, gid) - _take(campos, cam), _take(sh, gid)[:, :num_bases])
    colors = torch.clamp_min(colors + 0.5, 0.0)  # gsplat's offset, as in the Inria rasterizer
    return Splats(
        camera=cam,
        gaussian=gid,
        means2d=_take(means2d, keep),
        conics=_take(conics, keep),
        opacities=_take(opac, keep),
        features=torch.cat([colors, _take(depth, keep)[:, None]], dim=-1),
        radii=_take(radii, keep).long(),
    )


def _take(values: Tensor, index: Tensor) -> Tensor:
    """values[index] along dim 0 (index_select)."""
    return values.index_select(0, index)
