"""Rotation conversions used by the body model and the transport: axis-angle, matrices, quaternions.

Quaternions are (w, x, y, z), gsplat's convention. Every conversion is smooth at the identity and
stays finite at 180 degrees.
"""
from __future__ import annotations

import torch


def small_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a @ b for batches of small matrices (..., m, k) @ (..., k, n).

    Under torch.compile, a broadcast product summed over k: batched GEMM launches a cuBLAS kernel that the compiler
    cannot fuse, ~90 us for 100k 3 x 3 products on an H100 inside the real-time frame (benchmarks/NOTES.md,
    Renderer). Eagerly `@` stays: the broadcast form's autograd is 2.5-4x slower on the CPU."""
    if torch.compiler.is_compiling():
        return (a[..., :, :, None] * b[..., None, :, :]).sum(-2)
    return a @ b


def small_matvec(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """a @ v for batches of small matrices (..., m, k) and vectors (..., k) -> (..., m); see small_matmul."""
    if torch.compiler.is_compiling():
        return (a * v[..., None, :]).sum(-1)
    return (a @ v[..., None])[..., 0]


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula for (..., 3) axis-angle vectors -> (..., 3, 3) rotation matrices."""
    angle_sq = (axis_angle * axis_angle).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    angle = torch.sqrt(angle_sq.clamp_min(torch.finfo(axis_angle.dtype).tiny))
    small = angle_sq < 1e-8
    # sin(a)/a and (1-cos a)/a^2 with Taylor series near zero, so gradients at the rest pose are exact.
    safe_angle = torch.where(small, torch.ones_like(angle), angle)
    sin_c = torch.where(small, 1 - angle_sq / 6, torch.sin(safe_angle) / safe_angle)
    cos_c = torch.where(small, 0.5 - angle_sq / 24, (1 - torch.cos(safe_angle)) / (safe_angle * safe_angle))
    x, y, z = axis_angle.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(axis_angle.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device).expand_as(skew)
    return eye + sin_c * skew + cos_c * small_matmul(skew, skew)


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle, via quaternions (robust at 180 degrees)."""
    return quaternion_to_axis_angle(matrix_to_quaternion(matrix))


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w >= 0.

    Picks, per matrix, the best-conditioned of the four candidate formulas (Shepperd's method).
    """
    m = matrix
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    candidates_sq = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    roots = torch.sqrt(candidates_sq.clamp_min(1e-12)) * 2  # 4 * |component|
    w_x_y_z = [
        torch.stack([roots[..., 0] ** 2 / 4, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], roots[..., 1] ** 2 / 4, m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1], roots[..., 2] ** 2 / 4, m[..., 2, 1] + m[..., 1, 2]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2], roots[..., 3] ** 2 / 4], -1),
    ]
    stacked = torch.stack(w_x_y_z, dim=-2) / roots[..., :, None]  # (..., 4 candidates, 4)
    best = candidates_sq.argmax(dim=-1)
    quat = torch.gather(stacked, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    quat = quat / quat.norm(dim=-1, keepdim=True)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def quaternion_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions (w, x, y, z), normalised first -> (..., 3, 3) rotation matrices."""
    w, x, y, z = (quat / quat.norm(dim=-1, keepdim=True)).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quat.shape[:-1] + (3, 3))


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z): rotation b first, then a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quaternion_to_axis_angle(quat: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions -> (..., 3) axis-angle with angle in [0, pi]."""
    quat = torch.where(quat[..., :1] < 0, -quat, quat)
    xyz = quat[..., 1:]
    sin_half = xyz.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(sin_half, quat[..., :1])
    small = sin_half < 1e-6
    # angle / sin(angle/2) -> 2 as the angle -> 0.
    scale = torch.where(small, 2 + angle * angle / 12, angle / torch.where(small, torch.ones_like(sin_half), sin_half))
    return xyz * scale


def geodesic_distance(r1: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """Angle in [0, pi] of the relative rotation r1^T r2 for (..., 3, 3) matrices.

    Uses atan2 of the skew and trace parts, which stays accurate near 0 and near 180 degrees
    (acos of the trace loses half the digits at both ends).
    """
    rel = small_matmul(r1.transpose(-1, -2), r2)
    trace = rel[..., 0, 0] + rel[..., 1, 1] + rel[..., 2, 2]
    skew = torch.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1)
    return torch.atan2(skew.norm(dim=-1), trace - 1)
