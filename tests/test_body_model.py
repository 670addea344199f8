"""BodyModel skinning against a plain float64 per-vertex reference, analytic poses, and parameter readers."""
import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pig.body.model import NUM_JOINTS, SMPLX_JOINT_NAMES, SMPLX_PARENTS, BodyModel, BodyModelError
from pig.body.params import ParamsError, SmplxParams, from_dna, from_thuman
from pig.body.standin import make_standin_arrays

J = {name: i for i, name in enumerate(SMPLX_JOINT_NAMES)}


@pytest.fixture(scope="module")
def standin():
    return make_standin_arrays(0)


def random_model_arrays(rng, num_vertices=40, shape_columns=20):
    """A small SMPL-X-layout model with everything non-zero: shape, expression and pose blend shapes."""
    weights = rng.dirichlet(np.full(NUM_JOINTS, 0.3), size=num_vertices)
    regressor = rng.random((NUM_JOINTS, num_vertices))
    return {
        "v_template": rng.normal(size=(num_vertices, 3)),
        "f": rng.integers(0, num_vertices, size=(30, 3)),
        "shapedirs": 0.1 * rng.normal(size=(num_vertices, 3, shape_columns)),
        "posedirs": 0.05 * rng.normal(size=(num_vertices, 3, (NUM_JOINTS - 1) * 9)),
        "J_regressor": regressor / regressor.sum(axis=1, keepdims=True),
        "weights": weights,
        "kintree_table": np.stack([SMPLX_PARENTS, np.arange(NUM_JOINTS)]),
    }


def reference_lbs(arrays, full_pose, betas, expression, transl):
    """Plain float64 SMPL-X skinning of one frame, vertex by vertex (FORMATS.md order)."""
    v_template = np.asarray(arrays["v_template"], np.float64)
    shapedirs = np.asarray(arrays["shapedirs"], np.float64)
    columns = shapedirs.shape[2]
    split = 300 if columns >= 400 else columns // 2
    coeffs = np.zeros(columns)
    coeffs[: len(betas)] = betas
    coeffs[split : split + len(expression)] = expression
    shaped = v_template + shapedirs @ coeffs
    joints = np.asarray(arrays["J_regressor"]) @ shaped
    rotations = Rotation.from_rotvec(np.asarray(full_pose).reshape(NUM_JOINTS, 3)).as_matrix()
    pose_feature = np.concatenate([(rotations[j] - np.eye(3)).ravel() for j in range(1, NUM_JOINTS)])
    blended = shaped + np.asarray(arrays["posedirs"]) @ pose_feature
    parents = list(arrays["kintree_table"][0])
    world = []
    for j in range(NUM_JOINTS):
        local = np.eye(4)
        local[:3, :3] = rotations[j]
        local[:3, 3] = joints[j] - (joints[parents[j]] if j > 0 else 0)
        world.append(local if j == 0 else world[parents[j]] @ local)
    skinning = []
    for j in range(NUM_JOINTS):
        a = world[j].copy()
        a[:3, 3] = world[j][:3, 3] - world[j][:3, :3] @ joints[j]
        skinning.append(a)
    skinning = np.array(skinning)
    out = np.empty_like(blended)
    for v in range(len(blended)):
        transform = np.zeros((4, 4))
        for j in range(NUM_JOINTS):
            transform += arrays["weights"][v, j] * skinning[j]
        out[v] = transform[:3, :3] @ blended[v] + transform[:3, 3] + transl
    posed_joints = np.array([world[j][:3, 3] for j in range(NUM_JOINTS)]) + transl
    return out, posed_joints


def run(model, pose, betas=None, expression=None, transl=None):
    t = lambda a: None if a is None else torch.as_tensor(np.asarray(a))  # noqa: E731
    with torch.no_grad():
        return model(t(pose), t(betas), t(expression), t(transl))


def random_pose(rng, batch, scale=0.6):
    return scale * rng.normal(size=(batch, NUM_JOINTS, 3))


@pytest.mark.parametrize("shape_columns", [20, 400])
def test_random_model_matches_reference(rng, shape_columns):
    arrays = random_model_arrays(rng, shape_columns=shape_columns)
    model = BodyModel(arrays, dtype=torch.float64)
    split = 300 if shape_columns >= 400 else shape_columns // 2
    assert model.num_betas == split
    pose = random_pose(rng, 3)
    betas = rng.normal(size=10)
    expression = rng.normal(size=(3, 10))
    transl = rng.normal(size=(3, 3))
    out = run(model, pose, betas, expression, transl)
    for b in range(3):
        verts, joints = reference_lbs(arrays, pose[b], betas, expression[b], transl[b])
        np.testing.assert_allclose(out.vertices[b].numpy(), verts, atol=1e-10)
        np.testing.assert_allclose(out.joints[b].numpy(), joints, atol=1e-10)


def test_precomputed_rest_shape_poses_like_betas_and_expression(rng):
    """`rest`: the shaped rest body computed once (the real-time frame's per-timestep cache) and posed later gives
    the float64 reference, and exactly what betas and expression give in the same call."""
    arrays = random_model_arrays(rng, shape_columns=400)
    model = BodyModel(arrays, dtype=torch.float64)
    pose, betas, expression, transl = random_pose(rng, 3), rng.normal(size=10), rng.normal(size=(3, 10)), rng.normal(size=(3, 3))
    shaped, joints_rest = model.rest_shape(3, torch.tensor(betas), torch.tensor(expression))
    assert shaped.shape == (3, 40, 3) and joints_rest.shape == (3, NUM_JOINTS, 3)
    direct = run(model, pose, betas, expression, transl)
    cached = model(torch.tensor(pose), transl=torch.tensor(transl), rest=(shaped, joints_rest))
    for name in ("vertices", "joints", "transforms", "shaped_vertices"):
        assert torch.equal(getattr(cached, name), getattr(direct, name)), name
    for b in range(3):
        verts, joints = reference_lbs(arrays, pose[b], betas, expression[b], transl[b])
        np.testing.assert_allclose(cached.vertices[b].numpy(), verts, atol=1e-10)
        np.testing.assert_allclose(cached.joints[b].numpy(), joints, atol=1e-10)


def test_compiled_model_matches_reference(rng):
    """Under torch.compile the chain's and skinning's small products are broadcast sums (pig.body.rotation.small_matmul),
    not the eager `@`: the compiled model meets the reference as the eager one does, 180-degree joints included."""
    arrays = random_model_arrays(rng)
    model = BodyModel(arrays, dtype=torch.float64)
    pose = random_pose(rng, 2)
    pose[1, 5] = [np.pi, 0.0, 0.0]
    betas = rng.normal(size=10)
    compiled = torch.compile(lambda p: model(p, torch.as_tensor(betas)).vertices, fullgraph=True)
    vertices = compiled(torch.as_tensor(pose))
    for b in range(2):
        expected, _ = reference_lbs(arrays, pose[b], betas, np.zeros(10), np.zeros(3))
        np.testing.assert_allclose(vertices[b].numpy(), expected, atol=1e-10)


def test_standin_matches_reference(rng, standin):
    model = BodyModel(standin, dtype=torch.float64)
    pose = random_pose(rng, 2, scale=0.4)
    betas, expression, transl = rng.normal(size=10), rng.normal(size=(2, 10)), rng.normal(size=(2, 3))
    out = run(model, pose, betas, expression, transl)
    for b in range(2):
        verts, joints = reference_lbs(standin, pose[b], betas, expression[b], transl[b])
        np.testing.assert_allclose(out.vertices[b].numpy(), verts, atol=1e-10)
        np.testing.assert_allclose(out.joints[b].numpy(), joints, atol=1e-10)


def test_rest_pose_returns_shaped_template(rng):
    arrays = random_model_arrays(rng)
    model = BodyModel(arrays, dtype=torch.float64)
    betas, expression = rng.normal(size=10), rng.normal(size=(1, 10))
    out = run(model, np.zeros((1, NUM_JOINTS, 3)), betas, expression)
    shaped = arrays["v_template"] + arrays["shapedirs"] @ np.concatenate([betas, expression[0]])
    np.testing.assert_allclose(out.shaped_vertices[0].numpy(), shaped, atol=1e-12)
    np.testing.assert_allclose(out.vertices[0].numpy(), shaped, atol=1e-12)
    np.testing.assert_allclose(out.joints[0].numpy(), arrays["J_regressor"] @ shaped, atol=1e-12)
    np.testing.assert_allclose(out.transforms[0].numpy(), np.broadcast_to(np.eye(4), (NUM_JOINTS, 4, 4)), atol=1e-12)


def test_elbow_bend_moves_wrist_about_elbow(standin):
    model = BodyModel(standin, dtype=torch.float64)
    rest = run(model, np.zeros((1, NUM_JOINTS, 3))).joints[0].numpy()
    pose = np.zeros((1, NUM_JOINTS, 3))
    axis = np.array([0.0, 1.0, 0.0])
    pose[0, J["left_elbow"]] = np.pi / 2 * axis
    out = run(model, pose).joints[0].numpy()
    elbow, wrist = rest[J["left_elbow"]], rest[J["left_wrist"]]
    # 90 degrees about +y maps (dx, dy, dz) to (dz, dy, -dx).
    d = wrist - elbow
    np.testing.assert_allclose(out[J["left_wrist"]], elbow + np.array([d[2], d[1], -d[0]]), atol=1e-12)
    untouched = [j for j in range(NUM_JOINTS) if j not in (J["left_wrist"],) and not 25 <= j < 40]
    np.testing.assert_allclose(out[untouched], rest[untouched], atol=1e-12)


def test_global_rotation_pivots_about_pelvis_then_translates(rng, standin):
    model = BodyModel(standin, dtype=torch.float64)
    rest = run(model, np.zeros((1, NUM_JOINTS, 3)))
    pose = np.zeros((1, NUM_JOINTS, 3))
    pose[0, 0] = [0.3, -1.1, 0.5]
    transl = np.array([[0.2, -0.4, 1.5]])
    out = run(model, pose, transl=transl)
    rotation = Rotation.from_rotvec(pose[0, 0]).as_matrix()
    pelvis = rest.joints[0, 0].numpy()
    expected = (rest.vertices[0].numpy() - pelvis) @ rotation.T + pelvis + transl
    np.testing.assert_allclose(out.vertices[0].numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(out.joints[0, 0].numpy(), pelvis + transl[0], atol=1e-12)


def test_float32_agrees_with_float64(rng, standin):
    model64 = BodyModel(standin, dtype=torch.float64)
    model32 = BodyModel(standin)
    assert model32.dtype == torch.float32
    pose, betas, transl = random_pose(rng, 2, 0.5), rng.normal(size=10), rng.normal(size=(2, 3))
    v64 = run(model64, pose, betas, transl=transl).vertices.numpy()
    v32 = run(model32, pose.astype(np.float32), betas.astype(np.float32), transl=transl.astype(np.float32)).vertices
    assert v32.dtype == torch.float32
    np.testing.assert_allclose(v32.numpy(), v64, atol=2e-5)


def test_half_turn_rotations(rng):
    arrays = random_model_arrays(rng)
    model = BodyModel(arrays, dtype=torch.float64)
    pose = random_pose(rng, 1, 0.3)
    axes = rng.normal(size=(NUM_JOINTS, 3))
    half_turn = [0, 4, 18, 19, 30]
    pose[0, half_turn] = np.pi * axes[half_turn] / np.linalg.norm(axes[half_turn], axis=1, keepdims=True)
    out = run(model, pose)
    verts, joints = reference_lbs(arrays, pose[0], np.zeros(10), np.zeros(10), np.zeros(3))
    assert torch.isfinite(out.vertices).all()
    np.testing.assert_allclose(out.vertices[0].numpy(), verts, atol=1e-10)
    # A half turn about a and about -a is the same rotation.
    flipped = pose.copy()
    flipped[0, half_turn] *= -1
    np.testing.assert_allclose(run(model, flipped).vertices.numpy(), out.vertices.numpy(), atol=1e-10)


def test_betas_with_one_or_n_rows(rng):
    arrays = random_model_arrays(rng)
    model = BodyModel(arrays, dtype=torch.float64)
    pose, betas = random_pose(rng, 3), rng.normal(size=10)
    flat = run(model, pose, betas).vertices
    for shaped in (betas[None], np.repeat(betas[None], 3, axis=0)):
        np.testing.assert_allclose(run(model, pose, shaped).vertices.numpy(), flat.numpy(), atol=1e-12)
    per_frame = rng.normal(size=(3, 10))
    together = run(model, pose, per_frame).vertices.numpy()
    for b in range(3):
        np.testing.assert_allclose(together[b], run(model, pose[b : b + 1], per_frame[b]).vertices[0].numpy(), atol=1e-12)
    assert not np.allclose(together[0], together[1])
    with pytest.raises(BodyModelError, match="11 betas given"):
        run(model, pose, rng.normal(size=11))


def test_model_file_errors_name_the_file(tmp_path, rng):
    arrays = random_model_arrays(rng)
    del arrays["weights"]
    path = tmp_path / "broken.npz"
    np.savez(path, **arrays)
    with pytest.raises(BodyModelError, match=r"broken\.npz.*weights"):
        BodyModel.from_file(path)
    with pytest.raises(BodyModelError, match="does not exist"):
        BodyModel.from_file(tmp_path / "missing.npz")


# ---------------------------------------------------------------- parameter files


def thuman_arrays(rng, n=4, betas_rows=1):
    return {
        "betas": rng.normal(size=(betas_rows, 10)),
        "global_orient": rng.normal(size=(n, 3)),
        "transl": rng.normal(size=(n, 3)),
        "body_pose": rng.normal(size=(n, 63)),
        "jaw_pose": rng.normal(size=(n, 3)),
        "expression": rng.normal(size=(n, 10)),
        "left_hand_pose": rng.normal(size=(n, 45)),
        "right_hand_pose": rng.normal(size=(n, 45)),
    }


@pytest.mark.parametrize("betas_rows", [1, 4])
def test_from_thuman_places_every_part(rng, betas_rows):
    arrays = thuman_arrays(rng, betas_rows=betas_rows)
    params = from_thuman(arrays, "subject/smpl_params.npz")
    assert params.full_pose.shape == (4, NUM_JOINTS, 3)
    np.testing.assert_array_equal(params.full_pose[:, 0], arrays["global_orient"])
    np.testing.assert_array_equal(params.full_pose[:, 1:22].reshape(4, 63), arrays["body_pose"])
    np.testing.assert_array_equal(params.full_pose[:, 22], arrays["jaw_pose"])
    np.testing.assert_array_equal(params.full_pose[:, 23:25], 0.0)  # THuman4 has no eye poses
    np.testing.assert_array_equal(params.full_pose[:, 25:40].reshape(4, 45), arrays["left_hand_pose"])
    np.testing.assert_array_equal(params.full_pose[:, 40:55].reshape(4, 45), arrays["right_hand_pose"])
    np.testing.assert_array_equal(params.betas, arrays["betas"][0])
    np.testing.assert_array_equal(params.expression, arrays["expression"])
    np.testing.assert_array_equal(params.transl, arrays["transl"])


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("body_pose", np.full((4, 63), np.nan), r"smpl_params\.npz: 'body_pose' contains NaN"),
        ("transl", np.full((4, 3), np.inf), r"smpl_params\.npz: 'transl' contains NaN or infinite"),
        ("body_pose", np.zeros((4, 60)), r"smpl_params\.npz: 'body_pose' has shape \(4, 60\), expected \(4, 63\)"),
        ("left_hand_pose", np.zeros((4, 12)), r"'left_hand_pose' has shape \(4, 12\), expected \(4, 45\)"),
        ("betas", np.zeros((2, 10)), r"smpl_params\.npz: 'betas' has shape \(2, 10\)"),
        ("transl", np.zeros((3, 3)), r"'transl' has shape \(3, 3\), expected \(4, 3\)"),
    ],
)
def test_from_thuman_rejects_bad_arrays(rng, key, value, message):
    arrays = thuman_arrays(rng)
    arrays[key] = value
    with pytest.raises(ParamsError, match=message):
        from_thuman(arrays, "subject/smpl_params.npz")


def test_from_thuman_requires_body_pose(rng):
    arrays = thuman_arrays(rng)
    del arrays["body_pose"]
    with pytest.raises(ParamsError, match=r"smpl_params\.npz: missing key.*body_pose"):
        from_thuman(arrays, "subject/smpl_params.npz")


def test_from_dna_takes_frame_count_from_fullpose(rng):
    fullpose = rng.normal(size=(5, NUM_JOINTS, 3))
    arrays = {"betas": rng.normal(size=(1, 10)), "fullpose": fullpose, "transl": rng.normal(size=(5, 3)),
              "expression": rng.normal(size=(5, 10))}
    params = from_dna(arrays, "0165_01_annots.smc:SMPLx")
    assert params.num_frames == 5
    np.testing.assert_array_equal(params.full_pose, fullpose)
    np.testing.assert_array_equal(params.betas, arrays["betas"][0])
    no_expression = from_dna({k: v for k, v in arrays.items() if k != "expression"}, "x")
    np.testing.assert_array_equal(no_expression.expression, np.zeros((5, 10)))


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("fullpose", np.zeros((5, 54, 3)), r"annots\.smc:SMPLx: 'fullpose' has shape \(5, 162\), expected \(5, 165\)"),
        ("fullpose", np.full((5, NUM_JOINTS, 3), np.nan), r"annots\.smc:SMPLx: 'fullpose' contains NaN"),
        ("transl", np.zeros((4, 3)), r"'transl' has shape \(4, 3\), expected \(5, 3\)"),
        ("betas", np.zeros((3, 10)), r"'betas' has shape \(3, 10\)"),
    ],
)
def test_from_dna_rejects_bad_arrays(rng, key, value, message):
    arrays = {"betas": np.zeros((1, 10)), "fullpose": np.zeros((5, NUM_JOINTS, 3)), "transl": np.zeros((5, 3))}
    arrays[key] = value
    with pytest.raises(ParamsError, match=message):
        from_dna(arrays, "0165_01_annots.smc:SMPLx")


def test_params_save_load_round_trip(tmp_path, rng):
    params = from_thuman(thuman_arrays(rng), "x")
    params.save(tmp_path / "smplx.npz", frame_ids=[3, 5, 7, 9])
    loaded, frames = SmplxParams.load(tmp_path / "smplx.npz")
    np.testing.assert_array_equal(frames, [3, 5, 7, 9])
    for name in ("full_pose", "betas", "expression", "transl"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(params, name))


def test_betas_rows_that_differ_are_reported_with_the_file(rng):
    arrays = thuman_arrays(rng, betas_rows=4)
    with pytest.warns(UserWarning, match=r"subject/smpl_params.npz: 'betas' rows differ"):
        params = from_thuman(arrays, "subject/smpl_params.npz")
    np.testing.assert_array_equal(params.betas, arrays["betas"][0])
    arrays["betas"] = np.repeat(arrays["betas"][:1], 4, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from_thuman(arrays, "subject/smpl_params.npz")
