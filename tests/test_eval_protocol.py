"""Evaluation protocols (pig.metrics.protocol) against their references: scikit-image's SSIM, the crop rule by
OpenCV, pytorch-fid's resize."""
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from skimage.metrics import structural_similarity
from test_metrics import empty_hub  # noqa: F401 (a fixture)

from pig.metrics.protocol import crop_to_mask_box, mask_box, protocol, ssim_uniform


@pytest.mark.parametrize("shape", [(7, 7), (23, 31), (40, 33)])
def test_uniform_ssim_matches_scikit_image_defaults(rng, shape):
    x = rng.random((3, *shape, 3))
    y = np.clip(x + rng.normal(0, 0.2, x.shape), 0, 1)
    y[1] = rng.random(y[1].shape)  # an unrelated pair too
    got = ssim_uniform(torch.from_numpy(x).permute(0, 3, 1, 2), torch.from_numpy(y).permute(0, 3, 1, 2))
    expected = [structural_similarity(a, b, channel_axis=-1, data_range=1) for a, b in zip(x, y)]
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="smaller than the 7x7 window"):
        ssim_uniform(torch.zeros(1, 3, 6, 9), torch.zeros(1, 3, 6, 9))


def _reference_crop(image: np.ndarray, mask: np.ndarray, pad: int, size: int) -> np.ndarray:
    """The rule as written out in numpy and OpenCV: box of mask > 0 widened by pad, squared on ones, resized."""
    rows, cols = np.where(mask)
    v0, v1 = np.clip([rows.min() - pad, rows.max() + pad], 0, mask.shape[0])
    u0, u1 = np.clip([cols.min() - pad, cols.max() + pad], 0, mask.shape[1])
    side = max(v1 - v0, u1 - u0)
    square = np.ones((side, side, 3), np.float32)
    if v1 - v0 > u1 - u0:
        start = (side - (u1 - u0)) // 2
        square[:, start:start + u1 - u0] = image[v0:v1, u0:u1]
    else:
        start = (side - (v1 - v0)) // 2
        square[start:start + v1 - v0, :] = image[v0:v1, u0:u1]
    return cv2.resize(square, (size, size), interpolation=cv2.INTER_LINEAR)


@pytest.mark.parametrize("box", [(20, 60, 30, 45), (2, 90, 5, 110), (40, 41, 0, 120)])
def test_crop_to_mask_box_follows_the_rule(rng, box):
    height, width, pad, size = 96, 120, 10, 64
    image = rng.random((height, width, 3)).astype(np.float32)
    mask = np.zeros((height, width), bool)
    mask[box[0]:box[1], box[2]:box[3]] = True
    mask[box[0] + (box[1] - box[0]) // 2, box[2]] = True
    expected = _reference_crop(image, mask, pad, size)
    got = crop_to_mask_box(torch.from_numpy(image).permute(2, 0, 1)[None], torch.from_numpy(mask)[None], pad, size)
    np.testing.assert_allclose(got[0].permute(1, 2, 0).numpy(), expected, atol=2e-6)
    top, bottom, left, right = mask_box(torch.from_numpy(mask), pad)
    assert (top, left) == (max(box[0] - pad, 0), max(box[2] - pad, 0))
    assert (bottom, right) == (min(box[1] - 1 + pad, height), min(box[3] - 1 + pad, width))


def test_pytorch_fid_resize_is_bilinear_without_antialiasing(rng):
    """pytorch-fid resizes with F.interpolate(bilinear, align_corners=False); written out here in float64 with
    half-pixel centres, against which the protocol's rule is held (and the antialiased one differs)."""
    from pig.metrics.fid import resize_for_inception

    image = rng.random((2, 3, 64, 48))
    got = resize_for_inception(torch.from_numpy(image), protocol("animatable_gaussians").fid_resize).numpy()

    def axis(n_in, n_out):
        src = np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0, n_in - 1)
        low = np.floor(src).astype(int)
        high = np.minimum(low + 1, n_in - 1)
        return low, high, src - low

    (r0, r1, wr), (c0, c1, wc) = axis(64, 299), axis(48, 299)
    rows = image[:, :, r0] * (1 - wr)[:, None] + image[:, :, r1] * wr[:, None]
    expected = rows[..., c0] * (1 - wc) + rows[..., c1] * wc
    np.testing.assert_allclose(got, expected, atol=1e-12)
    ours = resize_for_inception(torch.from_numpy(image), protocol("ours").fid_resize)
    torch.testing.assert_close(ours, F.interpolate(torch.from_numpy(image), size=(299, 299), mode="bilinear",
                                                   antialias=True, align_corners=False))
    large = torch.from_numpy(rng.random((1, 3, 600, 500)))  # downscaled: the two rules differ
    assert (resize_for_inception(large, "antialiased_bilinear") - resize_for_inception(large, "pytorch_fid")).abs().max() > 0.1


def test_evaluate_by_animatable_gaussians_protocol_and_the_tables_name_it(tmp_path, empty_hub, rng):
    """SSIM by scikit-image's defaults on the full frame, LPIPS (AlexNet: quicker than VGG here) on the crop rule's crops, PSNR unchanged;
    the summary and the table headers name the protocol, and mixed protocols are refused."""
    import json

    import pandas as pd
    import yaml
    from test_metrics import _reference_alex_lpips, _tiny_capture, _write_lpips_weights

    from pig.data.images import read_png
    from pig.stages.evaluate import main as evaluate
    from pig.stages.tables import make_tables

    torch.manual_seed(0)
    backbone, linear = _write_lpips_weights("alex", empty_hub, tmp_path / "alex.pth")
    capture, renders = _tiny_capture(tmp_path, rng)
    metrics = {}
    for name in ("ours", "animatable_gaussians"):
        profile = tmp_path / f"{name}.yaml"
        profile.write_text(yaml.safe_dump({"evaluate": {"lpips_net": "alex", "protocol": name, "device": "cpu",
                                                        "lpips_linear_weights": str(tmp_path / "alex.pth")}}))
        metrics[name] = tmp_path / "results" / "dna" / name / "pig" / "metrics"
        assert evaluate(["--capture", str(capture), "--renders", str(renders), "--split", "novel_view",
                         "--output", str(metrics[name]), "--preset", str(profile)]) == 0
    ours, peer = (json.loads((metrics[n] / "novel_view_lod0.json").read_text())
                  for n in ("ours", "animatable_gaussians"))
    render = read_png(renders / "lod0" / "cam00" / "00000000.png")
    mask = cv2.imread(str(capture / "masks" / "cam00" / "00000000.png"), cv2.IMREAD_GRAYSCALE) > 127
    truth = read_png(capture / "images" / "cam00" / "00000000.png") * mask[..., None]
    assert peer["protocol"] == "animatable_gaussians" and ours["protocol"] == "ours" and ours["protocol_note"] == ""
    assert peer["psnr"] == pytest.approx(ours["psnr"], abs=1e-9)
    assert peer["ssim"] == pytest.approx(structural_similarity(render, truth, channel_axis=-1, data_range=1), abs=1e-6)
    crops = [torch.from_numpy(_reference_crop(image, mask, 50, 512)).permute(2, 0, 1)[None] for image in (render, truth)]
    assert peer["lpips"] == pytest.approx(float(_reference_alex_lpips(backbone, linear, *crops)), rel=1e-4)

    # The weights that scored the LPIPS column, by name and SHA-256 (FID had none), in the summary and the notes.
    import hashlib

    from pig.metrics.weights import TORCHVISION_FILES

    digests = [f"{path.name} (sha256 {hashlib.sha256(path.read_bytes()).hexdigest()[:12]})"
               for path in (empty_hub / TORCHVISION_FILES["alex"], tmp_path / "alex.pth")]
    assert peer["weights_note"] == "scored with weights " + ", ".join(digests)
    tables = tmp_path / "tables"
    make_tables("dna", [metrics["animatable_gaussians"] / "novel_view_lod0.json"], [], ["pig"], tables)
    assert peer["weights_note"] in (tables / "dna.md").read_text()
    columns = set(pd.read_csv(tables / "dna.csv").columns)
    assert {"novel_view_psnr", "novel_view_ssim_animatable_gaussians", "novel_view_lpips_alex_animatable_gaussians",
            "novel_view_fid_animatable_gaussians"} <= columns and "novel_view_ssim" not in columns
    assert "AnimatableGaussians: SSIM scikit-image defaults" in (tables / "dna.md").read_text()
    with pytest.raises(ValueError, match="different protocols"):
        make_tables("dna", [metrics[n] / "novel_view_lod0.json" for n in metrics], [], ["pig"], tmp_path / "mixed")


def test_inception_is_not_taken_from_tmp(tmp_path, empty_hub, monkeypatch):
    """A TorchScript file is code: one in a folder anyone can write (clean-fid's /tmp) is never loaded."""
    from pig.metrics import fid
    from pig.metrics.weights import WeightsMissing

    world = tmp_path / "world"
    world.mkdir()
    torch.jit.script(torch.nn.Identity()).save(str(world / fid.INCEPTION_FILE))
    monkeypatch.setattr(fid, "Path", lambda *parts: world if parts == ("/tmp",) else Path(*parts))
    with pytest.raises(WeightsMissing, match=r"weights file inception-2015-12-05.pt not found \(searched [^,]*\)"):
        fid.InceptionFeatures()
