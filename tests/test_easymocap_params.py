"""EasyMocap's SMPL-X parameterisation -> standard SMPL-X (pig.body.easymocap), held to EasyMocap's own definition
of the posed body, `V = R(Rh) X(poses, shapes, expression) + Th` (its `doc/02_output.md`), on the stand-in body
model with random shapes, expressions and rotations up to 180 degrees, in float64."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pig.body.easymocap import hand_components_of, to_standard
from pig.body.model import BodyModel, BodyModelError
from pig.body.params import ParamsError
from pig.body.standin import make_standin_arrays


@pytest.fixture(scope="module")
def arrays():
    """The stand-in's arrays with a mean hand, and an expression direction that moves the whole body (so the
    pelvis depends on the expression, as the conversion must account for)."""
    arrays = make_standin_arrays(0)
    rng = np.random.default_rng(7)
    arrays["hands_meanl"] = rng.normal(scale=0.3, size=45)
    arrays["hands_meanr"] = rng.normal(scale=0.3, size=45)
    arrays["shapedirs"] = arrays["shapedirs"].copy()
    arrays["shapedirs"][:, :, 10] += np.array([0.01, 0.02, -0.015])
    return arrays


@pytest.fixture(scope="module")
def model(arrays):
    return BodyModel(arrays, dtype=torch.float64)


def _easymocap_vertices(model, arrays, Rh, Th, poses, shapes, expression, k, flat_hand_mean):
    """EasyMocap's body written out joint by joint from its definition: the pose expanded by hand (hand PCA rows
    of the model file, its mean hand where not flat), posed about the origin frame of the model, then rotated by
    Rh (scipy) and moved by Th."""
    n = len(poses)
    full = np.zeros((n, 55, 3))
    for i in range(n):
        if k == 0:
            full[i] = poses[i].reshape(55, 3)
        else:
            body, left, right, head = np.split(poses[i], [66, 66 + k, 66 + 2 * k])
            full[i, :22] = body.reshape(22, 3)
            full[i, 22:25] = head.reshape(3, 3)
            full[i, 25:40] = sum(left[c] * arrays["hands_componentsl"][c] for c in range(k)).reshape(15, 3)
            full[i, 40:55] = sum(right[c] * arrays["hands_componentsr"][c] for c in range(k)).reshape(15, 3)
        if not flat_hand_mean:
            full[i, 25:40] += arrays["hands_meanl"].reshape(15, 3)
            full[i, 40:55] += arrays["hands_meanr"].reshape(15, 3)
    X = model(torch.from_numpy(full), torch.from_numpy(shapes)[None], torch.from_numpy(expression)).vertices.numpy()
    rotations = Rotation.from_rotvec(Rh).as_matrix()
    return np.einsum("nij,nvj->nvi", rotations, X) + Th[:, None]


def _random_fit(rng, n, length, root_zero=True):
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0, np.pi, size=n)
    angles[0] = np.pi  # exactly 180 degrees
    angles[1] = np.pi - 1e-9
    Rh = axes * angles[:, None]
    poses = rng.normal(scale=0.3, size=(n, length))
    if root_zero:
        poses[:, :3] = 0
    return (Rh, rng.normal(scale=[1.0, 0.3, 1.0], size=(n, 3)), poses, rng.normal(size=10),
            rng.normal(size=(n, 10)))


@pytest.mark.parametrize("length, k", [(87, 6), (165, 0), (77, 1), (163, 44), (111, 18)])
@pytest.mark.parametrize("flat_hand_mean", [True, False])
def test_standard_parameters_pose_the_same_vertices(model, arrays, length, k, flat_hand_mean):
    rng = np.random.default_rng(length + 1000 * flat_hand_mean)
    Rh, Th, poses, shapes, expression = _random_fit(rng, 6, length, root_zero=length != 165)
    params = to_standard(Rh, Th, poses, shapes, expression, model, flat_hand_mean)
    standard = model(torch.from_numpy(params.full_pose), torch.from_numpy(params.betas)[None],
                     torch.from_numpy(params.expression), torch.from_numpy(params.transl)).vertices.numpy()
    reference = _easymocap_vertices(model, arrays, Rh, Th, poses, shapes, expression, k, flat_hand_mean)
    assert np.abs(standard - reference).max() < 1e-5
    # The translation is not Th: a body rotated about the origin is not one rotated about its pelvis.
    assert np.abs(params.transl - Th).max() > 1e-2


def test_a_nonzero_stored_root_composes_with_rh(model, arrays):
    """EasyMocap keeps poses[:3] zero, but a fit that stores a root there is rotated by it first, then by Rh."""
    rng = np.random.default_rng(3)
    Rh, Th, poses, shapes, expression = _random_fit(rng, 5, 87, root_zero=False)
    params = to_standard(Rh, Th, poses, shapes, expression, model)
    standard = model(torch.from_numpy(params.full_pose), torch.from_numpy(params.betas)[None],
                     torch.from_numpy(params.expression), torch.from_numpy(params.transl)).vertices.numpy()
    reference = _easymocap_vertices(model, arrays, Rh, Th, poses, shapes, expression, 6, True)
    assert np.abs(standard - reference).max() < 1e-5
    expected_root = (Rotation.from_rotvec(Rh) * Rotation.from_rotvec(poses[:, :3])).as_matrix()
    np.testing.assert_allclose(Rotation.from_rotvec(params.full_pose[:, 0]).as_matrix(), expected_root, atol=1e-9)


def test_translation_in_closed_form(model):
    """transl = Th + R(Rh) J0 - J0 with J0 the pelvis of the body shaped by betas and expression, computed here from
    the model's arrays directly (shape blend, then the pelvis row of the joint regressor)."""
    rng = np.random.default_rng(5)
    Rh, Th, poses, shapes, expression = _random_fit(rng, 3, 87)
    params = to_standard(Rh, Th, poses, shapes, expression, model)
    coeffs = np.concatenate([np.broadcast_to(shapes, (3, 10)), expression], axis=1)
    shapedirs = model.shapedirs.numpy()
    rest = model.v_template.numpy() + np.einsum("vcs,ns->nvc", shapedirs, coeffs)
    j0 = np.einsum("v,nvc->nc", model.j_regressor.numpy()[0], rest)
    expected = Th + np.einsum("nij,nj->ni", Rotation.from_rotvec(Rh).as_matrix(), j0) - j0
    np.testing.assert_allclose(params.transl, expected, atol=1e-12)


@pytest.mark.parametrize("length, expected", [(87, 6), (165, 0), (77, 1), (163, 44), (79, 2)])
def test_component_count_from_the_length(length, expected):
    assert hand_components_of(length, "x.json") == expected


@pytest.mark.parametrize("length, words", [(72, "an SMPL fit"), (78, r"an SMPL\+H fit"), (75, "no SMPL-X form"),
                                           (86, "no SMPL-X form"), (164, "no SMPL-X form"), (166, "no SMPL-X form"),
                                           (0, "no SMPL-X form")])
def test_lengths_that_fit_no_form_are_refused(length, words):
    with pytest.raises(ParamsError, match=words) as err:
        hand_components_of(length, "smplx/000003.json")
    assert "smplx/000003.json" in str(err.value)


def test_pca_needs_the_model_components(arrays):
    plain = {k: v for k, v in arrays.items() if not k.startswith("hands_components")}
    model = BodyModel(plain, source="plain.npz", dtype=torch.float64)
    assert not model.has_hand_components
    rng = np.random.default_rng(0)
    fit = _random_fit(rng, 2, 87)
    with pytest.raises(ParamsError, match="plain.npz has no 'hands_componentsl'"):
        to_standard(*fit, model)
    to_standard(*_random_fit(rng, 2, 165), model)  # the full form needs none


def test_malformed_components_are_refused(arrays):
    bad = dict(arrays, hands_componentsl=np.zeros((6, 44)))
    with pytest.raises(BodyModelError, match="'hands_componentsl' has shape"):
        BodyModel(bad, source="bad.npz")
    fewer = dict(arrays, hands_componentsl=arrays["hands_componentsl"][:6],
                 hands_componentsr=arrays["hands_componentsr"][:6])
    model = BodyModel(fewer, source="six.npz", dtype=torch.float64)
    with pytest.raises(ParamsError, match="only 6 hand components"):
        to_standard(*_random_fit(np.random.default_rng(1), 2, 66 + 2 * 12 + 9), model)


def test_body_model_file_loads_the_components(tmp_path, arrays):
    path = tmp_path / "model.npz"
    np.savez(path, **arrays)
    model = BodyModel.from_file(path, dtype=torch.float64)
    np.testing.assert_array_equal(model.hands_components[0].numpy(), arrays["hands_componentsl"])
    np.testing.assert_array_equal(model.hands_components[1].numpy(), arrays["hands_componentsr"])
