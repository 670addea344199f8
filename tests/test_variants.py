"""Method variants of issue 13: the template-bound baseline, offsets in the anchor's frame, the single-level model.

Each is a row of every preset's `variants:` section, builds from its overrides and trains for a few iterations.
"""
import math

import numpy as np
import pandas as pd
import pytest
import torch

from pig.avatar.checkpoint import load_avatar
from pig.avatar.config import AvatarConfig
from pig.avatar.driver import AvatarDriver
from pig.avatar.variants import variant_overrides
from pig.body.params import SmplxParams
from pig.body.rotation import axis_angle_to_matrix, matrix_to_axis_angle
from pig.body.transport import barycentric_points
from pig.config import ConfigError, derive_preset, from_dict, load_preset, load_section
from avatar_fixture import small_avatar

NEW_VARIANTS = ("template_bound", "local_offsets", "lod_1of1")


@pytest.fixture(scope="module")
def standin(tmp_path_factory):
    from pig.body.standin import write_standin

    path = tmp_path_factory.mktemp("standin") / "body_model.npz"
    write_standin(path)
    return path.read_bytes()


def _model(standin, refine: bool, **avatar):
    """A 3-timestep avatar on the stand-in body with `avatar` overrides."""
    rng = np.random.default_rng(0)
    pose = rng.normal(scale=0.2, size=(3, 55, 3))
    params = SmplxParams(pose, np.zeros(10), np.zeros((3, 10)), np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], float))
    return small_avatar(standin, params, refine, num_anchors=400, levels=2, sh_degree=0, hidden_layers=1, hidden_width=16,
                        **avatar)


def _posed_template(model, steps: torch.Tensor, lod: int, poses=None) -> torch.Tensor:
    """Vertices (K, V, 3) of the body the model poses: refined shape, refined pose or `poses`."""
    with torch.no_grad():
        z_mean = model.anchor_features(model.canonical_anchors(), lod)[1]
        betas, pose = model.refined_params(steps, z_mean)
        if poses is not None:
            pose = poses
        return model.body_model(pose, betas, model.expression[steps], model.transl[steps]).vertices


def _surface_points(model, steps: torch.Tensor, lod: int, poses=None) -> np.ndarray:
    """The level's attachment points on the posed template, by barycentric sums in float64 numpy."""
    n = model.level_sizes[lod]
    triangles = model.body_model.faces.numpy()[model.face_ids[:n].numpy()]
    corners = _posed_template(model, steps, lod, poses).double().numpy()[:, triangles]  # (K, n, 3, 3)
    return np.einsum("nc,kncx->knx", model.bary[:n].double().numpy(), corners)


# ---- the presets ----


@pytest.mark.parametrize("preset", ["paper", "cpu-demo", "test"])
def test_every_preset_defines_the_new_variants_as_valid_overrides(preset):
    data = load_preset(preset)
    for name in NEW_VARIANTS:
        cfg = load_section(data, "avatar", AvatarConfig, variant_overrides(data, name).get("avatar"))
        base = load_section(data, "avatar", AvatarConfig)
        if name == "template_bound":
            assert (cfg.learn_anchors, cfg.offsets) == (False, False)
        elif name == "local_offsets":
            assert cfg.offset_frame == "local" and base.offset_frame == "world"
        else:  # all anchors in one level: the paper's 1/1 row has the full count
            assert cfg.levels == 1 and cfg.num_anchors == base.num_anchors and base.levels > 1


def test_offset_frame_is_checked():
    with pytest.raises(ConfigError, match=r"avatar\.offset_frame: expected one of \['world', 'local'\], found 'surface'"):
        from_dict(AvatarConfig, {"offset_frame": "surface"}, "avatar")
    with pytest.raises(ValueError, match="avatar.offset_frame must be 'world' or 'local', got 'canonical'"):
        AvatarConfig(offset_frame="canonical")


# ---- template_bound: splat centres are the skinned template's surface points ----


@pytest.mark.parametrize("lod", [0, 1])
def test_template_bound_centres_are_the_skinned_template_surface_points(standin, lod):
    model = _model(standin, refine=True, learn_anchors=False, offsets=False)
    assert model.anchors is None
    with torch.no_grad():  # a non-zero raw offset output, which the baseline must ignore
        model.decoder.shape[-1].bias[:3] = torch.tensor([3.0, -2.0, 1.0])
    steps = torch.tensor([0, 2])
    with torch.no_grad():
        means = model(steps, lod).means
    np.testing.assert_allclose(means.double().numpy(), _surface_points(model, steps, lod), rtol=0, atol=2e-6)
    # Exactly, not up to a small residual: x(theta) = x_init(theta) + R (x_init - x_init), plus no offset.
    n = model.level_sizes[lod]
    surface = barycentric_points(_posed_template(model, steps, lod), model.body_model.faces, model.face_ids[:n], model.bary[:n])
    assert torch.equal(means, surface)
    # A novel pose too: the query pose drives the template and the centres stay on it.
    poses = model.pose_init[:1].clone()
    poses[0, 0] = torch.tensor([0.0, math.pi, 0.0])
    with torch.no_grad():
        means = model(steps[:1], lod, poses=poses).means
    np.testing.assert_allclose(means.double().numpy(), _surface_points(model, steps[:1], lod, poses), rtol=0, atol=2e-6)
    # The full method's centres leave the surface by the decoded offset (the check above can fail).
    free = _model(standin, refine=True)
    with torch.no_grad():
        free.decoder.shape[-1].bias[:3] = torch.tensor([3.0, -2.0, 1.0])
        gap = np.abs(free(steps, lod).means.double().numpy() - _surface_points(free, steps, lod)).max()
    assert gap > 0.01


# ---- local_offsets: the offset turns with the body ----


def _rotated_global(pose: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """`pose` (55, 3) with its global orientation turned by `rotation` (3, 3) in world space."""
    turned = pose.clone()
    turned[0] = matrix_to_axis_angle(rotation @ axis_angle_to_matrix(pose[0]))
    return turned


def _offsets(model, step: int, pose: torch.Tensor) -> torch.Tensor:
    """Splat centre minus transported anchor (mu - x(theta), Eq. 10) of the finest level under `pose`, (n, 3)."""
    steps = torch.tensor([step])
    lod = model.num_levels - 1
    with torch.no_grad():
        means = model(steps, lod, poses=pose[None]).means[0]
        vertices = model.body_model(pose[None], model.betas_init, model.expression[steps], model.transl[steps]).vertices
        centres, _ = model.transport(model.canonical_anchors(), vertices, lod)
    return means - centres[0]


@pytest.mark.parametrize("axis", [[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.3, -0.5, 0.8]])
def test_local_offsets_turn_with_a_half_turned_body_and_world_offsets_do_not(standin, axis):
    """A 180-degree turn of the global orientation turns the posed body rigidly by Q: local offsets become
    Q d, world offsets stay d; both finite."""
    axis = torch.tensor(axis) / torch.tensor(axis).norm()
    half_turn = axis_angle_to_matrix(math.pi * axis)
    # Q is a half turn: Q = 2 a a^T - I, closed form.
    torch.testing.assert_close(half_turn, 2 * torch.outer(axis, axis) - torch.eye(3), atol=1e-6, rtol=0)
    for frame in ("local", "world"):
        model = _model(standin, refine=False, offset_frame=frame)
        with torch.no_grad():  # offsets of a few centimetres, varying per anchor through the MLP
            model.decoder.shape[-1].bias[:3] = torch.tensor([0.4, -0.6, 0.5])
        pose = model.pose_init[1]
        before, after = _offsets(model, 1, pose), _offsets(model, 1, _rotated_global(pose, half_turn))
        assert torch.isfinite(before).all() and torch.isfinite(after).all()
        assert before.norm(dim=-1).min() > 0.01
        turned = before @ half_turn.T
        if frame == "local":
            torch.testing.assert_close(after, turned, atol=2e-5, rtol=0)
        else:
            torch.testing.assert_close(after, before, atol=2e-5, rtol=0)
            assert (after - turned).norm(dim=-1).min() > 0.01


def test_local_offsets_are_the_transport_rotation_times_the_decoded_offset(standin):
    """mu = x(theta) + R d mu per anchor, R the anchor's transport rotation (Eq. 3); the driver agrees."""
    model = _model(standin, refine=False, offset_frame="local")
    with torch.no_grad():
        model.decoder.shape[-1].bias[:3] = torch.tensor([0.4, -0.6, 0.5])
    pose = _rotated_global(model.pose_init[2], axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi])))
    steps, lod = torch.tensor([2]), 1
    with torch.no_grad():
        vertices = model.body_model(pose[None], model.betas_init, model.expression[steps], model.transl[steps]).vertices
        _, rotation = model.transport(model.canonical_anchors(), vertices, lod)
        decoded = model.decode(model.anchor_features(model.canonical_anchors(), lod)[0], steps, lod).offset
    expected = np.einsum("nij,nj->ni", rotation[0].double().numpy(), decoded[0].double().numpy())
    np.testing.assert_allclose(_offsets(model, 2, pose).double().numpy(), expected, rtol=0, atol=2e-6)
    driven = AvatarDriver(model).gaussians(lod, pose=pose, timestep=2)[0]
    torch.testing.assert_close(driven, model(steps, lod, poses=pose[None]).means[0].detach())


# ---- each new variant fits for a few iterations ----


@pytest.fixture(scope="module")
def short_preset(tmp_path_factory):
    return str(derive_preset(tmp_path_factory.mktemp("variants") / "preset.yaml", "test",
                             fit={"iterations": 2, "eval_every": 2, "eval_frames": 1, "checkpoint_minutes": 0.0}))


@pytest.mark.parametrize("variant", NEW_VARIANTS)
def test_new_variant_fits_a_few_iterations(small_capture, short_preset, tmp_path, variant):
    from pig.avatar.training import fit

    model = load_avatar(fit(small_capture, tmp_path / variant, short_preset, variant=variant))
    log = pd.read_csv(tmp_path / variant / "train_log.csv")
    assert log["iteration"].iloc[-1] == 2 and np.isfinite(log["heldout_psnr"].dropna()).all()
    anchors = load_section(load_preset(short_preset), "avatar", AvatarConfig).num_anchors
    if variant == "lod_1of1":
        assert model.level_sizes == [anchors]
    else:
        assert model.level_sizes[-1] == anchors and model.num_levels == 2
    assert model.cfg.offset_frame == ("local" if variant == "local_offsets" else "world")
    if variant == "template_bound":  # trained, the centres are still the template's surface points
        steps = torch.tensor([0, 1])
        with torch.no_grad():
            means = model(steps, 1).means
        np.testing.assert_allclose(means.double().numpy(), _surface_points(model, steps, 1), rtol=0, atol=2e-6)
