"""The real-time frame (pig.avatar.driver, frame_graph=True) captured as a CUDA graph against the launched path.

Run on the GPU machine (skipped without CUDA). The graph replays the compiled frame on new poses written into its
static buffers; each replay must give the splats and nearest timestep of the per-pose path for that pose.
"""
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from test_driver import _avatar  # noqa: E402  (the CPU tests' avatar: non-zero grid, moved anchors, refiner)

from pig.avatar.driver import AvatarDriver  # noqa: E402

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


@pytest.mark.parametrize("with_transl", [False, True])
def test_captured_frame_follows_new_poses(tmp_path, with_transl):
    from pig.body.standin import write_standin

    write_standin(tmp_path / "body_model.npz")
    model = _avatar((tmp_path / "body_model.npz").read_bytes()).cuda()
    graph, plain = AvatarDriver(model, frame_graph=True), AvatarDriver(model)
    rng = np.random.default_rng(0)
    train = model.pose_init.cpu().numpy()
    for i in range(6):
        pose = train[i % model.num_timesteps] + rng.normal(scale=0.05, size=(55, 3))
        transl = rng.normal(scale=0.1, size=3) if with_transl else None
        for lod in range(model.num_levels):
            splats, step = graph.posed_frame(lod, pose, transl)
            assert int(step) == model.nearest_timestep(torch.as_tensor(pose))
            for ours, theirs in zip(splats, plain.gaussians(lod, pose, transl)):
                # Inductor fuses and reorders the float32 arithmetic: rounding-level differences (2.6e-5 seen)
                torch.testing.assert_close(ours, theirs, rtol=2e-4, atol=2e-4)
    assert len(graph._frames) == model.num_levels  # one capture per level


def test_back_to_back_frames_read_their_own_pose(tmp_path):
    """Frames requested without a host synchronisation between them: each replay must read its own pose, i.e. the
    host must not refill the pinned staging buffer while the previous frame's copy out of it is still queued."""
    from pig.body.standin import write_standin

    write_standin(tmp_path / "body_model.npz")
    model = _avatar((tmp_path / "body_model.npz").read_bytes()).cuda()
    graph, plain = AvatarDriver(model, frame_graph=True), AvatarDriver(model)
    rng = np.random.default_rng(1)
    train = model.pose_init.cpu().numpy()
    poses = [train[i % model.num_timesteps] + rng.normal(scale=0.05, size=(55, 3)) for i in range(8)]
    lod = model.num_levels - 1
    graph.posed_frame(lod, poses[0])  # compile and capture outside the queued run
    torch.cuda.synchronize()
    torch.cuda._sleep(50_000_000)  # keeps the stream busy, so the copies below queue behind it
    means = [graph.posed_frame(lod, pose)[0][0].clone() for pose in poses]  # clone: ordered on the stream, no sync
    for pose, ours in zip(poses, means):
        torch.testing.assert_close(ours, plain.gaussians(lod, pose)[0], rtol=2e-4, atol=2e-4)


@pytest.mark.parametrize("compile_frames", [True, False])
def test_captured_frames_that_decode_follow_their_timesteps(tmp_path, compile_frames):
    """The render stage's frames (decoded_budget_bytes=0, captured as launched or compiled): a training timestep in
    its refined pose and a pose-driven frame, each decoding its timestep inside the graph, replayed in an order that
    revisits timesteps, against the launched per-timestep and per-pose paths."""
    from pig.body.standin import write_standin

    write_standin(tmp_path / "body_model.npz")
    model = _avatar((tmp_path / "body_model.npz").read_bytes()).cuda()
    graph = AvatarDriver(model, frame_graph=True, decoded_budget_bytes=0, compile_frames=compile_frames)
    plain = AvatarDriver(model)
    rng = np.random.default_rng(2)
    train = model.pose_init.cpu().numpy()
    tolerance = dict(rtol=2e-4, atol=2e-4)  # the rest-shape path and inductor's fusion: rounding-level differences
    for lod in range(model.num_levels):
        for t in (2, 0, 1, 2, 0):
            for ours, theirs in zip(graph.timestep_frame(lod, t), plain.gaussians(lod, timestep=t)):
                torch.testing.assert_close(ours, theirs, **tolerance)
            pose = train[t] + rng.normal(scale=0.05, size=(55, 3))
            splats, step = graph.posed_frame(lod, pose, [0.1, -0.2, 0.0])
            assert int(step) == model.nearest_timestep(torch.as_tensor(pose))
            for ours, theirs in zip(splats, plain.gaussians(lod, pose, [0.1, -0.2, 0.0])):
                torch.testing.assert_close(ours, theirs, **tolerance)
    assert not graph._decoded_all and len(graph._frames) == 2 * model.num_levels


def test_back_to_back_timestep_frames_read_their_own_timestep(tmp_path):
    """As test_back_to_back_frames_read_their_own_pose, for the int64 timestep staged into a training frame's graph."""
    from pig.body.standin import write_standin

    write_standin(tmp_path / "body_model.npz")
    model = _avatar((tmp_path / "body_model.npz").read_bytes()).cuda()
    graph = AvatarDriver(model, frame_graph=True, decoded_budget_bytes=0, compile_frames=False)
    plain = AvatarDriver(model)
    lod, steps = model.num_levels - 1, [1, 2, 0, 2, 1, 0]
    graph.timestep_frame(lod, 0)  # capture outside the queued run
    torch.cuda.synchronize()
    torch.cuda._sleep(50_000_000)
    means = [graph.timestep_frame(lod, t)[0].clone() for t in steps]
    for t, ours in zip(steps, means):
        torch.testing.assert_close(ours, plain.gaussians(lod, timestep=t)[0], rtol=2e-4, atol=2e-4)
