"""3D barycentric anchor transport: per-attachment surface frames and the rotation between them.

Implements Eqs. 2-3: R = [t|b|n]_posed [t|b|n]_canon^T and x(theta) = x_init(theta) + R (x - x_init).
"""
from __future__ import annotations

import torch

# Below this relative size an edge or a normal counts as degenerate and a fallback direction is used.
_DEGENERATE = 1e-10


def barycentric_points(vertices: torch.Tensor, faces: torch.Tensor, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Surface points from fixed attachments: (B, V, 3) vertices -> (B, N, 3)."""
    corners = vertices[:, faces[face_ids]]  # (B, N, 3 corners, 3)
    return (bary.to(vertices.dtype)[None, :, :, None] * corners).sum(dim=2)


def _normalize(v: torch.Tensor, fallback: torch.Tensor, tol: torch.Tensor) -> torch.Tensor:
    """Unit vectors, with `fallback` (unit) where |v| <= tol; gradients stay finite on both branches."""
    norm = v.norm(dim=-1, keepdim=True)
    ok = norm > tol
    safe = torch.where(ok, v, fallback) / torch.where(ok, norm, torch.ones_like(norm))
    return torch.where(ok, safe, fallback)


def _perpendicular(t: torch.Tensor) -> torch.Tensor:
    """A unit vector perpendicular to unit `t`: t crossed with the axis it is least aligned with."""
    axis = torch.nn.functional.one_hot(t.abs().argmin(dim=-1), 3).to(t.dtype)
    p = torch.linalg.cross(t, axis)
    return p / p.norm(dim=-1, keepdim=True)


def surface_frames(vertices: torch.Tensor, faces: torch.Tensor, face_ids: torch.Tensor) -> torch.Tensor:
    """Right-handed orthonormal frames [t | b | n] (columns) of the attachment triangles.

    vertices (B, V, 3) -> (B, N, 3, 3). t follows the first edge, n the triangle normal, b = n x t.
    A zero-length first edge falls back to the second edge (then to the x axis); a zero-area
    triangle gets a normal perpendicular to t, so every frame is finite with det +1.
    """
    corners = vertices[:, faces[face_ids]]  # (B, N, 3, 3)
    e1 = corners[:, :, 1] - corners[:, :, 0]
    e2 = corners[:, :, 2] - corners[:, :, 0]
    scale = torch.maximum(e1.norm(dim=-1, keepdim=True), e2.norm(dim=-1, keepdim=True)).detach()
    tol = _DEGENERATE * scale.clamp_min(1e-30)
    x_axis = torch.zeros_like(e1)
    x_axis[..., 0] = 1
    t = _normalize(e1, _normalize(e2, x_axis, tol), tol)
    n = _normalize(torch.linalg.cross(e1, e2), _perpendicular(t.detach()), tol * scale)
    # Re-orthogonalise: for a sliver, n from the cross product is only approximately perpendicular to t.
    n = n - (n * t).sum(-1, keepdim=True) * t
    n = _normalize(n, _perpendicular(t.detach()), torch.full_like(tol, 1e-6))
    b = torch.linalg.cross(n, t)
    return torch.stack([t, b, n], dim=-1)


def transport_rotation(posed_frames: torch.Tensor, canonical_frames: torch.Tensor) -> torch.Tensor:
    """Eq. 2: R = F_posed F_canon^T; (B, N, 3, 3) and (N, 3, 3) -> (B, N, 3, 3), proper rotations."""
    return posed_frames @ canonical_frames.transpose(-1, -2)


def transport_points(
    anchors: torch.Tensor, x_init: torch.Tensor, posed_init: torch.Tensor, rotation: torch.Tensor
) -> torch.Tensor:
    """Eq. 3: x(theta) = x_init(theta) + R (x - x_init); anchors, x_init (N, 3), posed_init (B, N, 3)."""
    offset = (anchors - x_init).to(rotation.dtype)
    return posed_init + (rotation @ offset[None, :, :, None])[..., 0]
