"""Nearest training timestep of a query pose: argmin_t sum_j d_SO(3)(R_j(query), R_j(train_t)) over body joints.

The paper's novel-pose rule (Section 4.1): the chosen timestep feeds the time embedding gamma(t)
(Eq. 6) while the query pose itself drives the transport (Eqs. 2-3).
"""
from __future__ import annotations

import torch

from pig.body.rotation import axis_angle_to_matrix, geodesic_distance

# SMPL-X body-pose joints (1..21): the global orientation does not change the clothing state. As a slice too: a
# CUDA graph (pig.avatar.driver's frame) cannot capture the host-to-device copy of an index list.
BODY_SLICE = slice(1, 22)
BODY_JOINTS = tuple(range(BODY_SLICE.start, BODY_SLICE.stop))


def pose_distances(query: torch.Tensor, train: torch.Tensor, joints: tuple[int, ...] = BODY_JOINTS) -> torch.Tensor:
    """Summed per-joint geodesic distances (Q, T) between axis-angle poses query (Q, J, 3) and train (T, J, 3)."""
    if query.dim() != 3 or train.dim() != 3 or query.shape[1:] != train.shape[1:] or query.shape[-1] != 3:
        raise ValueError(f"pose_distances expects (Q, J, 3) and (T, J, 3) axis-angle poses, found {tuple(query.shape)} and {tuple(train.shape)}")
    index = torch.as_tensor(joints, device=query.device)
    rq = axis_angle_to_matrix(query[:, index])  # (Q, J', 3, 3)
    rt = axis_angle_to_matrix(train[:, index])  # (T, J', 3, 3)
    # One query at a time keeps memory at O(T J) for long sequences (THuman4: 2000 training steps).
    return torch.stack([geodesic_distance(rq[q, None], rt).sum(-1) for q in range(rq.shape[0])])


def nearest_timestep(query: torch.Tensor, train: torch.Tensor, joints: tuple[int, ...] = BODY_JOINTS) -> torch.Tensor:
    """Index (Q,) into `train` of the nearest training pose for each query pose (ties -> earliest)."""
    if train.shape[0] == 0:
        raise ValueError("nearest_timestep needs at least one training pose")
    return pose_distances(query, train, joints).argmin(dim=1)
