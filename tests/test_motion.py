"""Motion clips: the three file layouts, bad-input messages, slerp resampling against scipy, the world
rotation about the root pivot against posing the body model, alignment to a capture's up/ground/centre
(z-up clips into y-up and y-down captures, 180-degree turns), and the shipped demo clip."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from pig.body.model import SMPLX_JOINT_NAMES, BodyModel
from pig.body.motion import (DEMO_MOTION, SMPLH_TO_SMPLX, Motion, MotionError, align_motion, body_up, capture_frame,
                             demo_motion_arrays, main, read_motion, rotate_world, rotation_between)


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    from pig.body.standin import write_standin

    path = tmp_path_factory.mktemp("standin") / "body_model.npz"
    write_standin(path)
    return BodyModel.from_file(path, dtype=torch.float64)


def _vertices(body, full_pose, transl, betas):
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        return body(t(full_pose), t(betas), transl=t(transl)).vertices.numpy()


def _root_about(axis, angles):
    """Root rotations about a fixed axis (unit) by each angle, as axis-angle (N, 3)."""
    return np.asarray(angles)[:, None] * np.asarray(axis, float)[None]


# -- layouts ---------------------------------------------------------------------------------------

def test_reads_amass_smplx(tmp_path, rng):
    poses, trans = rng.normal(scale=0.3, size=(5, 165)), rng.normal(size=(5, 3))
    path = tmp_path / "clip.npz"
    np.savez(path, poses=poses.astype(np.float32), trans=trans, mocap_framerate=np.array(60.0), betas=np.arange(16.0) / 4,
             gender=np.array("neutral"))
    motion = read_motion(path)
    assert motion.full_pose.dtype == np.float64 and motion.full_pose.shape == (5, 55, 3)
    np.testing.assert_array_equal(motion.full_pose, poses.astype(np.float32).reshape(5, 55, 3))
    np.testing.assert_array_equal(motion.transl, trans)
    assert motion.fps == 60.0 and motion.source == str(path)
    np.testing.assert_array_equal(motion.betas, np.arange(16.0) / 4)
    assert read_motion(path, fps=24).fps == 24.0


def test_smplh_joints_land_on_their_smplx_names(tmp_path, rng):
    fingers = [f"{f}{k}" for f in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)]
    smplh_names = SMPLX_JOINT_NAMES[:22] + [f"left_{f}" for f in fingers] + [f"right_{f}" for f in fingers]
    assert [SMPLX_JOINT_NAMES[j] for j in SMPLH_TO_SMPLX] == smplh_names

    poses = rng.normal(scale=0.3, size=(4, 156))
    path = tmp_path / "smplh.npz"
    np.savez(path, poses=poses, trans=np.zeros((4, 3)), mocap_frame_rate=120.0)  # SMPL-X AMASS spells it so
    motion = read_motion(path)
    smplh = poses.reshape(4, 52, 3)
    np.testing.assert_array_equal(motion.full_pose[:, SMPLX_JOINT_NAMES.index("right_wrist")], smplh[:, 21])
    np.testing.assert_array_equal(motion.full_pose[:, SMPLX_JOINT_NAMES.index("left_index1")], smplh[:, 22])
    np.testing.assert_array_equal(motion.full_pose[:, SMPLX_JOINT_NAMES.index("right_thumb3")], smplh[:, 51])
    np.testing.assert_array_equal(motion.full_pose[:, 25:55], smplh[:, 22:52])  # hands move
    assert np.all(motion.full_pose[:, 22:25] == 0)  # jaw and eyes
    assert motion.fps == 120.0 and motion.betas is None


def _thuman_arrays(rng, n=4):
    return {"betas": rng.normal(size=(1, 10)), "global_orient": rng.normal(size=(n, 3)), "transl": rng.normal(size=(n, 3)),
            "body_pose": rng.normal(size=(n, 63)), "jaw_pose": rng.normal(size=(n, 3)), "expression": np.zeros((n, 10)),
            "left_hand_pose": rng.normal(size=(n, 45)), "right_hand_pose": rng.normal(size=(n, 45))}


def test_reads_thuman4_params(tmp_path, rng):
    arrays = _thuman_arrays(rng)
    path = tmp_path / "smpl_params.npz"
    np.savez(path, **arrays)
    motion = read_motion(path)
    np.testing.assert_array_equal(motion.full_pose[:, 0], arrays["global_orient"])
    np.testing.assert_array_equal(motion.full_pose[:, 1:22].reshape(4, 63), arrays["body_pose"])
    np.testing.assert_array_equal(motion.full_pose[:, 22], arrays["jaw_pose"])
    assert np.all(motion.full_pose[:, 23:25] == 0)
    np.testing.assert_array_equal(motion.full_pose[:, 40:55].reshape(4, 45), arrays["right_hand_pose"])
    np.testing.assert_array_equal(motion.transl, arrays["transl"])
    np.testing.assert_array_equal(motion.betas, arrays["betas"][0])
    assert motion.fps == 30.0 and read_motion(path, fps=50).fps == 50.0


def test_reads_dna_fullpose_with_hand_mean(tmp_path, rng):
    fullpose, transl = rng.normal(size=(3, 55, 3)), rng.normal(size=(3, 3))
    hands_mean = np.zeros((55, 3))
    hands_mean[25:] = rng.normal(size=(30, 3))
    path = tmp_path / "dna.npz"
    np.savez(path, fullpose=fullpose, transl=transl)
    motion = read_motion(path, hands_mean=hands_mean)
    np.testing.assert_array_equal(motion.full_pose[:, :25], fullpose[:, :25])
    np.testing.assert_allclose(motion.full_pose[:, 25:], fullpose[:, 25:] + hands_mean[25:], rtol=0, atol=1e-15)
    assert motion.fps == 15.0 and motion.betas is None
    with pytest.raises(MotionError, match="flat_hand_mean=False; pass hands_mean="):
        read_motion(path)


# -- bad input -------------------------------------------------------------------------------------

def _amass(n=3, cols=165):
    return {"poses": np.zeros((n, cols)), "trans": np.zeros((n, 3)), "mocap_framerate": np.array(30.0)}


BAD = {
    "99 columns": (dict(_amass(cols=99)), "`poses` has 99 columns; expected 156 (SMPL-H, AMASS) or 165 (SMPL-X)"),
    "72 columns": (dict(_amass(cols=72)), "`poses` has 72 columns; expected 156 (SMPL-H, AMASS) or 165 (SMPL-X)"),
    "3-d poses": (dict(_amass(), poses=np.zeros((3, 55, 3))), "`poses` has shape (3, 55, 3); expected (N, 156) or (N, 165)"),
    "no trans": ({k: v for k, v in _amass().items() if k != "trans"}, "missing key(s) ['trans']; expected AMASS npz"),
    "no frame rate": ({k: v for k, v in _amass().items() if k != "mocap_framerate"},
                      "missing key(s) ['mocap_framerate']; expected AMASS npz"),
    "trans frames": (dict(_amass(), trans=np.zeros((2, 3))), "`trans` has shape (2, 3); expected (3, 3) to match `poses`"),
    "nan pose": (dict(_amass(), poses=np.where(np.arange(165) == 7, np.nan, np.zeros((3, 165)))),
                 "`poses` contains NaN or infinite values (first at index [0, 7]); expected AMASS npz"),
    "inf trans": (dict(_amass(), trans=np.full((3, 3), np.inf)), "the translation of frame 0 is [inf, inf, inf]"),
    "zero rate": (dict(_amass(), mocap_framerate=np.array(0.0)), "`mocap_framerate` is 0 fps; expected a frame rate from 1"),
    "zero frames": (dict(_amass(n=0)), "`poses` has zero frames; expected AMASS npz"),
    "thuman zero frames": ({"global_orient": np.zeros((0, 3)), "body_pose": np.zeros((0, 63)), "transl": np.zeros((0, 3)),
                            "betas": np.zeros(10)}, "`global_orient` has zero frames; expected THuman4 smpl_params.npz"),
    "thuman body_pose": ({"global_orient": np.zeros((2, 3)), "body_pose": np.zeros((2, 60)), "transl": np.zeros((2, 3)),
                          "betas": np.zeros(10)}, "'body_pose' has shape (2, 60), expected (2, 63); expected THuman4"),
    "thuman no body_pose": ({"global_orient": np.zeros((2, 3)), "transl": np.zeros((2, 3)), "betas": np.zeros(10)},
                            "missing key(s) ['body_pose']"),
    "thuman nan transl": ({"global_orient": np.zeros((2, 3)), "body_pose": np.zeros((2, 63)), "betas": np.zeros(10),
                           "transl": np.array([[0, 0, 0], [0, np.nan, 0]])}, "the translation of frame 1 is [0.0, nan, 0.0]"),
    "dna shape": ({"fullpose": np.zeros((2, 54, 3)), "transl": np.zeros((2, 3))},
                  "'fullpose' has shape (2, 162), expected (2, 165); expected DNA-style npz"),
    "unknown keys": ({"root_orient": np.zeros((2, 3))}, "no known motion layout (keys ['root_orient']); expected one of: AMASS"),
    "no arrays": ({}, "no known motion layout (keys [])"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_layouts_name_file_and_expected_layout(tmp_path, case):
    arrays, message = BAD[case]
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(MotionError) as err:
        read_motion(path, hands_mean=np.zeros((55, 3)))
    text = str(err.value)
    assert text.startswith(f"{path}: ") and message in text and "\n" not in text


@pytest.mark.parametrize("content, message", [(b"", "not a valid npz archive (the file is empty)"),
                                              (b"poses,trans\n1,2\n", "not a valid npz archive (the file starts with b'pose')"),
                                              (None, "motion file not found; expected one of: AMASS")])
def test_unreadable_files(tmp_path, content, message):
    path = tmp_path / "clip.npz"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(MotionError) as err:
        read_motion(path)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value) and "\n" not in str(err.value)


def test_pickled_member_is_not_unpickled(tmp_path):
    path = tmp_path / "clip.npz"
    np.savez(path, poses=np.array([{"a": 1}], dtype=object), trans=np.zeros((1, 3)), mocap_framerate=30.0)
    with pytest.raises(MotionError, match="'poses' holds pickled Python objects, which are not loaded"):
        read_motion(path)


# -- time ------------------------------------------------------------------------------------------

def test_resample_matches_scipy_slerp(rng):
    n, fps = 9, 10.0
    pose = rng.normal(scale=1.2, size=(n, 55, 3))  # large angles: the shorter arc must be taken
    pose[:, 3] = _root_about([0, 0, 1], np.linspace(3.0, 3.3, n))  # across 180 degrees, axis-angle flips sign
    transl = rng.normal(size=(n, 3))
    motion = Motion(pose, transl, fps, None, "x")
    out = motion.resample(24.0)
    times = np.arange(out.num_frames) / 24.0
    assert out.num_frames == 20 and out.fps == 24.0 and times[-1] <= (n - 1) / fps  # 0.8 s span
    for joint in (0, 3, 17, 54):
        reference = Slerp(np.arange(n) / fps, Rotation.from_rotvec(pose[:, joint]))(times).as_matrix()
        np.testing.assert_allclose(Rotation.from_rotvec(out.full_pose[:, joint]).as_matrix(), reference, atol=1e-10)
    for axis in range(3):
        np.testing.assert_allclose(out.transl[:, axis], np.interp(times, np.arange(n) / fps, transl[:, axis]), atol=1e-12)
    same = motion.resample(fps)
    np.testing.assert_allclose(Rotation.from_rotvec(same.full_pose.reshape(-1, 3)).as_matrix(),
                               Rotation.from_rotvec(pose.reshape(-1, 3)).as_matrix(), atol=1e-12)
    assert motion.resample(5.0).num_frames == 5
    with pytest.raises(ValueError, match="expected a frame rate from 1 to 1000 fps"):
        motion.resample(0.0)


def test_select_slices_frames_and_rate(rng):
    motion = Motion(rng.normal(size=(10, 55, 3)), rng.normal(size=(10, 3)), 30.0, None, "x")
    part = motion.select(slice(2, 9, 3))
    np.testing.assert_array_equal(part.full_pose, motion.full_pose[[2, 5, 8]])
    np.testing.assert_array_equal(part.transl, motion.transl[[2, 5, 8]])
    assert part.fps == 10.0
    with pytest.raises(MotionError, match="select none of the 10 frames"):
        motion.select(slice(20, 30))


# -- orientation -----------------------------------------------------------------------------------

@pytest.mark.parametrize("a, b", [([0, 1, 0], [0, 0, 1]), ([0, 1, 0], [0, -1, 0]), ([0, 0, 1], [0, 0, -1]),
                                  ([1, 2, 3], [-1, -2, -3]), ([1, 2, 3], [-1, -2, -3 + 1e-9]), ([1, 0, 0], [1, 0, 0]),
                                  ([0.3, -0.2, 0.9], [-0.5, 0.1, 0.2])])
def test_rotation_between_is_a_rotation_taking_a_to_b(a, b):
    q = rotation_between(a, b)
    a, b = np.asarray(a, float) / np.linalg.norm(a), np.asarray(b, float) / np.linalg.norm(b)
    np.testing.assert_allclose(q @ a, b, atol=1e-8)
    np.testing.assert_allclose(q @ q.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(q) - 1) < 1e-12


def test_world_rotation_identity_against_posed_vertices(body, rng):
    pose = rng.normal(scale=0.3, size=(3, 55, 3))
    transl, betas = rng.normal(size=(3, 3)), rng.normal(scale=0.8, size=10)
    q = Rotation.from_rotvec([0.4, -2.9, 1.1]).as_matrix()
    with torch.no_grad():
        root_joint = body(torch.zeros(1, 55, 3, dtype=torch.float64), torch.from_numpy(betas)).joints[0, 0].numpy()
    assert np.linalg.norm(root_joint) > 1e-3  # the pivot matters
    rotated = rotate_world(Motion(pose, transl, 30.0), q, root_joint)
    expected = _vertices(body, pose, transl, betas) @ q.T
    np.testing.assert_allclose(_vertices(body, rotated.full_pose, rotated.transl, betas), expected, atol=1e-10)
    np.testing.assert_array_equal(rotated.full_pose[:, 1:], pose[:, 1:])


def _z_up_clip(rng, n=5):
    """Turning about world z, small tilts, rest y-up body rotated onto z (AMASS-like), wandering in x-y."""
    tilt = Rotation.from_rotvec(rng.normal(scale=0.1, size=(n, 3)))
    roots = Rotation.from_rotvec(_root_about([0, 0, 1], np.linspace(0, 2, n))) * tilt * Rotation.from_rotvec([np.pi / 2, 0, 0])
    pose = rng.normal(scale=0.2, size=(n, 55, 3))
    pose[:, 0] = roots.as_rotvec()
    transl = np.c_[rng.normal(size=(n, 2)), 0.9 + rng.normal(scale=0.05, size=n)]
    return Motion(pose, transl, 30.0, None, "clip")


@pytest.mark.parametrize("capture_up", [[0, 1, 0], [0, -1, 0]])
def test_z_up_clip_lands_upright_on_ground_at_centre(body, rng, capture_up):
    clip = _z_up_clip(rng)
    assert body_up(clip.full_pose)[2] > 0.95
    betas = rng.normal(scale=0.5, size=10)
    up, ground, centre = np.asarray(capture_up, float), -0.7, np.array([0.4, 123.0, -1.3])
    aligned = align_motion(clip, body, betas, up, ground, centre)
    np.testing.assert_allclose(body_up(aligned.full_pose), up, atol=1e-6)
    heights = _vertices(body, aligned.full_pose, aligned.transl, betas) @ up
    assert abs(heights.min() - ground) < 1e-9
    with torch.no_grad():
        joints = body(torch.from_numpy(aligned.full_pose), torch.from_numpy(betas), transl=torch.from_numpy(aligned.transl)).joints
    mean_root = joints[:, 0].numpy().mean(axis=0)
    np.testing.assert_allclose(mean_root[[0, 2]], centre[[0, 2]], atol=1e-9)  # horizontal only


def test_alignment_is_one_rigid_motion_of_the_clip(body, rng):
    clip, betas = _z_up_clip(rng, n=4), rng.normal(scale=0.5, size=10)
    aligned = align_motion(clip, body, betas, [0, -1, 0], 0.2, np.zeros(3))
    q = rotation_between(body_up(clip.full_pose), [0, -1, 0])
    offset = _vertices(body, aligned.full_pose, aligned.transl, betas) - _vertices(body, clip.full_pose, clip.transl, betas) @ q.T
    np.testing.assert_allclose(offset, np.broadcast_to(offset[0, 0], offset.shape), atol=1e-10)


def test_half_turn_and_up_override(body, rng):
    clip = Motion(np.zeros((2, 55, 3)), np.zeros((2, 3)), 30.0)  # rest pose: body up is exactly +y
    clip.full_pose[:, 5] = [0.3, 0, 0]
    down = align_motion(clip, body, np.zeros(10), [0, -1, 0], 0.0, np.zeros(3))
    np.testing.assert_allclose(body_up(down.full_pose), [0, -1, 0], atol=1e-12)
    assert abs(np.linalg.norm(down.full_pose[0, 0]) - np.pi) < 1e-9
    forced = align_motion(clip, body, np.zeros(10), [0, 1, 0], 0.5, np.zeros(3), up_override="-z")
    np.testing.assert_allclose(body_up(forced.full_pose), [0, 0, -1], atol=1e-12)
    assert abs((_vertices(body, forced.full_pose, forced.transl, np.zeros(10)) @ [0, 0, -1]).min() - 0.5) < 1e-9
    with pytest.raises(ValueError, match="up axis 'up' not understood; expected one of"):
        align_motion(clip, body, np.zeros(10), [0, 1, 0], 0.0, np.zeros(3), up_override="up")


@pytest.mark.parametrize("flip", [False, True])
def test_capture_frame_from_training_poses(body, rng, flip):
    t = 6
    pose = rng.normal(scale=0.2, size=(t, 55, 3))
    roots = Rotation.from_rotvec(_root_about([0, 1, 0], rng.uniform(-3, 3, size=t)))  # turns about y keep up = +y
    if flip:  # a y-down capture
        roots = Rotation.from_rotvec([np.pi, 0, 0]) * roots
    pose[:, 0] = roots.as_rotvec()
    transl, betas = rng.normal(scale=0.3, size=(t, 3)), rng.normal(scale=0.5, size=10)
    avatar = SimpleNamespace(pose_init=torch.from_numpy(pose), transl=torch.from_numpy(transl),
                             betas_init=torch.from_numpy(betas), body_model=body)
    up, ground, centre = capture_frame(avatar, num_frames=t)
    expected_up = np.array([0, -1.0 if flip else 1.0, 0])
    np.testing.assert_allclose(up, expected_up, atol=1e-12)
    assert abs(ground - (_vertices(body, pose, transl, betas) @ expected_up).min()) < 1e-12
    with torch.no_grad():
        joints = body(torch.from_numpy(pose), torch.from_numpy(betas), transl=torch.from_numpy(transl)).joints.numpy()
    np.testing.assert_allclose(centre[[0, 2]], joints[:, 0, [0, 2]].mean(axis=0), atol=1e-12)
    assert abs(centre @ up - ground) < 1e-12
    same = capture_frame((pose, transl, betas, body), num_frames=t)
    np.testing.assert_allclose(np.concatenate([same[0], [same[1]], same[2]]), np.concatenate([up, [ground], centre]))


# -- demo ------------------------------------------------------------------------------------------

def test_demo_clip_ships_loads_and_regenerates(tmp_path):
    assert DEMO_MOTION.stat().st_size < 300_000
    demo = read_motion(DEMO_MOTION)
    assert demo.num_frames == 144 and demo.fps == 30.0 and demo.full_pose.shape == (144, 55, 3)
    assert body_up(demo.full_pose)[2] > 0.99  # z-up, as AMASS clips are
    assert np.all(demo.full_pose[:, 23:25] == 0)
    first, second = demo_motion_arrays(), demo_motion_arrays()
    for key in first:
        np.testing.assert_array_equal(first[key], second[key])
    main(["--write-demo", str(tmp_path / "demo.npz")])
    again = read_motion(tmp_path / "demo.npz")
    np.testing.assert_allclose(again.full_pose, demo.full_pose, rtol=0, atol=1e-6)  # libm may differ by an ulp
    np.testing.assert_allclose(again.transl, demo.transl, rtol=0, atol=1e-6)


def test_demo_differs_from_the_default_training_motion():
    from pig.data.synthetic import SyntheticConfig
    from pig.data.synthetic.motion import Motion as SyntheticMotion

    cfg = SyntheticConfig()
    times = np.arange(cfg.frames) * (cfg.duration_s / cfg.frames)
    training = SyntheticMotion(cfg.seed, 0.0).full_pose(times)
    demo = read_motion(DEMO_MOTION)
    assert demo.num_frames / demo.fps > cfg.duration_s
    body = slice(1, 22)
    # every demo frame is at least 0.1 rad (summed over body joints) away from every training frame
    gaps = np.abs(demo.full_pose[:, None, body] - training[None, :, body]).sum(axis=(2, 3))
    assert gaps.min() > 0.1
