"""The novel-pose timestep rule on poses built so that the nearest one is known."""
from __future__ import annotations

import math

import pytest
import torch

from pig.avatar.nearest_pose import BODY_JOINTS, nearest_timestep, pose_distances


def _axis_angle(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float64)
    return axis / axis.norm() * angle


def test_distance_is_sum_of_joint_angles():
    train = torch.zeros(1, 55, 3, dtype=torch.float64)
    query = torch.zeros(1, 55, 3, dtype=torch.float64)
    query[0, 3] = _axis_angle([0, 0, 1], 0.3)
    query[0, 18] = _axis_angle([1, 1, 0], 1.1)
    query[0, 0] = _axis_angle([0, 1, 0], 2.0)  # global orientation: ignored
    query[0, 30] = _axis_angle([0, 1, 0], 2.0)  # hand joint: ignored
    assert pose_distances(query, train).item() == pytest.approx(1.4, abs=1e-12)


def test_nearest_timestep_known_answer():
    gen = torch.Generator().manual_seed(0)
    train = (torch.rand(8, 55, 3, generator=gen, dtype=torch.float64) - 0.5) * 2
    # Each query is a training pose with one body joint turned a little further about its own axis,
    # so its distance to that pose is exactly the extra angle, far below the spread between poses.
    order = torch.tensor([5, 0, 7, 2])
    query = train[order].clone()
    for q, joint in enumerate((1, 9, 21, 12)):
        aa = query[q, joint]
        query[q, joint] = aa * (1 + 0.01 / aa.norm())
    torch.testing.assert_close(nearest_timestep(query, train), order)
    torch.testing.assert_close(pose_distances(query, train)[torch.arange(4), order], torch.full((4,), 0.01, dtype=torch.float64))


def test_near_180_degrees():
    # Rotations by pi - e and pi + e about the same axis are 2e apart (not 2 pi - 2e),
    # and pi about opposite axes is the same rotation.
    eps = 1e-4
    axis = [0.3, -0.5, 0.8]
    train = torch.zeros(3, 55, 3, dtype=torch.float64)
    train[0, 4] = _axis_angle(axis, math.pi - eps)
    train[1, 4] = _axis_angle(axis, math.pi / 2)
    train[2, 4] = _axis_angle([1, 0, 0], math.pi - 0.5)
    query = torch.zeros(2, 55, 3, dtype=torch.float64)
    query[0, 4] = _axis_angle(axis, math.pi + eps)
    query[1, 4] = _axis_angle([-a for a in axis], math.pi)
    distances = pose_distances(query, train)
    assert distances[0, 0].item() == pytest.approx(2 * eps, rel=1e-6)
    assert distances[1, 0].item() == pytest.approx(eps, rel=1e-6)
    torch.testing.assert_close(nearest_timestep(query, train), torch.tensor([0, 0]))


def test_body_joints_and_errors():
    assert BODY_JOINTS == tuple(range(1, 22))
    with pytest.raises(ValueError, match=r"\(Q, J, 3\)"):
        pose_distances(torch.zeros(2, 55, 3), torch.zeros(2, 21, 3))
