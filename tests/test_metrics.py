"""Metrics against independent references: closed forms, scikit-image, and hand-built twin networks."""
from __future__ import annotations

import json
import math
import re

import cv2
import numpy as np
import pandas as pd
import pytest
import torch
import torch.nn.functional as F
import yaml
from skimage.metrics import structural_similarity

from pig.body.params import SmplxParams
from pig.data.capture import Capture
from pig.data.capture_record import RECORD, capture_record
from pig.metrics.fid import FeatureStatistics, InceptionFeatures, fid_from_statistics, frechet_distance
from pig.metrics.lpips import LPIPS, WeightsMissing, backbone_features
from pig.metrics.psnr import psnr
from pig.metrics.ssim import ssim
from pig._io import write_json, write_png
from pig.data.images import read_png


@pytest.fixture
def empty_hub(tmp_path, monkeypatch):
    """An empty torch hub cache, so no real weights on this machine leak into the tests."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setattr("pig.metrics.weights.lpips_package_weights", lambda: None)
    return tmp_path / "torch_home" / "hub" / "checkpoints"


def test_psnr_closed_form(rng):
    x = torch.from_numpy(rng.random((3, 3, 8, 9)))
    noise = torch.from_numpy(rng.choice([-1.0, 1.0], size=x.shape)) * 0.05
    # +-0.05 everywhere: MSE is exactly 0.0025, PSNR = 10 log10(R^2 / 0.0025).
    for data_range in (1.0, 255.0):
        expected = 10 * math.log10(data_range**2 / 0.0025)
        torch.testing.assert_close(psnr(x, x + noise, data_range), torch.full((3,), expected, dtype=torch.float64))
    assert torch.isinf(psnr(x, x)).all()


@pytest.mark.parametrize("shape", [(2, 3, 32, 40), (1, 3, 11, 11), (1, 3, 17, 64)])
@pytest.mark.parametrize("data_range", [1.0, 255.0])
def test_ssim_matches_scikit_image(rng, shape, data_range):
    x = rng.random(shape) * data_range
    y = np.clip(x + rng.normal(0, 0.2 * data_range, shape), 0, data_range)
    ours = ssim(torch.from_numpy(x), torch.from_numpy(y), data_range, reduction="none")
    for b in range(shape[0]):
        reference = structural_similarity(
            x[b], y[b], gaussian_weights=True, sigma=1.5, use_sample_covariance=False, channel_axis=0, data_range=data_range
        )
        assert ours[b].item() == pytest.approx(reference, abs=1e-10)


def test_ssim_extremes_and_gradient(rng):
    x = torch.from_numpy(rng.random((1, 3, 24, 24)))
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-12)
    # A constant image against itself (zero variance) is still 1, thanks to C1 and C2.
    flat = torch.full((1, 3, 16, 16), 0.3, dtype=torch.float64)
    assert ssim(flat, flat).item() == pytest.approx(1.0, abs=1e-12)
    # Black against white: luminance term (C1) / (1 + C1) with zero variances.
    c1 = 0.01**2
    black, white = torch.zeros(1, 3, 16, 16, dtype=torch.float64), torch.ones(1, 3, 16, 16, dtype=torch.float64)
    assert ssim(black, white).item() == pytest.approx(c1 / (1 + c1), rel=1e-12)
    # Analytic gradient against central finite differences (float64), on a small image to stay fast.
    y = torch.from_numpy(rng.random((1, 1, 12, 13))).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: ssim(x[:, :1, :12, :13], t), (y,), fast_mode=True)


def test_ssim_rejects_small_images():
    with pytest.raises(ValueError, match="at least 11"):
        ssim(torch.zeros(1, 3, 10, 30), torch.zeros(1, 3, 10, 30))


def test_frechet_distance_closed_form(rng):
    d = 5
    a = rng.normal(size=(d, d))
    b = rng.normal(size=(d, d))
    s1, s2 = a @ a.T + np.eye(d), b @ b.T + 0.1 * np.eye(d)
    mu1, mu2 = rng.normal(size=d), rng.normal(size=d)
    # Independent reference: trace of the principal square root by scipy, float64.
    from scipy.linalg import sqrtm

    expected = np.sum((mu1 - mu2) ** 2) + np.trace(s1 + s2 - 2 * np.real(sqrtm(s1 @ s2)))
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, rel=1e-10)
    # Commuting diagonal covariances: sum (sqrt(s1_i) - sqrt(s2_i))^2 exactly.
    v1, v2 = rng.random(d) + 0.5, rng.random(d) + 0.5
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(v1) - np.sqrt(v2)) ** 2)
    assert frechet_distance(mu1, np.diag(v1), mu2, np.diag(v2)) == pytest.approx(expected, rel=1e-12)


def test_frechet_distance_singular_covariances(rng):
    # Rank-1 covariances along orthogonal axes: tr sqrt(S1 S2) = 0; along the same axis: sqrt(v1 v2).
    e0, e1 = np.eye(3)[0], np.eye(3)[1]
    zero = np.zeros(3)
    assert frechet_distance(zero, 4 * np.outer(e0, e0), zero, 9 * np.outer(e1, e1)) == pytest.approx(13.0, abs=1e-9)
    assert frechet_distance(zero, 4 * np.outer(e0, e0), zero, 9 * np.outer(e0, e0)) == pytest.approx(1.0, abs=1e-9)
    # Few samples in many dimensions (rank-deficient, as FID on a small test set): finite and ~0 for a set
    # against itself, flagged as biased below min_images but still computed.
    stats = FeatureStatistics()
    stats.update(rng.normal(size=(10, 64)))
    value, note = fid_from_statistics(stats, stats, min_images=5)
    assert note == "" and abs(value) < 1e-8
    value, note = fid_from_statistics(stats, stats, min_images=2000)
    assert abs(value) < 1e-8 and note == "FID over 10 images (< 2000): biased high, compare only at equal N"


def _reference_distance(features_x, features_y, linear: dict) -> torch.Tensor:
    """LPIPS's distance from two lists of feature maps: unit-normalised channels, squared difference weighted
    by the linear layers, averaged over pixels, summed over layers."""
    total = 0
    for k, (a, b) in enumerate(zip(features_x, features_y)):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        total = total + F.conv2d((a - b) ** 2, linear[f"lin{k}.model.1.weight"]).mean(dim=(1, 2, 3))
    return total


def _reference_alex_lpips(backbone: dict, linear: dict, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """LPIPS written out layer by layer from the two state_dicts, independently of pig.metrics.lpips."""
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def taps(img):
        h = ((img * 2 - 1) - shift) / scale
        h = F.relu(F.conv2d(h, backbone["features.0.weight"], backbone["features.0.bias"], stride=4, padding=2))
        out = [h]
        h = F.relu(F.conv2d(F.max_pool2d(h, 3, 2), backbone["features.3.weight"], backbone["features.3.bias"], padding=2))
        out.append(h)
        h = F.relu(F.conv2d(F.max_pool2d(h, 3, 2), backbone["features.6.weight"], backbone["features.6.bias"], padding=1))
        out.append(h)
        h = F.relu(F.conv2d(h, backbone["features.8.weight"], backbone["features.8.bias"], padding=1))
        out.append(h)
        h = F.relu(F.conv2d(h, backbone["features.10.weight"], backbone["features.10.bias"], padding=1))
        out.append(h)
        return out

    return _reference_distance(taps(x), taps(y), linear)


def test_lpips_loads_torchvision_and_lpips_files(tmp_path, empty_hub):
    torch.manual_seed(0)
    # A torchvision-format checkpoint (features.* plus classifier keys, which LPIPS ignores).
    backbone = {f"features.{k}": v for k, v in backbone_features("alex").state_dict().items()}
    backbone["classifier.1.weight"] = torch.randn(4, 9216)
    linear = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate((64, 192, 384, 256, 256))}
    empty_hub.mkdir(parents=True)
    torch.save(backbone, empty_hub / "alexnet-owt-7be5be79.pth")
    linear_path = tmp_path / "alex.pth"
    torch.save(linear, linear_path)

    metric = LPIPS("alex", linear_weights=linear_path)
    x, y = torch.rand(2, 3, 64, 72), torch.rand(2, 3, 64, 72)
    torch.testing.assert_close(metric(x, y), _reference_alex_lpips(backbone, linear, x, y))
    torch.testing.assert_close(metric(x, x), torch.zeros(2))
    # Differentiable w.r.t. the images, frozen itself.
    y.requires_grad_()
    metric(x, y).sum().backward()
    assert y.grad.abs().sum() > 0 and all(p.grad is None for p in metric.parameters())


def _reference_vgg_lpips(backbone: dict, linear: dict, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """LPIPS-VGG written out block by block from the two state_dicts: VGG16's five conv blocks (2, 2, 3, 3, 3
    3x3 convolutions, 2x2 max-pool between blocks), compared after each block's last ReLU."""
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
    blocks = [(0, 2), (5, 7), (10, 12, 14), (17, 19, 21), (24, 26, 28)]

    def taps(img):
        h = ((img * 2 - 1) - shift) / scale
        out = []
        for b, convs in enumerate(blocks):
            if b:
                h = F.max_pool2d(h, 2)
            for i in convs:
                h = F.relu(F.conv2d(h, backbone[f"features.{i}.weight"], backbone[f"features.{i}.bias"], padding=1))
            out.append(h)
        return out

    return _reference_distance(taps(x), taps(y), linear)


def _write_lpips_weights(net: str, hub, linear_path) -> tuple[dict, dict]:
    """Random weights in torchvision's (into the hub cache) and the lpips package's format; returns both."""
    backbone = {f"features.{k}": v for k, v in backbone_features(net).state_dict().items()}
    channels = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}[net]
    linear = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(channels)}
    hub.mkdir(parents=True, exist_ok=True)
    torch.save(backbone, hub / {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}[net])
    torch.save(linear, linear_path)
    return backbone, linear


def test_lpips_vgg_loads_torchvision_and_lpips_files(tmp_path, empty_hub):
    torch.manual_seed(0)
    backbone, linear = _write_lpips_weights("vgg", empty_hub, tmp_path / "vgg.pth")
    metric = LPIPS("vgg", linear_weights=tmp_path / "vgg.pth")
    x, y = torch.rand(2, 3, 32, 40), torch.rand(2, 3, 32, 40)
    expected = _reference_vgg_lpips(backbone, linear, x, y)
    torch.testing.assert_close(metric(x, y), expected)
    assert (expected > 0).all()
    torch.testing.assert_close(metric(x, x), torch.zeros(2))
    # The AlexNet files do not stand in for VGG's (nor the other way round).
    with pytest.raises(WeightsMissing, match="alexnet-owt-7be5be79.pth"):
        LPIPS("alex", linear_weights=tmp_path / "vgg.pth")


@pytest.mark.parametrize("net, smallest", [("alex", 31), ("vgg", 16)])
def test_lpips_smallest_image(tmp_path, empty_hub, net, smallest):
    torch.manual_seed(0)
    _write_lpips_weights(net, empty_hub, tmp_path / "lin.pth")
    metric = LPIPS(net, linear_weights=tmp_path / "lin.pth")
    x = torch.rand(1, 3, smallest, 3 * smallest)
    assert torch.isfinite(metric(x, x.flip(-1))).all()
    too_small = torch.rand(1, 3, 3 * smallest, smallest - 1)
    with pytest.raises(ValueError, match=rf"LPIPS \({net}\) needs images of at least {smallest} pixels per side, "
                                         rf"found {smallest - 1}x{3 * smallest}"):
        metric(too_small, too_small)


def test_lpips_missing_weights_name_the_file(tmp_path, empty_hub):
    with pytest.raises(WeightsMissing, match="alexnet-owt-7be5be79.pth"):
        LPIPS("alex")
    with pytest.raises(WeightsMissing, match="does not exist"):
        LPIPS("alex", backbone_weights=tmp_path / "nowhere.pth")
    bad = tmp_path / "bad.pth"
    torch.save({"something": torch.zeros(1)}, bad)
    with pytest.raises(WeightsMissing, match="expected torchvision alex keys"):
        LPIPS("alex", backbone_weights=bad, linear_weights=bad)


class _TinyInception(torch.nn.Module):
    """Stand-in with the real network's call signature: forward(x in [0, 255], return_features)."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, 5, stride=4)

    def forward(self, x: torch.Tensor, return_features: bool = False) -> torch.Tensor:
        features = self.conv(x / 255).relu().mean(dim=(2, 3))
        return features if return_features else features.sum(1, keepdim=True)


def test_inception_features_load_torchscript(tmp_path, empty_hub):
    torch.manual_seed(0)
    tiny = _TinyInception()
    path = tmp_path / "inception-2015-12-05.pt"
    torch.jit.script(tiny).save(str(path))
    extractor = InceptionFeatures(path)
    images = torch.rand(3, 3, 299, 299)
    torch.testing.assert_close(extractor(images), tiny(images * 255, return_features=True))
    # Other sizes are resized to 299 first.
    small = torch.rand(2, 3, 64, 48)
    resized = F.interpolate(small, size=(299, 299), mode="bilinear", antialias=True, align_corners=False)
    torch.testing.assert_close(extractor(small), tiny(resized.clamp(0, 1) * 255, return_features=True))
    with pytest.raises(WeightsMissing, match="inception-2015-12-05.pt"):
        InceptionFeatures(tmp_path / "absent.pt")


def _tiny_capture(root, rng, width: int = 40, height: int = 32, frames: int = 1, missing: tuple[int, ...] = (),
                  fps: float = 10.0):
    """A preprocessed capture by hand: one camera, `frames` frames in every split, no image or mask for the
    `missing` frames (rendered all the same); returns (capture dir, renders dir)."""
    capture = root / "capture"
    (capture / "images" / "cam00").mkdir(parents=True)
    (capture / "masks" / "cam00").mkdir(parents=True)
    write_json(capture / "cameras.json", {"cam00": {"K": np.eye(3).tolist(), "R": np.eye(3).tolist(),
                                                    "T": [0.0, 0.0, 2.0], "width": width, "height": height}})
    SmplxParams(np.zeros((frames, 55, 3)), np.zeros(10), np.zeros((frames, 10)),
                np.zeros((frames, 3))).save(capture / "smplx.npz")
    part = {"cameras": ["cam00"], "frames": list(range(frames))}
    (capture / "split.json").write_text(json.dumps({"train": part, "novel_view": part, "novel_pose": part}))
    (capture / "report.json").write_text(json.dumps({"background": [0, 0, 0]}))
    mask = np.zeros((height, width), np.uint8)
    mask[4:-4, 6:-6] = 255
    renders = root / "renders" / "novel_view"
    (renders / "lod0" / "cam00").mkdir(parents=True)
    for frame in range(frames):
        if frame not in missing:
            write_png(capture / "images" / "cam00" / f"{frame:08d}.png", rng.random((height, width, 3)))
            cv2.imwrite(str(capture / "masks" / "cam00" / f"{frame:08d}.png"), mask)
        write_png(renders / "lod0" / "cam00" / f"{frame:08d}.png", rng.random((height, width, 3)))
    write_json(renders / "lod0" / "timing.json", {"splats": 100, "model_mb": 1.0, "seconds_per_frame": 1 / fps,
                                                  "fps": fps, "device": "cpu"})
    (capture / "body_model.npz").write_bytes(b"")  # hashed into the capture's fingerprint, never read here
    write_json(renders / RECORD, capture_record(Capture.load(capture)))  # as the render stage records its capture
    return capture, renders


def _strict_json(path):
    """json.loads that refuses NaN and Infinity, as a standard-conforming parser does."""
    def refuse(token):
        raise ValueError(f"{path}: non-standard JSON constant {token}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_evaluate_small_set_gets_a_flagged_fid_and_strict_json(tmp_path, empty_hub, rng):
    """Six frames, one missing from the capture: FID over the 5 scored views (checked against np.cov statistics
    of the network's features), flagged below fid_min_images; LPIPS weights absent and a NaN render time are
    written as null, and the tables show n/a for them and `FID (N=5, biased)`."""
    from pig.stages.evaluate import main as evaluate
    from pig.stages.tables import make_tables

    torch.manual_seed(0)
    tiny = _TinyInception()
    torch.jit.script(tiny).save(str(tmp_path / "inception-2015-12-05.pt"))
    capture, renders = _tiny_capture(tmp_path, rng, frames=6, missing=(2,), fps=math.nan)
    profile = tmp_path / "profile.yaml"
    profile.write_text(yaml.safe_dump({"evaluate": {"inception_weights": str(tmp_path / "inception-2015-12-05.pt"),
                                                    "fid_min_images": 2000, "batch_size": 2, "device": "cpu"}}))
    metrics = tmp_path / "results" / "dna" / "0165_08" / "pig" / "metrics"
    assert evaluate(["--capture", str(capture), "--renders", str(renders), "--split", "novel_view",
                     "--output", str(metrics), "--profile", str(profile)]) == 0

    summary = _strict_json(metrics / "novel_view_lod0.json")
    assert summary["lpips"] is None and summary["fps"] is None and "LPIPS is NaN" in summary["lpips_note"]
    assert summary["images"] == summary["fid_images"] == 5 and summary["fid_min_images"] == 2000
    assert summary["fid_note"] == "FID over 5 images (< 2000): biased high, compare only at equal N"
    assert len(pd.read_csv(metrics / "novel_view_lod0.csv")) == 5
    # Reference: the network on all five pairs at once, statistics by np.cov.
    kept = [f"{frame:08d}.png" for frame in (0, 1, 3, 4, 5)]
    mask = cv2.imread(str(capture / "masks" / "cam00" / kept[0]), cv2.IMREAD_GRAYSCALE)[..., None] > 127
    as_batch = lambda images: torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2)  # noqa: E731
    fake = as_batch([read_png(renders / "lod0" / "cam00" / name) for name in kept])
    real = as_batch([read_png(capture / "images" / "cam00" / name) * mask for name in kept])
    features = [InceptionFeatures(tmp_path / "inception-2015-12-05.pt")(x).double().numpy() for x in (fake, real)]
    expected = frechet_distance(*(v for f in features for v in (f.mean(0), np.cov(f, rowvar=False))))
    assert expected > 0 and summary["fid"] == pytest.approx(expected, rel=1e-6)

    tables = tmp_path / "results" / "tables"
    make_tables("dna", [metrics / "novel_view_lod0.json"], [], ["pig"], tables)
    main = pd.read_csv(tables / "dna.csv").set_index("variant")
    assert main.loc["pig", "novel_view_fid"] == pytest.approx(summary["fid"], rel=1e-5)
    assert main.loc["pig", "novel_view_fid_images"] == 5 and main.loc["pig", "novel_view_fid_biased"] == 1
    assert math.isnan(main.loc["pig", "novel_view_lpips_alex"])
    assert all(main[c].dtype.kind in "fi" for c in main.columns if c.startswith("novel_"))  # numeric CSV columns
    fid_text = f"{summary['fid']:.1f}"  # FID to one decimal, its image count and bias in a footnote
    count_note = "FID over 5 images per set, biased: fewer than the evaluate stage's fid_min_images"
    markdown = (tables / "dna.md").read_text()
    notes = dict(re.findall(r"^(\d+)\. (.*)$", markdown, flags=re.M))
    number = next(k for k, note in notes.items() if note == count_note)
    marker = number.translate(str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹"))
    row = next(line for line in markdown.splitlines() if line.startswith("| pig"))
    assert f"| n/a | {fid_text}{marker} |" in row
    assert "FID over 5 images (< 2000): biased high, compare only at equal N" in notes.values()
    assert "fid_images" not in markdown
    lod = (tables / "dna_lod.md").read_text()
    assert f"| {fid_text}{marker} |" in lod and "| n/a | cpu |" in lod  # fps null -> n/a


def test_evaluate_without_inception_weights_leaves_fid_missing(tmp_path, empty_hub, rng):
    from pig.stages.evaluate import main as evaluate

    capture, renders = _tiny_capture(tmp_path, rng, frames=3)
    profile = tmp_path / "profile.yaml"
    profile.write_text(yaml.safe_dump({"evaluate": {"inception_weights": str(tmp_path / "absent.pt"), "device": "cpu"}}))
    metrics = tmp_path / "metrics"
    assert evaluate(["--capture", str(capture), "--renders", str(renders), "--split", "novel_view",
                     "--output", str(metrics), "--profile", str(profile)]) == 0
    summary = _strict_json(metrics / "novel_view_lod0.json")
    assert summary["fid"] is None and summary["fid_images"] == 3
    assert summary["fid_note"] == (f"FID is NaN: FID Inception network: configured weights file {tmp_path / 'absent.pt'} "
                                   "does not exist (expected inception-2015-12-05.pt)")


def test_evaluate_with_vgg_and_the_tables_name_the_backbone(tmp_path, empty_hub, rng):
    """`evaluate.lpips_net: vgg` in a profile scores with VGG, the summary records it and the table headers say it."""
    from pig.stages.evaluate import main as evaluate
    from pig.stages.tables import make_tables

    torch.manual_seed(0)
    backbone, linear = _write_lpips_weights("vgg", empty_hub, tmp_path / "vgg.pth")
    capture, renders = _tiny_capture(tmp_path, rng)
    profile = tmp_path / "profile.yaml"
    profile.write_text(yaml.safe_dump({"evaluate": {"lpips_net": "vgg", "lpips_linear_weights": str(tmp_path / "vgg.pth"),
                                                    "device": "cpu"}}))
    metrics = tmp_path / "results" / "dna" / "0165_08" / "pig" / "metrics"
    assert evaluate(["--capture", str(capture), "--renders", str(renders), "--split", "novel_view",
                     "--output", str(metrics), "--profile", str(profile)]) == 0

    summary = json.loads((metrics / "novel_view_lod0.json").read_text())
    assert summary["lpips_net"] == "vgg" and summary["lpips_note"] == ""
    render = torch.from_numpy(read_png(renders / "lod0" / "cam00" / "00000000.png")).permute(2, 0, 1)[None]
    image = read_png(capture / "images" / "cam00" / "00000000.png")
    mask = cv2.imread(str(capture / "masks" / "cam00" / "00000000.png"), cv2.IMREAD_GRAYSCALE) > 127
    truth = torch.from_numpy(image * mask[..., None]).permute(2, 0, 1)[None]
    assert summary["lpips"] == pytest.approx(float(_reference_vgg_lpips(backbone, linear, render, truth)), rel=1e-5)

    tables = tmp_path / "results" / "tables"
    make_tables("dna", [metrics / "novel_view_lod0.json"], [], ["pig"], tables)
    main = pd.read_csv(tables / "dna.csv").set_index("variant")
    assert {"novel_view_lpips_vgg", "novel_pose_lpips_vgg"} <= set(main.columns)
    assert not any(c.endswith("_lpips") or "alex" in c for c in main.columns)
    assert main.loc["pig", "novel_view_lpips_vgg"] == pytest.approx(summary["lpips"], rel=1e-5)
    lod = pd.read_csv(tables / "dna_lod.csv")
    assert "lpips_vgg" in lod.columns and "lpips" not in lod.columns
    assert "| Novel views LPIPS↓ (vgg) |" in (tables / "dna.md").read_text().splitlines()[2]
    assert "| LPIPS↓ (vgg) |" in (tables / "dna_lod.md").read_text()


def _scored(root, subject: str, net: str | None):
    path = root / "dna" / subject / "pig" / "metrics" / "novel_view_lod0.json"
    path.parent.mkdir(parents=True)
    summary = {"split": "novel_view", "lod": 0, "psnr": 30.0, "ssim": 0.9, "lpips": 0.05, "fid": math.nan,
               "psnr_blank": 10.0, "ssim_blank": 0.5, "splats": 100, "model_mb": 1.0, "fps": 10.0, "device": "cpu"}
    path.write_text(json.dumps(summary if net is None else {**summary, "lpips_net": net}))
    return path


def test_tables_refuse_mixed_or_unnamed_lpips_backbones(tmp_path):
    from pig.stages.tables import make_tables

    out = tmp_path / "tables"
    mixed = [_scored(tmp_path, "s0", "alex"), _scored(tmp_path, "s1", "vgg")]
    with pytest.raises(ValueError, match=r"different LPIPS backbones \(\{'alex': 's0/pig/metrics/novel_view_lod0\.json', "
                                         r"'vgg': 's1/pig/metrics/novel_view_lod0\.json'\}\)"):
        make_tables("dna", mixed, [], ["pig"], out)
    unnamed = [mixed[1], _scored(tmp_path, "s2", None)]
    with pytest.raises(ValueError, match=r"s2/pig/metrics/novel_view_lod0\.json: summary does not name its LPIPS backbone"):
        make_tables("dna", unnamed, [], ["pig"], out)
    assert not out.exists()


def test_tables_state_the_smallest_fid_set_and_refuse_a_fid_without_its_count(tmp_path):
    from pig.stages.tables import make_tables

    def scored(subject: str, **fid):
        path = _scored(tmp_path, subject, "alex")
        write_json(path, {**json.loads(path.read_text()), "fid_min_images": 2000, **fid})
        return path

    full, short = scored("s0", fid=10.0, fid_images=2000), scored("s1", fid=12.0, fid_images=1999)
    out = tmp_path / "tables"
    make_tables("dna", [full, short], [], ["pig"], out)
    main = pd.read_csv(out / "dna.csv").set_index("variant")
    assert main.loc["pig", "novel_view_fid"] == pytest.approx(11.0)
    assert main.loc["pig", "novel_view_fid_images"] == 1999 and main.loc["pig", "novel_view_fid_biased"] == 1
    markdown = (out / "dna.md").read_text()
    assert "| 11.0¹ |" in markdown
    assert "1. FID over 1999 images per set, biased: fewer than the evaluate stage's fid_min_images" in markdown
    assert math.isnan(main.loc["pig", "novel_pose_fid_images"])  # no novel-pose summary, no count
    make_tables("dna", [full], [], ["pig"], out)
    assert "| 10.0¹ |" in (out / "dna.md").read_text() and "1. FID over 2000 images per set\n" in (out / "dna.md").read_text()
    assert pd.read_csv(out / "dna.csv").set_index("variant").loc["pig", "novel_view_fid_biased"] == 0

    older = _scored(tmp_path, "s2", "alex")
    write_json(older, {**json.loads(older.read_text()), "fid": 10.0})
    with pytest.raises(ValueError, match=r"s2/pig/metrics/novel_view_lod0\.json: summary has a FID but not the image "
                                         r"count it was computed over \(no fid_images / fid_min_images"):
        make_tables("dna", [full, older], [], ["pig"], out)
