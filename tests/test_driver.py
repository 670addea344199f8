"""Pose-driven fast path (pig.avatar.driver): the model's Gaussians, with per-avatar work done once."""

import numpy as np
import pytest
import torch

from pig.avatar.driver import AvatarDriver
from pig.body.params import SmplxParams
from pig.field.precondition import bake_preconditioning
from avatar_fixture import small_avatar


@pytest.fixture(scope="module")
def standin(tmp_path_factory):
    from pig.body.standin import write_standin

    path = tmp_path_factory.mktemp("standin") / "body_model.npz"
    write_standin(path)
    return path.read_bytes()


def _avatar(standin, refine=True):
    """A small avatar as a fit leaves it: non-zero grid, moved anchors, decoders and refiner far from zero."""
    rng = np.random.default_rng(0)
    pose = rng.normal(scale=0.2, size=(3, 55, 3))
    params = SmplxParams(pose, np.zeros(10), np.zeros((3, 10)), rng.normal(scale=0.1, size=(3, 3)))
    model = small_avatar(standin, params, refine, num_anchors=600, levels=3, sh_degree=1, hidden_layers=2, hidden_width=32)
    with torch.no_grad():
        for level in model.grid.levels:
            level.set_value(torch.randn_like(level()))
        model.anchors.set_value(model.x_init + 0.01 * torch.randn_like(model.x_init))
        for layer in [*model.decoder.modules(), *model.refiner.modules()]:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.normal_(std=0.5)
    bake_preconditioning(model)  # as the render stage does; the KNN solves would dominate these tests
    return model.eval()


@pytest.fixture(scope="module")
def avatars(standin):
    """One avatar with and one without a refiner, built once (the drivers never change them)."""
    return {refine: _avatar(standin, refine) for refine in (True, False)}


def _row(pose, transl):
    return SmplxParams(np.asarray(pose)[None], np.zeros(10), np.zeros((1, 10)), np.asarray(transl)[None])


@pytest.mark.parametrize("lod", [0, 1, 2])
@pytest.mark.parametrize("refine", [True, False])
def test_driver_equals_model_for_training_timesteps_and_pose_overrides(avatars, refine, lod):
    model = avatars[refine]
    driver = AvatarDriver(model)
    for t in range(model.num_timesteps):
        for ours, theirs in zip(driver.gaussians(lod, timestep=t), model.gaussians(t, lod)):
            torch.testing.assert_close(ours, theirs)
    # A novel pose with its translation; the 180-degree root turn is the extreme axis-angle case.
    pose = np.random.default_rng(lod).normal(scale=0.3, size=(55, 3))
    pose[0] = [0.0, np.pi, 0.0]
    transl = np.array([0.3, -0.1, 0.2])
    nearest = model.nearest_timestep(torch.as_tensor(pose))
    reference = model.gaussians(nearest, lod, _row(pose, transl))
    for ours, theirs in zip(driver.gaussians(lod, pose, transl), reference):
        torch.testing.assert_close(ours, theirs)
    # gamma(t) from a given timestep; without a translation, the timestep's own.
    t = (nearest + 1) % model.num_timesteps
    with torch.no_grad():
        g = model(torch.tensor([t]), lod, torch.as_tensor(pose)[None], None)
    for ours, theirs in zip(driver.gaussians(lod, pose, None, t), (g.means, g.quats, g.scales, g.opacities, g.sh)):
        torch.testing.assert_close(ours, theirs[0])
    if refine:  # the refined pose and shape differ from the initial ones, so the comparison above saw them
        betas, poses = driver.refined()
        assert (betas - model.betas_init).abs().max() > 1e-3 and (poses - model.pose_init).abs().max() > 1e-3


@pytest.mark.parametrize("refine", [True, False])
def test_real_time_frame_equals_the_per_pose_path(avatars, refine):
    """`frame_graph=True`: every timestep decoded up front, the nearest timestep an argmin on the device; same
    splats and timestep as the per-pose path (on the CPU the same function runs uncaptured), at every LOD, for a
    180-degree root turn, an exact training pose (distance 0) and poses between two training poses."""
    model = avatars[refine]
    driver, plain = AvatarDriver(model, frame_graph=True), AvatarDriver(model)
    rng = np.random.default_rng(5)
    train = model.pose_init.numpy()
    poses = [train[1].copy(), 0.5 * (train[0] + train[2]), rng.normal(scale=0.3, size=(55, 3))]
    poses[2][0] = [np.pi, 0.0, 0.0]
    for lod in range(model.num_levels):
        for pose, transl in zip(poses, (None, [0.1, 0.2, -0.3], [0.0, 0.0, 0.0])):
            splats, step = driver.posed_frame(lod, pose, transl)
            assert int(step) == model.nearest_timestep(torch.as_tensor(pose))
            for ours, theirs in zip(splats, plain.gaussians(lod, pose, transl)):
                torch.testing.assert_close(ours, theirs)
            for ours, theirs in zip(driver.gaussians(lod, pose, transl), splats):  # gaussians() takes this path
                assert torch.equal(ours, theirs)
    assert int(driver.posed_frame(0, train[1])[1]) == 1
    assert driver.decoded_all(0).sh.shape[:2] == (model.num_timesteps, model.level_sizes[0])


def test_real_time_frame_over_its_budget_decodes_its_timestep(avatars):
    """Over the budget the frame decodes the nearest timestep itself: the per-pose path's splats, no stacked cache."""
    model = avatars[False]
    driver = AvatarDriver(model, frame_graph=True, decoded_budget_bytes=1000)
    need = driver.decoded_all_bytes(2)
    assert need == model.num_timesteps * model.level_sizes[2] * (3 + 4 + 3 + 1 + 3 * 4) * 4
    assert not driver.frame_graph_fits(2)
    pose = model.pose_init[2].numpy() + 0.05
    splats, step = driver.posed_frame(2, pose, [0.1, 0.0, 0.2])
    assert int(step) == model.nearest_timestep(torch.as_tensor(pose)) == 2
    for ours, theirs in zip(splats, AvatarDriver(model).gaussians(2, pose, [0.1, 0.0, 0.2])):
        torch.testing.assert_close(ours, theirs)
    assert 2 not in driver._decoded_all


def test_the_decoded_budget_bounds_the_levels_held_together(avatars):
    """A level that fits the budget alone but not beside the levels already held decodes in its frames instead."""
    model = avatars[False]
    budget = AvatarDriver(model).decoded_all_bytes(2)
    driver = AvatarDriver(model, frame_graph=True, decoded_budget_bytes=budget)
    pose = model.pose_init[1].numpy()
    driver.posed_frame(2, pose)
    assert driver.frame_graph_fits(2) and list(driver._decoded_all) == [2]
    assert driver.decoded_all_bytes(0) < budget and not driver.frame_graph_fits(0)
    for ours, theirs in zip(driver.posed_frame(0, pose)[0], AvatarDriver(model).gaussians(0, pose)):
        torch.testing.assert_close(ours, theirs)
    assert list(driver._decoded_all) == [2]
    first_coarse = AvatarDriver(model, frame_graph=True, decoded_budget_bytes=budget)
    first_coarse.posed_frame(0, pose)
    assert list(first_coarse._decoded_all) == [0] and not first_coarse.frame_graph_fits(2)


@pytest.mark.parametrize("budget", [8 << 30, 0])
@pytest.mark.parametrize("refine", [True, False])
def test_timestep_frame_equals_the_per_timestep_path(avatars, refine, budget):
    """A training timestep in its refined pose through the frame function (the novel-view split's frames), its
    attributes gathered from every timestep decoded up front or, with no budget, decoded in the frame: the
    per-timestep path's splats at every LOD and timestep (the first and the last included), and gaussians() with
    only a timestep takes it."""
    model = avatars[refine]
    driver, plain = AvatarDriver(model, frame_graph=True, decoded_budget_bytes=budget), AvatarDriver(model)
    for lod in range(model.num_levels):
        for t in range(model.num_timesteps):
            splats = driver.timestep_frame(lod, t)
            for ours, theirs in zip(splats, plain.gaussians(lod, timestep=t)):
                torch.testing.assert_close(ours, theirs)
            for ours, theirs in zip(driver.gaussians(lod, timestep=t), splats):
                assert torch.equal(ours, theirs)
    assert sorted(driver._decoded_all) == ([] if budget == 0 else list(range(model.num_levels)))
    with pytest.raises(ValueError, match=r"timestep must lie in 0\.\.2, got 3"):
        driver.timestep_frame(0, model.num_timesteps)


class _Counter:
    def __init__(self, module):
        self.calls = 0
        self.handle = module.register_forward_hook(self)

    def __call__(self, *args):
        self.calls += 1


@pytest.mark.parametrize("refine", [True, False])
def test_grid_once_per_lod_refiner_once_decoders_once_per_lod_and_timestep(avatars, refine):
    model = avatars[refine]
    counters = grid, anchors, refiner, decoder = [_Counter(m) for m in (model.grid, model.anchors, model.refiner, model.decoder)]
    driver = AvatarDriver(model, decoded_cache=100)
    rng = np.random.default_rng(2)
    for _ in range(2):
        for lod in range(model.num_levels):
            for t in (0, 1):
                driver.gaussians(lod, rng.normal(scale=0.2, size=(55, 3)), None, t)
            driver.gaussians(lod, timestep=0)
    # With a refiner, z_bar needs every anchor: one grid evaluation serves all levels.
    assert grid.calls == (1 if refine else model.num_levels)
    assert anchors.calls == 1 and refiner.calls == (1 if refine else 0)
    assert decoder.calls == model.num_levels * 2
    # A cache of one (LOD, timestep) decodes again whenever the pair changes.
    decoder.calls = 0
    small = AvatarDriver(model, decoded_cache=1)
    for t in (0, 0, 1, 1, 0):
        small.gaussians(0, timestep=t)
    assert decoder.calls == 3
    for counter in counters:
        counter.handle.remove()


def test_nearest_timestep_once_per_pose(avatars, monkeypatch):
    model = avatars[False]
    calls = []
    original = model.nearest_timestep
    monkeypatch.setattr(model, "nearest_timestep", lambda pose: calls.append(1) or original(pose))
    driver = AvatarDriver(model)
    a = model.pose_init[2].numpy() + 1e-3
    b = model.pose_init[0].numpy().copy()
    steps = [driver.nearest_timestep(p) for p in (a, b, a.copy(), torch.as_tensor(a), b, a)]
    assert steps == [2, 0, 2, 2, 0, 2] and len(calls) == 2
    driver.gaussians(1, a)  # the frame path reuses the cached timestep
    assert len(calls) == 2
    driver.forget_poses()
    assert driver.nearest_timestep(a) == 2 and len(calls) == 3


def test_bad_inputs_get_clear_errors(avatars):
    driver = AvatarDriver(avatars[False])
    pose = np.zeros((55, 3))
    with pytest.raises(ValueError, match=r"expected a \(55, 3\) axis-angle pose, found shape \(54, 3\)"):
        driver.gaussians(0, np.zeros((54, 3)))
    nan = pose.copy()
    nan[3, 1] = np.nan
    with pytest.raises(ValueError, match="pose holds NaN"):
        driver.gaussians(0, nan)
    with pytest.raises(ValueError, match="translation holds NaN"):
        driver.gaussians(0, pose, [0.0, np.inf, 0.0])
    with pytest.raises(ValueError, match=r"expected a \(3,\) translation, found shape \(2,\)"):
        driver.gaussians(0, pose, [0.0, 1.0])
    with pytest.raises(ValueError, match=r"lod must lie in 0..2, got 3"):
        driver.gaussians(3, timestep=0)
    with pytest.raises(ValueError, match=r"timestep must lie in 0..2, got 3"):
        driver.gaussians(0, timestep=3)
    with pytest.raises(ValueError, match="needs a timestep, a pose, or both"):
        driver.gaussians(0)
    with pytest.raises(ValueError, match="cache sizes must be >= 0"):
        AvatarDriver(driver.model, decoded_cache=-1)


# ---- render stage (slow: generated capture + a short fit) ----


@pytest.fixture(scope="module")
def fitted(tiny_fit):
    return tiny_fit


@pytest.mark.slow
def test_render_stage_images_match_the_model_path(fitted):
    from pig.avatar.checkpoint import load_avatar
    from pig.data.capture import Capture
    from pig.render.api import RasterizerConfig, render_gaussians
    from pig.stages.render import BLACK, SplitRenderer

    capture_dir, checkpoint = fitted
    capture = Capture.load(capture_dir)
    model = load_avatar(checkpoint)
    bake_preconditioning(model)
    for split in ("train", "novel_pose"):
        cameras, frames = capture.split[split]["cameras"][:2], [int(f) for f in capture.split[split]["frames"]][:2]
        renderer = SplitRenderer(model, capture, cameras, torch.device("cpu"), RasterizerConfig(backend="cpu"))
        for lod in range(model.num_levels):
            for frame in frames:
                # The model path the render stage took before the driver.
                if frame in model.frame_ids:
                    timestep, row = model.timestep_of_frame(frame), None
                else:
                    row = capture.params.select([list(capture.frames).index(frame)])
                    timestep = model.nearest_timestep(row.full_pose[0])
                splats = [t.float() for t in model.gaussians(timestep, lod, row)]
                for name, result, c in renderer.render(frame, lod):
                    cam = capture.cameras[name]
                    viewmat = torch.as_tensor(cam.viewmat(), dtype=torch.float32)[None]
                    K = torch.as_tensor(cam.K, dtype=torch.float32)[None]
                    old = render_gaussians(*splats, viewmat, K, cam.width, cam.height, torch.tensor(BLACK), backend="cpu")
                    assert old.alpha.max() > 0.1, "nothing rendered: the comparison would be empty"
                    difference = (result.color[c] - old.color[0]).abs().mean().item()
                    assert difference < 1e-3, (split, lod, frame, name, difference)
