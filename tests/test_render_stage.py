"""Render and evaluate stages on a split whose cameras differ in image size (as DNA-Rendering's do)."""
import hashlib
import json
import os
import shutil

import cv2
import numpy as np
import pandas as pd
import pytest
import torch

from pig.avatar.training import fit
from pig.data.render_store import RenderReader
from pig.render.api import RasterizerConfig
from pig.stages.evaluate import EvaluateConfig, evaluate_split
from pig.stages.render import render_split


@pytest.fixture(scope="module")
def fitted(tiny_fit):
    return tiny_fit


def _halve_camera(capture, camera: str) -> None:
    """Rewrite one camera of a preprocessed capture at half resolution (K with the pixel-centre convention)."""
    cameras = json.loads((capture / "cameras.json").read_text())
    entry = cameras[camera]
    K = np.asarray(entry["K"], float)
    K[:2, :2] *= 0.5
    K[:2, 2] = (K[:2, 2] + 0.5) * 0.5 - 0.5
    entry.update(K=K.tolist(), width=entry["width"] // 2, height=entry["height"] // 2)
    (capture / "cameras.json").write_text(json.dumps(cameras))
    size = (entry["width"], entry["height"])
    for kind, interpolation in (("images", cv2.INTER_AREA), ("masks", cv2.INTER_NEAREST)):
        for path in (capture / kind / camera).glob("*.png"):
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(path), cv2.resize(image, size, interpolation=interpolation))


@pytest.mark.slow
def test_render_and_evaluate_a_split_with_two_image_sizes(fitted, tmp_path):
    source, checkpoint = fitted
    capture = tmp_path / "capture"
    shutil.copytree(source, capture)
    split = json.loads((capture / "split.json").read_text())["novel_pose"]
    assert len(split["cameras"]) >= 2
    small = split["cameras"][0]
    _halve_camera(capture, small)
    # Fitted on the halved capture: render refuses an avatar of another capture (the original's cameras).
    checkpoint = fit(capture, tmp_path / "pig", str(checkpoint.parent.parent / "preset.yaml"))
    cfg = EvaluateConfig(timing_frames=1)
    renders = tmp_path / "renders" / "novel_pose"
    render_split(checkpoint, capture, "novel_pose", renders, cfg, RasterizerConfig(backend="cpu"))
    (renders / "stale.png").write_bytes(b"")
    # A rerun over the stage's own output needs no --overwrite and replaces the whole folder.
    render_split(checkpoint, capture, "novel_pose", renders, cfg, RasterizerConfig(backend="cpu"))
    assert not (renders / "stale.png").exists() and [p.name for p in renders.parent.iterdir()] == ["novel_pose"]

    cameras = json.loads((capture / "cameras.json").read_text())
    reader = RenderReader(renders / "lod0")
    for cam in split["cameras"]:
        for frame in split["frames"]:
            image = reader.image(cam, int(frame))
            assert image.shape[:2] == (cameras[cam]["height"], cameras[cam]["width"]), cam
    assert cameras[small]["width"] * 2 == cameras[split["cameras"][1]]["width"]

    assert evaluate_split(capture, renders, "novel_pose", tmp_path / "metrics", cfg)  # a rerun over its own output
    csvs = evaluate_split(capture, renders, "novel_pose", tmp_path / "metrics", cfg)
    table = pd.read_csv(csvs[0])
    assert len(table) == len(split["cameras"]) * len(split["frames"])
    assert set(table["camera"]) == set(split["cameras"])
    # Each row is scored against its own camera's ground truth, at that camera's size.
    from pig.data.capture import Capture

    loaded = Capture.load(capture)
    for row in table.itertuples():
        render = reader.image(row.camera, int(row.frame)).astype(np.float64)
        truth = loaded.image(row.camera, int(row.frame)) * loaded.mask(row.camera, int(row.frame))[..., None]
        expected = 10 * np.log10(1.0 / np.mean((render - truth) ** 2))
        assert row.psnr == pytest.approx(expected, abs=1e-3), row.camera


def test_render_records_the_hash_of_the_checkpoint_it_rendered_when_a_fit_replaces_it(fitted, tmp_path, monkeypatch):
    """Sweep three, case 10: render read avatar.pt for the model, again for the loss terms and again for its SHA-256;
    a fit renaming a new checkpoint into place in between had the old model's renders recorded under the new hash
    (a resumed render then continued them with the new model)."""
    import pig.avatar.checkpoint as checkpoint_module
    from pig.data.render_store import read_manifest

    capture, avatar = fitted
    checkpoint = tmp_path / "avatar.pt"
    shutil.copyfile(avatar, checkpoint)
    rendered_from = hashlib.sha256(checkpoint.read_bytes()).hexdigest()
    state = torch.load(avatar, map_location="cpu", weights_only=True)  # a later checkpoint of the fit: other weights
    key = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][key] = state["model"][key] + 0.5
    newer = tmp_path / ".avatar.tmp.pt"
    torch.save(state, newer)
    build = checkpoint_module.build_avatar

    def build_while_a_fit_replaces_the_file(spec):
        if newer.exists():
            os.replace(newer, checkpoint)
        return build(spec)

    monkeypatch.setattr(checkpoint_module, "build_avatar", build_while_a_fit_replaces_the_file)
    renders = tmp_path / "renders" / "novel_view"
    render_split(checkpoint, capture, "novel_view", renders, EvaluateConfig(timing_frames=1),
                 RasterizerConfig(backend="cpu"))

    assert not newer.exists() and hashlib.sha256(checkpoint.read_bytes()).hexdigest() != rendered_from
    assert read_manifest(renders)["checkpoint_sha256"] == rendered_from


def test_render_of_the_finest_lod_alone_equals_that_lod_of_every_lod(fitted, tmp_path):
    from pig.data.ground_truth import SPLATS, SplatTrack

    capture, checkpoint = fitted
    cfg, raster = EvaluateConfig(timing_frames=1), RasterizerConfig(backend="cpu")
    render_split(checkpoint, capture, "novel_view", tmp_path / "all", cfg, raster)
    render_split(checkpoint, capture, "novel_view", tmp_path / "finest", cfg, raster, lods=[-1])
    levels = sorted(int(p.name[3:]) for p in (tmp_path / "all").glob("lod*"))
    assert len(levels) > 1 and [p.name for p in (tmp_path / "finest").glob("lod*")] == [f"lod{levels[-1]}"]
    manifest = json.loads((tmp_path / "finest" / "manifest.json").read_text())
    assert manifest["levels"] == [levels[-1]]
    cameras = json.loads((capture / "cameras.json").read_text())
    sizes = {name: (entry["width"], entry["height"]) for name, entry in cameras.items()}
    readers = [RenderReader(tmp_path / name / f"lod{levels[-1]}", sizes) for name in ("all", "finest")]
    for camera in manifest["cameras"]:
        for frame in manifest["frames"]:
            np.testing.assert_array_equal(readers[1].image_u8(camera, frame), readers[0].image_u8(camera, frame))
    tracks = [SplatTrack.load(tmp_path / name / f"lod{levels[-1]}" / SPLATS) for name in ("all", "finest")]
    np.testing.assert_array_equal(tracks[1].centres, tracks[0].centres)
    with pytest.raises(ValueError, match=f"--lod {len(levels)}: .* has levels 0..{len(levels) - 1}"):
        render_split(checkpoint, capture, "novel_view", tmp_path / "beyond", cfg, raster, lods=[len(levels)])


def test_the_stages_encode_workers_option_overrides_the_preset_and_is_checked():
    """`--encode-workers` (the workflow passes its job's threads) replaces evaluate.encode_workers for render and
    evaluate alike; below 1 it is refused naming the key, and without it the preset's value stands."""
    from argparse import Namespace

    from pig.config import ConfigError, load_preset
    from pig.stages.evaluate import evaluate_section

    preset = load_preset("paper")
    assert evaluate_section(preset, Namespace(device=None, encode_workers=None)).encode_workers == 2
    cfg = evaluate_section(preset, Namespace(device="cpu", encode_workers=12))
    assert (cfg.encode_workers, cfg.device, cfg.lpips_net) == (12, "cpu", "vgg")
    with pytest.raises(ConfigError, match="encode_workers"):
        evaluate_section(preset, Namespace(device=None, encode_workers=0))
