"""Avatar model + fit stage: masked loss, gradient flow to every group, novel-pose override, short fit, resume."""
from dataclasses import asdict

import cv2
import numpy as np
import pytest
import torch
import yaml

from pig.avatar.build import build_avatar
from pig.avatar.checkpoint import load_avatar
from pig.avatar.config import AvatarConfig
from pig.avatar.losses import band_radius, boundary_band, boundary_band_host, image_loss
from pig.body.params import SmplxParams
from pig.field.latent_grid import FieldConfig
from pig.field.precondition import PrecondConfig
from pig.render.api import render_gaussians
from avatar_fixture import small_avatar
from preset_files import write_test_preset


def test_boundary_band_matches_opencv_dilate_minus_erode(rng):
    mask = np.zeros((4, 40, 50), np.uint8)
    mask[0, 10:30, 5:20] = 1
    mask[1] = rng.random((40, 50)) > 0.6
    mask[3] = 1  # [2] empty: no band; [3] full: no band either (the outside is left out)
    tiny = (rng.random((2, 2, 3)) > 0.5).astype(np.uint8)  # smaller than the window
    for masks in (mask, tiny):
        for r in (1, 3, 5):
            kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
            # OpenCV's default border for dilate/erode leaves the outside out of both operations.
            expected = np.stack([cv2.dilate(m, kernel).astype(bool) & ~cv2.erode(m, kernel, borderType=cv2.BORDER_REPLICATE).astype(bool)
                                 for m in masks])
            np.testing.assert_array_equal(boundary_band(torch.tensor(masks, dtype=torch.bool), r).numpy(), expected)
            for m, band in zip(masks.astype(bool), expected):  # the loader threads' form (fit.host_band)
                np.testing.assert_array_equal(boundary_band_host(m, r), band)
    assert not boundary_band(torch.tensor(mask, dtype=torch.bool), 0).any()
    assert not boundary_band_host(mask[0].astype(bool), 0).any() and boundary_band_host(mask[0].astype(bool), 0).shape == (40, 50)
    assert not boundary_band(torch.tensor(mask[2:], dtype=torch.bool), 3).any()
    assert band_radius(1150, 3.0, 1150) == 3 and band_radius(256, 3.0, 1150) == 1 and band_radius(64, 3.0, 1150) == 0


def test_loss_ignores_band_pixels_and_matches_closed_form(rng):
    target = torch.tensor(rng.random((2, 24, 24, 3)), dtype=torch.float32)
    render = target.clone()
    band = torch.zeros(2, 24, 24, dtype=torch.bool)
    band[:, 5:9] = True
    render[band] = 0.9  # differs only inside the band
    bg = torch.tensor([0.2, 0.3, 0.4])
    terms = image_loss(render, target, band, bg, (8, 2, 2))
    assert terms["l1"].item() == 0 and abs(terms["ssim"].item()) < 1e-6 and "lpips" not in terms
    render[:, 12, 12] += 0.3  # outside the band: L1 is the mean absolute difference
    terms = image_loss(render, target, band, bg, (8, 2, 2))
    torch.testing.assert_close(terms["l1"], torch.tensor(0.3 * 3 * 2 / (2 * 24 * 24 * 3)))
    torch.testing.assert_close(terms["total"], 8 * terms["l1"] + 2 * terms["ssim"])


@pytest.fixture(scope="module")
def standin(tmp_path_factory):
    from pig.body.standin import write_standin

    path = tmp_path_factory.mktemp("standin") / "body_model.npz"
    write_standin(path)
    return path.read_bytes()


def _small_model(standin, refine=True, **avatar):
    rng = np.random.default_rng(0)
    pose = rng.normal(scale=0.2, size=(3, 55, 3))
    params = SmplxParams(pose, np.zeros(10), np.zeros((3, 10)), np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], float))
    return small_avatar(standin, params, refine, num_anchors=600, levels=3, sh_degree=1, hidden_layers=2, hidden_width=32,
                        **avatar)


def _camera():
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # looking down -z at a y-up body
    viewmat[2, 3] = 3.0
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    return viewmat[None], K[None]


def test_gradient_reaches_grid_anchors_decoders_and_refiner(standin):
    model = _small_model(standin)
    viewmat, K = _camera()
    g = model(torch.tensor([1, 2]), lod=2)
    target = torch.rand(1, 32, 32, 3, generator=torch.Generator().manual_seed(0))
    loss = sum((render_gaussians(g.means[k], g.quats[k], g.scales[k], g.opacities[k], g.sh[k], viewmat, K, 32, 32,
                                 torch.zeros(3), backend="cpu").color - target).abs().mean() for k in range(2))
    loss.backward()
    groups = {"grid": model.grid.parameters(), "anchors": model.anchors.parameters(),
              "decoders": model.decoder.parameters(), "refiner": model.refiner.parameters()}
    for name, params in groups.items():
        total = sum(p.grad.abs().sum().item() for p in params if p.grad is not None)
        assert total > 0, f"no gradient reached the {name}"


def test_model_outputs_levels_and_novel_pose_override(standin):
    model = _small_model(standin, refine=False)
    sizes = model.level_sizes
    assert sizes == [150, 300, 600]
    for lod in range(3):
        g = model(torch.tensor([0]), lod)
        assert g.means.shape == (1, sizes[lod], 3) and g.sh.shape == (1, sizes[lod], 4, 3)
        torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(1, sizes[lod]))
    # The coarse level's anchors are the first anchors of the finer level: same canonical positions.
    with torch.no_grad():
        fine, coarse = model(torch.tensor([1]), 2), model(torch.tensor([1]), 0)
    assert fine.means.shape[1] == 600 and coarse.means.shape[1] == 150
    # A pose override equal to the training pose reproduces that timestep; another pose moves the splats.
    row = SmplxParams(model.pose_init[1:2].numpy(), model.betas_init.numpy(), model.expression[1:2].numpy(), model.transl[1:2].numpy())
    same = model.gaussians(1, 2, row)
    torch.testing.assert_close(same[0], fine.means[0])
    row.transl = row.transl + np.array([[0.0, 0.0, 0.5]])
    moved = model.gaussians(1, 2, row)
    torch.testing.assert_close(moved[0], fine.means[0] + torch.tensor([0.0, 0.0, 0.5]))
    assert model.nearest_timestep(model.pose_init[2]) == 2
    assert model.timestep_of_frame(12) == 2


# ---- fit stage on a generated capture (slow: generation + two short fits) ----


@pytest.mark.slow
def test_short_fit_learns_and_resumes_to_the_same_result(small_capture, tmp_path):
    import pandas as pd

    from pig.avatar.training import fit

    preset = write_test_preset(tmp_path, iterations=30, eval_every=15, checkpoint_minutes=0.0)
    capture = small_capture
    reference = fit(capture, tmp_path / "full", preset)
    log = pd.read_csv(tmp_path / "full" / "train_log.csv")
    assert log["iteration"].iloc[-1] == 30 and (tmp_path / "full" / "train_log.png").exists()
    assert log["loss"].iloc[-6:].mean() < log["loss"].iloc[1:7].mean()
    psnr = log["heldout_psnr"].dropna().to_numpy()
    assert len(psnr) == 3 and psnr[-1] > psnr[0] + 0.5, psnr
    # train_s leaves the held-out evaluations and the checkpoint writes (one an iteration here) out: the gap to
    # wall_s grows after each checkpoint (a row is logged before its own), and across the evaluation at 15 by at least
    # that evaluation's seconds.
    gap = (log["wall_s"] - log["train_s"]).to_numpy()
    at = {int(i): k for k, i in enumerate(log["iteration"])}
    assert (gap[2:] > gap[1:-1]).all() and gap[at[16]] - gap[at[15]] >= log["eval_s"][at[15]]

    class Killed(Exception):
        pass

    def kill_at_12(iteration):
        if iteration == 12:
            raise Killed

    with pytest.raises(Killed):
        fit(capture, tmp_path / "resumed", preset, on_iteration=kill_at_12)
    assert not (tmp_path / "resumed" / "avatar.pt").exists()
    assert torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)["iteration"] == 12
    resumed = fit(capture, tmp_path / "resumed", preset)
    resumed_log = pd.read_csv(tmp_path / "resumed" / "train_log.csv")
    assert resumed_log["iteration"].tolist() == log["iteration"].tolist()
    a, b = torch.load(reference, weights_only=True), torch.load(resumed, weights_only=True)
    assert a["iteration"] == b["iteration"] == 30
    for key, value in a["model"].items():
        assert torch.equal(b["model"][key], value), key  # bit-exact resume
    model = load_avatar(resumed)
    means, quats, scales, opacities, sh = model.gaussians(0, model.num_levels - 1)
    assert means.shape[0] == model.level_sizes[-1] and torch.isfinite(means).all()


@pytest.mark.slow
def test_leftover_checkpoint_of_another_fit_is_not_resumed(small_capture, tmp_path):
    """A checkpoint.pt of a fit on another capture with the same frame numbers, or of another variant, is
    refused with a message naming it, and left as it is."""
    import shutil

    from pig.avatar.checkpoint import CheckpointError
    from pig.avatar.training import fit

    other = tmp_path / "other"
    shutil.copytree(small_capture, other)
    params, frames = SmplxParams.load(other / "smplx.npz")
    params.transl = params.transl + 0.05
    params.save(other / "smplx.npz", frame_ids=frames)
    preset = write_test_preset(tmp_path, iterations=4, eval_every=4, checkpoint_minutes=0.0)

    class Killed(Exception):
        pass

    def kill(iteration):
        raise Killed

    with pytest.raises(Killed):
        fit(other, tmp_path / "pig", preset, on_iteration=kill)
    state = tmp_path / "pig" / "checkpoint.pt"
    written = state.read_bytes()
    with pytest.raises(CheckpointError) as err:
        fit(small_capture, tmp_path / "pig", preset)
    assert str(err.value) == (f"{state}: checkpoint of another fit, not resumed: the capture differs (smplx); "
                              "delete it to start the fit over, or point --output elsewhere")
    with pytest.raises(CheckpointError, match=r"not resumed: preset section 'avatar' differs in offsets; "
                                              r"the variant differs \('pig', now 'no_offsets'\); delete it"):
        fit(other, tmp_path / "pig", preset, variant="no_offsets")
    assert state.read_bytes() == written and not (tmp_path / "pig" / "avatar.pt").exists()


def test_single_timestep_and_single_level_decode_and_train(standin):
    """T = 1 and L = 1: time embedding and LOD input are defined as zero-width / zero; gradients still flow."""
    params = SmplxParams(np.zeros((1, 55, 3)), np.zeros(10), np.zeros((1, 10)), np.zeros((1, 3)))
    cfg = AvatarConfig(num_anchors=100, levels=1, sh_degree=0, hidden_layers=1, hidden_width=16)
    spec = dict(avatar=asdict(cfg), field=asdict(FieldConfig(resolutions=[4], features=4)), precond=asdict(PrecondConfig()),
                body_model_npz=standin, params=asdict(params), frame_ids=[7], variant="pig")
    torch.manual_seed(0)
    model = build_avatar(spec)
    assert model.num_levels == 1 and model.level_sizes == [100]
    g = model(torch.tensor([0]), 0)
    assert g.means.shape == (1, 100, 3) and g.sh.shape == (1, 100, 1, 3)
    for value in (g.means, g.quats, g.scales, g.opacities, g.sh):
        assert torch.isfinite(value).all()
    (g.means.sum() + g.sh.sum() + g.opacities.sum()).backward()
    for name, module in (("grid", model.grid), ("decoders", model.decoder)):
        assert sum(p.grad.abs().sum().item() for p in module.parameters() if p.grad is not None) > 0, name
    assert model.timestep_of_frame(7) == 0 and model.nearest_timestep(torch.zeros(55, 3)) == 0


class _Killed(Exception):
    pass


def _record_batches(monkeypatch) -> list:
    """Patch the fit's batch source to record what each iteration trains on: the LOD, the (timestep, cameras)
    of each view batch and the sum of its pixels."""
    from pig.avatar.batches import TrainingBatches

    record, get = [], TrainingBatches.get

    def recording_get(self, iteration):
        batch = get(self, iteration)
        record.append((iteration, batch.lod, [(vb.timestep, tuple(vb.cameras), vb.images.double().sum().item())
                                              for views in batch.views for vb in views]))
        return batch

    monkeypatch.setattr(TrainingBatches, "get", recording_get)
    return record


@pytest.mark.slow
def test_killed_and_resumed_fit_draws_the_same_batches_and_weights(small_capture, tmp_path, monkeypatch):
    """A fit killed after iteration 3 and resumed trains on the batches of an uninterrupted one, iteration for
    iteration, and ends with bit-identical weights."""
    from pig.avatar.training import fit

    preset = write_test_preset(tmp_path, {"num_anchors": 300}, iterations=7, eval_every=100, checkpoint_minutes=0.0,
                               views=2, timesteps=2, prefetch=3, loader_workers=2, view_cache=4)
    record = _record_batches(monkeypatch)
    reference = fit(small_capture, tmp_path / "full", preset)
    uninterrupted = list(record)
    record.clear()

    def kill_at_3(iteration):
        if iteration == 3:
            raise _Killed

    with pytest.raises(_Killed):
        fit(small_capture, tmp_path / "resumed", preset, on_iteration=kill_at_3)
    resumed = fit(small_capture, tmp_path / "resumed", preset)
    # Iterations 0-2, then 3-6 after the resume (the killed run had staged 3-5 ahead: dropped, drawn again).
    assert [r[0] for r in record] == list(range(7)) and record == uninterrupted
    assert len({(r[1], tuple(b[:2] for b in r[2])) for r in record}) > 4  # the batches differ between iterations
    a, b = load_avatar(reference).state_dict(), load_avatar(resumed).state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


@pytest.mark.slow
def test_corrupt_image_found_mid_training_stops_the_fit_and_keeps_the_checkpoint(small_capture, tmp_path):
    """A training image truncated after the fit started is found when the first batch that needs it is due:
    the iterations before it run, the error names the file, and checkpoint.pt and the log stay as saved."""
    import shutil

    from pig.avatar.batches import Sampler
    from pig.data.capture import Capture
    from pig.data.raw import CaptureError
    from pig._cli import error_line
    from pig.avatar.training import fit

    capture_dir = tmp_path / "capture"
    shutil.copytree(small_capture, capture_dir)
    small = {"num_anchors": 300}
    preset = write_test_preset(tmp_path, small, iterations=12, eval_every=100, checkpoint_minutes=0.0, prefetch=2,
                               view_cache=64)
    def kill_at_3(iteration):
        if iteration == 3:
            raise _Killed

    with pytest.raises(_Killed):
        fit(capture_dir, tmp_path / "pig", preset, on_iteration=kill_at_3)
    state, log = tmp_path / "pig" / "checkpoint.pt", tmp_path / "pig" / "train_log.csv"
    saved = state.read_bytes(), log.read_bytes()

    # The view whose first use after the resume (at iteration index 3) comes last.
    capture = Capture.load(capture_dir)
    train = capture.split["train"]
    sampler = Sampler(0, 2, tuple(tuple(train["cameras"]) for _ in train["frames"]), 1, 2)  # the test preset's fit
    first_use = {}
    for i in range(3, 12):
        for step, cams in sampler.picks(i).steps:
            for cam in cams:
                first_use.setdefault((cam, train["frames"][step]), i)
    (cam, frame), due = max(first_use.items(), key=lambda item: item[1])
    assert due >= 5
    [path] = (capture_dir / "images" / cam).glob(f"{frame:08d}.*")
    # Same size (the capture's fingerprint still matches, so the fit resumes), no end marker: a cut-off file.
    data = path.read_bytes()
    path.write_bytes(data[:-12] + bytes(12))

    done = []
    resume_preset = write_test_preset(tmp_path, small, iterations=12, eval_every=100, checkpoint_minutes=1e6,
                                      prefetch=2, view_cache=64)
    with pytest.raises(CaptureError) as err:
        fit(capture_dir, tmp_path / "pig", resume_preset, on_iteration=done.append)
    assert done == list(range(4, due + 1))  # trained up to the batch that needs the file
    assert error_line(err.value).startswith(f"{path}: truncated")
    assert (state.read_bytes(), log.read_bytes()) == saved and not (tmp_path / "pig" / "avatar.pt").exists()
    # train_log.png: drawn at the first run's held-out evaluations, for watching the fit.
    assert sorted(p.name for p in (tmp_path / "pig").iterdir()) == sorted([".pig-stage", "checkpoint.pt", "train_log.csv",
                                                                           "train_log.png"])


def test_fit_without_training_images_names_the_capture(small_capture, tmp_path):
    import shutil

    from pig.data.raw import CaptureError
    from pig.avatar.training import fit

    capture_dir = tmp_path / "capture"
    shutil.copytree(small_capture, capture_dir)
    for folder in (capture_dir / "images").iterdir():
        shutil.rmtree(folder)
    with pytest.raises(CaptureError, match=r"capture: no image and mask of the train split \(cameras \['cam00'"):
        fit(capture_dir, tmp_path / "pig", write_test_preset(tmp_path))
    assert not any((tmp_path / "pig" / name).exists() for name in ("avatar.pt", "checkpoint.pt", "train_log.csv"))


def test_threads_argument_takes_the_place_of_the_presets_cpu_threads(small_capture, tmp_path):
    """The workflow passes the rule's threads (`--threads`) to a CPU fit; without them the preset's fit.cpu_threads
    holds. A resume with other threads is the same fit. The caller's thread count comes back afterwards."""
    from pig.avatar.training import fit
    from pig.stages.fit import main

    preset = yaml.safe_load(open(write_test_preset(tmp_path)))
    preset["fit"].update(iterations=2, eval_every=2, cpu_threads=2)
    path = tmp_path / "threads.yaml"
    path.write_text(yaml.safe_dump(preset))
    before, seen = torch.get_num_threads(), {}
    for name, threads in (("preset", None), ("argument", 1)):
        fit(small_capture, tmp_path / name, str(path), on_iteration=lambda i, n=name: seen.setdefault(n, torch.get_num_threads()),
            threads=threads)
    assert seen == {"preset": 2, "argument": 1} and torch.get_num_threads() == before
    with pytest.raises(SystemExit):
        main(["--capture", str(small_capture), "--output", str(tmp_path / "zero"), "--preset", str(path), "--threads", "0"])
