"""The procedural stand-in body: SMPL-X layout, a closed genus-0 surface, human proportions, usable skinning and shape."""
import numpy as np
import pytest
import torch
import trimesh

from pig.body.model import NUM_JOINTS, SMPLX_JOINT_NAMES, SMPLX_PARENTS, BodyModel
from pig.body.standin import make_standin_arrays, write_standin

J = {name: i for i, name in enumerate(SMPLX_JOINT_NAMES)}
LEFT = [i for i, n in enumerate(SMPLX_JOINT_NAMES) if n.startswith("left")]
RIGHT = [i for i, n in enumerate(SMPLX_JOINT_NAMES) if n.startswith("right")]


@pytest.fixture(scope="module")
def arrays():
    return make_standin_arrays(0)


@pytest.fixture(scope="module")
def mesh(arrays):
    return trimesh.Trimesh(arrays["v_template"], arrays["f"], process=False)


@pytest.fixture(scope="module")
def model(arrays):
    return BodyModel(arrays, dtype=torch.float64)


def rest_joints(arrays):
    return arrays["J_regressor"] @ arrays["v_template"]


def shaped(model, betas=None, expression=None):
    with torch.no_grad():
        zero = torch.zeros(1, NUM_JOINTS, 3, dtype=torch.float64)
        out = model(zero, None if betas is None else torch.as_tensor(betas), None if expression is None else torch.as_tensor(expression))
    return out.shaped_vertices[0].numpy()


def test_smplx_layout(arrays):
    v = len(arrays["v_template"])
    assert 3000 <= v <= 15000
    assert arrays["shapedirs"].shape == (v, 3, 20)
    assert arrays["posedirs"].shape == (v, 3, 486) and not arrays["posedirs"].any()
    assert arrays["J_regressor"].shape == (NUM_JOINTS, v) and arrays["weights"].shape == (v, NUM_JOINTS)
    np.testing.assert_array_equal(arrays["kintree_table"][0], SMPLX_PARENTS)
    np.testing.assert_array_equal(arrays["hands_meanl"], np.zeros(45))
    np.testing.assert_array_equal(arrays["hands_meanr"], np.zeros(45))
    for key in ("J_regressor", "weights"):
        rows = arrays[key]
        assert rows.min() >= 0
        np.testing.assert_allclose(rows.sum(axis=1), 1.0, atol=1e-12)


def test_loads_as_body_model_with_ten_betas_and_expressions(model):
    assert model.num_betas == 10 and model.num_expression == 10


def test_surface_is_closed_genus_zero_and_outward(mesh):
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 2  # one sphere-like surface, no handles between fingers
    assert len(mesh.split(only_watertight=False)) == 1
    assert mesh.volume > 0  # outward normals
    assert mesh.area_faces.min() > 1e-8  # no slivers for the transport's triangle frames


def test_human_proportions_y_up_facing_z(arrays, mesh):
    joints = rest_joints(arrays)
    low, high = mesh.bounds
    height = high[1] - low[1]
    assert 1.6 < height < 1.85
    assert 0.9 < (high[0] - low[0]) / height < 1.15  # T-pose arm span ~ stature
    assert joints[J["head"], 1] > joints[J["neck"], 1] > joints[J["spine3"], 1] > joints[J["pelvis"], 1]
    assert joints[J["pelvis"], 1] > joints[J["left_knee"], 1] > joints[J["left_ankle"], 1]
    # The person's left is +x, the face looks along +z, arms lie along x at shoulder height.
    assert joints[J["left_wrist"], 0] > 0.6 and joints[J["right_wrist"], 0] < -0.6
    assert abs(joints[J["left_wrist"], 1] - joints[J["left_shoulder"], 1]) < 0.05
    assert joints[J["left_eye"], 2] > joints[J["head"], 2] + 0.05
    assert joints[J["left_foot"], 2] > joints[J["left_ankle"], 2] + 0.05  # toes point forward
    for finger in ("index", "middle", "ring", "pinky", "thumb"):
        tip, base = joints[J[f"left_{finger}3"]], joints[J[f"left_{finger}1"]]
        assert np.linalg.norm(tip - base) > 0.04
    np.testing.assert_allclose(joints[LEFT] * [-1, 1, 1], joints[RIGHT], atol=1e-9)  # mirror symmetric


def test_joints_regressed_inside_the_body(arrays, mesh):
    assert mesh.contains(rest_joints(arrays)).all()


def test_weights_smooth_and_sided(arrays, mesh):
    weights = arrays["weights"]
    edges = mesh.edges_unique
    step = np.abs(weights[edges[:, 0]] - weights[edges[:, 1]]).sum(axis=1)
    assert step.max() < 1.0  # hard part labels would jump by 2 across every seam
    assert (weights.max(axis=1) < 0.999).mean() > 0.2  # a real share of vertices is blended
    x = arrays["v_template"][:, 0]
    assert weights[x > 0.3][:, RIGHT].max() == 0 and weights[x < -0.3][:, LEFT].max() == 0


def test_elbow_bend_moves_only_the_forearm(model, arrays):
    pose = torch.zeros(1, NUM_JOINTS, 3, dtype=torch.float64)
    pose[0, J["left_elbow"], 1] = -np.pi / 2
    with torch.no_grad():
        posed = model(pose).vertices[0].numpy()
    moved = np.linalg.norm(posed - arrays["v_template"], axis=1) > 1e-9
    x = arrays["v_template"][:, 0]
    assert moved[x > 0.75].all() and not moved[x < 0.2].any()
    hand = x > 0.8
    assert np.linalg.norm(posed[hand] - arrays["v_template"][hand], axis=1).min() > 0.2


def test_shape_directions_change_height_and_girth(model, mesh, arrays):
    rest = shaped(model)
    np.testing.assert_allclose(rest, arrays["v_template"], atol=1e-12)
    taller = shaped(model, np.eye(10)[0])
    assert 0.04 < np.ptp(taller[:, 1]) - np.ptp(rest[:, 1]) < 0.09
    wider = shaped(model, np.eye(10)[1])
    volume = trimesh.Trimesh(wider, arrays["f"], process=False).volume
    assert volume > 1.1 * mesh.volume
    assert abs(np.ptp(wider[:, 1]) - np.ptp(rest[:, 1])) < 0.01
    # Every direction does something, and shortening is the negative of lengthening.
    for k in range(10):
        assert np.abs(shaped(model, np.eye(10)[k]) - rest).max() > 0.005
    shorter = shaped(model, -np.eye(10)[0])
    np.testing.assert_allclose(shorter - rest, rest - taller, atol=1e-12)


def test_expressions_only_move_the_face(model, arrays):
    joints = rest_joints(arrays)
    rest = shaped(model)
    for k in range(10):
        moved = np.linalg.norm(shaped(model, None, np.eye(10)[k][None]) - rest, axis=1)
        assert moved.max() > 0.003
        assert moved[arrays["v_template"][:, 1] < joints[J["neck"], 1]].max() == 0


def test_seed_picks_free_directions_only(arrays):
    other, base = make_standin_arrays(1), arrays
    np.testing.assert_array_equal(other["v_template"], base["v_template"])
    np.testing.assert_array_equal(other["weights"], base["weights"])
    np.testing.assert_array_equal(other["shapedirs"][..., :5], base["shapedirs"][..., :5])
    assert not np.allclose(other["shapedirs"][..., 5:], base["shapedirs"][..., 5:])


def test_write_standin_round_trip(tmp_path, arrays):
    path = write_standin(tmp_path / "models" / "standin.npz")
    assert [p.name for p in path.parent.iterdir()] == ["standin.npz"]  # no temporary left behind
    loaded = BodyModel.from_file(path, dtype=torch.float64)
    np.testing.assert_array_equal(loaded.v_template.numpy(), arrays["v_template"])
    np.testing.assert_array_equal(loaded.faces.numpy(), arrays["f"])
