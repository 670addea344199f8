"""3D barycentric anchor transport: per-attachment surface frames and the rotation between them.

Implements Eqs. 2-3: R = [t|b|n]_posed [t|b|n]_canon^T and x(theta) = x_init(theta) + R (x - x_init).
"""
from __future__ import annotations

import torch

from .rotation import small_matmul, small_matvec


def barycentric_points(vertices: torch.Tensor, faces: torch.Tensor, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Surface points from fixed attachments: (B, V, 3) vertices -> (B, N, 3)."""
    corners = vertices[:, faces[face_ids]]  # (B, N, 3 corners, 3)
    return (bary.to(vertices.dtype)[None, :, :, None] * corners).sum(dim=2)


def _normalize(v: torch.Tensor, fallback: torch.Tensor, tol: torch.Tensor) -> torch.Tensor:
    """v / |v|, with `fallback` where |v| <= tol; gradients stay finite on both branches."""
    norm = v.norm(dim=-1, keepdim=True)
    ok = norm > tol
    safe = torch.where(ok, v, fallback) / torch.where(ok, norm, torch.ones_like(norm))
    return torch.where(ok, safe, fallback)


def _perpendicular(t: torch.Tensor) -> torch.Tensor:
    """A unit vector perpendicular to unit `t`: t crossed with the axis it is least aligned with."""
    axis = torch.nn.functional.one_hot(t.abs().argmin(dim=-1), 3).to(t.dtype)
    p = torch.linalg.cross(t, axis)
    return p / p.norm(dim=-1, keepdim=True)


def _neighbourhood_sums(vertices: torch.Tensor, faces: torch.Tensor, face_ids: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Sums over the triangles touching each attachment triangle's corners (with multiplicity) of their
    area-weighted normals and of their first edges: (B, N, 3) each."""
    triangles = vertices[:, faces]  # (B, F, 3 corners, 3)
    first = triangles[:, :, 1] - triangles[:, :, 0]
    per_face = torch.cat([torch.linalg.cross(first, triangles[:, :, 2] - triangles[:, :, 0]), first], dim=-1)
    at_vertices = per_face.new_zeros(per_face.shape[0], vertices.shape[1], 6)
    at_vertices = at_vertices.index_add(1, faces.reshape(-1), per_face.repeat_interleave(3, dim=1))
    sums = at_vertices[:, faces[face_ids]].sum(dim=2)
    return sums[..., :3], sums[..., 3:]


def surface_frames(vertices: torch.Tensor, faces: torch.Tensor, face_ids: torch.Tensor, sync_free: bool = False) -> torch.Tensor:
    """Right-handed orthonormal frames [t | b | n] (columns) of the attachment triangles.

    vertices (B, V, 3) -> (B, N, 3, 3). A regular triangle: t along its first edge, n its normal, b = n x t.
    A degenerate triangle borrows what it lacks from the triangles touching its corners, so that its frame
    still turns with the surface: every rule below gives F(Q V + c) = Q F(V) for a rotation Q.
    - An edge shorter than sqrt(eps) times the mesh's mean first-edge length counts as zero: t falls back
      from the first edge to the second, and for coincident corners to the sum of the first edges of the
      triangles touching its corners, taken in their plane.
    - The normal is undefined when either edge is zero or the sine of the angle between the edges is
      below sqrt(eps) (zero area, collinear or coincident corners, float rounding of a sliver): n is then
      the sum of the area-weighted normals of the triangles touching its corners (their vertex normals),
      made perpendicular to t.
    Only where that neighbourhood has no area, or no edge at all, do world axes fill in. Every frame is
    finite with det +1, and has finite gradients. The neighbourhood sums (over the whole mesh) are
    computed only when some attachment triangle is degenerate; `sync_free` computes them always, so that the
    device is never asked which (the same frames; a CUDA graph cannot capture that question).
    """
    dtype = vertices.dtype
    rel = torch.finfo(dtype).eps ** 0.5
    mean_edge = (vertices[:, faces[:, 1]] - vertices[:, faces[:, 0]]).norm(dim=-1).mean(dim=1).detach()
    zero_edge = rel * mean_edge.clamp_min(torch.finfo(dtype).tiny)[:, None, None]  # (B, 1, 1)
    zero_area = zero_edge * mean_edge[:, None, None]

    corners = vertices[:, faces[face_ids]]  # (B, N, 3, 3)
    e1 = corners[:, :, 1] - corners[:, :, 0]
    e2 = corners[:, :, 2] - corners[:, :, 0]
    area_normal = torch.linalg.cross(e1, e2)
    e1_len, e2_len = e1.norm(dim=-1, keepdim=True).detach(), e2.norm(dim=-1, keepdim=True).detach()
    edges_ok = (e1_len > zero_edge) & (e2_len > zero_edge)
    sine_floor = torch.where(edges_ok, rel * e1_len * e2_len, torch.full_like(e1_len, float("inf")))
    if not sync_free and bool((area_normal.norm(dim=-1, keepdim=True) > sine_floor).all()):
        hood_normal, hood_first = torch.zeros_like(e1), torch.zeros_like(e1)  # never selected below
    else:
        hood_normal, hood_first = _neighbourhood_sums(vertices, faces, face_ids)
    hood_n = _normalize(hood_normal, torch.zeros_like(hood_normal), zero_area)
    hood_t = hood_first - (hood_first * hood_n).sum(-1, keepdim=True) * hood_n

    x_axis = torch.zeros_like(e1)
    x_axis[..., 0] = 1
    t = _normalize(e1, _normalize(e2, _normalize(hood_t, x_axis, zero_edge), zero_edge), zero_edge)
    hood_normal = hood_normal - (hood_normal * t).sum(-1, keepdim=True) * t
    n = _normalize(area_normal, _normalize(hood_normal, _perpendicular(t.detach()), zero_area), sine_floor)
    # Re-orthogonalise: for a sliver, n from the cross product is only approximately perpendicular to t.
    n = n - (n * t).sum(-1, keepdim=True) * t
    n = _normalize(n, _perpendicular(t.detach()), torch.full_like(e1_len, 1e-6))
    b = torch.linalg.cross(n, t)
    return torch.stack([t, b, n], dim=-1)


def transport_rotation(posed_frames: torch.Tensor, canonical_frames: torch.Tensor) -> torch.Tensor:
    """Eq. 2: R = F_posed F_canon^T; (B, N, 3, 3) and (N, 3, 3) -> (B, N, 3, 3), proper rotations."""
    return small_matmul(posed_frames, canonical_frames.transpose(-1, -2))


def transport_points(
    anchors: torch.Tensor, x_init: torch.Tensor, posed_init: torch.Tensor, rotation: torch.Tensor
) -> torch.Tensor:
    """Eq. 3: x(theta) = x_init(theta) + R (x - x_init); anchors, x_init (N, 3), posed_init (B, N, 3)."""
    offset = (anchors - x_init).to(rotation.dtype)
    return posed_init + small_matvec(rotation, offset[None])
