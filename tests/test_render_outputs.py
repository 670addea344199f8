"""The render stage's stored outputs against the rasterizer's own: colour, alpha and depth of every view, and the
splat centres and opacities of `splats.npz`, recomputed here from the checkpoint through the model's forward (not
the stage's driver) and `render_gaussians`; `model_mb` of timing.json against the checkpoint's tensors.

`_stored_view` and `_stored_splats` read the stage's current storage (colour in 8-bit lossless chunks through
RenderReader; alpha and depth in the EXR per view that `every_view` adds; splats.npz per level): they are the only
places to change when that storage changes.
"""
import json

import numpy as np
import pytest
import torch

from pig.avatar.checkpoint import load_avatar
from pig.data.capture import Capture
from pig.data.exr import read_exr
from pig.data.ground_truth import SPLATS, SplatTrack
from pig.data.render_store import RenderReader
from pig.field.precondition import bake_preconditioning
from pig.render.api import RasterizerConfig, render_gaussians
from pig.stages.evaluate import EvaluateConfig
from pig.stages.render import render_split


def _stored_view(level_dir, camera: str, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb in [0, 1] (H, W, 3), alpha (H, W), depth (H, W)) of one view as the render stage stored it."""
    exr = read_exr(level_dir / camera / f"{frame:08d}.exr")
    return RenderReader(level_dir).image(camera, frame), exr["A"], exr["Z"]


def _stored_splats(level_dir) -> SplatTrack:
    return SplatTrack.load(level_dir / SPLATS)


@pytest.fixture(scope="module")
def rendered(tiny_fit, tmp_path_factory):
    """(capture, avatar.pt, renders of the novel-pose split) of the tiny fit, through the render stage."""
    capture_dir, checkpoint = tiny_fit
    out = tmp_path_factory.mktemp("render_outputs") / "renders"
    render_split(checkpoint, capture_dir, "novel_pose", out, EvaluateConfig(timing_frames=1), RasterizerConfig(backend="cpu"),
                 every_view=True)
    return capture_dir, checkpoint, out


@pytest.mark.slow
def test_render_stage_stores_what_the_rasterizer_renders(rendered):
    capture_dir, checkpoint, out = rendered
    capture = Capture.load(capture_dir)
    split = capture.split["novel_pose"]
    model = load_avatar(checkpoint).eval()
    baked = load_avatar(checkpoint).eval()
    bake_preconditioning(baked)
    frames = [int(f) for f in split["frames"]]
    assert not set(frames) & set(model.frame_ids)  # novel poses: the nearest timestep and the capture's pose
    for lod in range(model.num_levels):
        level_dir = out / f"lod{lod}"
        track = _stored_splats(level_dir)
        np.testing.assert_array_equal(track.frames, sorted(frames))
        for f, frame in enumerate(track.frames):
            row = capture.frames.index(frame)
            pose = capture.params.select([row])
            step = model.nearest_timestep(torch.as_tensor(pose.full_pose[0]))
            g = [t.float() for t in model.gaussians(step, lod, pose)]
            np.testing.assert_allclose(track.centres[f], g[0].numpy(), rtol=0, atol=2e-5)
            np.testing.assert_allclose(track.opacities[f], g[3].numpy(), rtol=0, atol=2e-5)
            for camera in split["cameras"]:
                cam = capture.cameras[camera]
                viewmat = torch.as_tensor(cam.viewmat(), dtype=torch.float32)[None]
                K = torch.as_tensor(cam.K, dtype=torch.float32)[None]
                ref = render_gaussians(*g, viewmat, K, cam.width, cam.height,
                                       torch.as_tensor(capture.background, dtype=torch.float32), backend="cpu")
                rgb, alpha, depth = _stored_view(level_dir, camera, frame)
                np.testing.assert_allclose(rgb, ref.color[0].clamp(0, 1).numpy(), rtol=0, atol=0.5 / 255 + 1e-4)
                np.testing.assert_allclose(alpha, ref.alpha[0, ..., 0].numpy(), rtol=0, atol=1e-4)
                covered = ref.alpha[0, ..., 0].numpy() > 0.05  # expected depth is sum w z / alpha: steady where covered
                assert covered.sum() > 20
                np.testing.assert_allclose(depth[covered], ref.depth[0, ..., 0].numpy()[covered], rtol=1e-4, atol=1e-4)
        # model_mb: the tensors of the avatar a renderer holds (preconditioning baked: x, not u and its origin), in MB,
        # per-anchor ones at the level's share; summed here over the state dict's entries by name.
        timing = json.loads((level_dir / "timing.json").read_text())
        state = baked.state_dict()
        n, size = model.level_sizes[-1], model.level_sizes[lod]
        body = {k for k in state if k.startswith("body_model.")}
        expected = sum(t.numel() * t.element_size() * (size / n if t.dim() and t.shape[0] == n else 1)
                       for k, t in state.items() if k not in body) / 2**20
        assert timing["splats"] == size and timing["model_mb"] == pytest.approx(expected, rel=0.02)


def _psnr_db(x: np.ndarray, y: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((x.astype(np.float64) - y.astype(np.float64)) ** 2)))


@pytest.mark.slow
def test_blank_row_is_a_black_image_scored_against_the_masked_truth(rendered, tmp_path):
    """The evaluate summary's psnr_blank and the tables' black-image row: the mean over the split's views of the PSNR of
    an all-black image against the masked ground truth, computed here in float64 numpy."""
    import pandas as pd

    from pig.stages.evaluate import evaluate_split
    from pig.stages.tables import BLANK_ROW, make_tables

    capture_dir, checkpoint, out = rendered
    capture = Capture.load(capture_dir)
    expected = np.mean([_psnr_db(np.zeros_like(capture.image(c, f)), capture.image(c, f) * capture.mask(c, f)[..., None])
                        for c, f in capture.views("novel_pose")])
    variant = tmp_path / "synthetic" / "subject00" / "pig"
    finest = len(list(out.glob("lod*"))) - 1
    evaluate_split(capture_dir, out, "novel_pose", variant / "metrics", EvaluateConfig(), levels=[finest])
    summary = json.loads((variant / "metrics" / f"novel_pose_lod{finest}.json").read_text())
    assert summary["psnr_blank"] == pytest.approx(expected, abs=1e-3)
    (variant / "train_log.csv").write_bytes((checkpoint.parent / "train_log.csv").read_bytes())
    make_tables("synthetic", [variant / "metrics" / f"novel_pose_lod{finest}.json"], [variant / "train_log.csv"], ["pig"],
                tmp_path / "tables")
    table = pd.read_csv(tmp_path / "tables" / "synthetic.csv").set_index("variant")
    assert table.loc[BLANK_ROW, "novel_pose_psnr"] == pytest.approx(expected, abs=1e-3)
    assert table.loc[BLANK_ROW, "novel_pose_ssim"] == pytest.approx(summary["ssim_blank"], abs=1e-6)
    assert table.loc[BLANK_ROW, "splats"] == 0
