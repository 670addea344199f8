"""The metric networks' arithmetic (evaluate.lpips_precision, fid_precision, channels_last): float32 untouched, the
lower precisions run in their dtype, and a bfloat16 evaluation on the CPU stays within issue 39's bounds of float32
while PSNR and SSIM do not move at all."""
import cv2
import numpy as np
import pytest
import torch

from pig.config import ConfigError, load_section
from pig.data.capture import Capture
from pig.data.render_store import ChunkEncoder, chunk_path, write_manifest
from pig.metrics.fid import InceptionFeatures
from pig.metrics.lpips import LPIPS, _channel_norm, _unit
from pig.stages.evaluate import EvaluateConfig, evaluate_levels, precision_note


def smooth_images(rng, count: int, height: int, width: int) -> np.ndarray:
    """(count, H, W, 3) uint8 images with a photo's spectrum more than noise's: bicubic blow-ups of 6 x 6 colour
    fields with a hard-edged disc."""
    images = []
    for _ in range(count):
        image = cv2.resize(rng.random((6, 6, 3), dtype=np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
        cv2.circle(image, (int(rng.integers(width)), int(rng.integers(height))), height // 3, (0.9, 0.2, 0.1), -1)
        images.append(np.clip(np.round(image * 255), 0, 255).astype(np.uint8))
    return np.stack(images)


def render_like(truths: np.ndarray, rng, sigma: float) -> np.ndarray:
    """A blurred, shifted, noisy copy of each truth, as a fitted avatar's render differs from it."""
    out = [np.roll(cv2.GaussianBlur(t.astype(np.float32), (0, 0), sigma), 1, axis=1) + rng.normal(0, 3, t.shape)
           for t in truths]
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def conv_dtypes(net: torch.nn.Module) -> tuple[list, list]:
    """(input dtypes and channels-last flags seen by every Conv2d of `net`, filled on each forward; hook handles)."""
    seen = []

    def record(_, args, output):
        seen.append((output.dtype, args[0].is_contiguous(memory_format=torch.channels_last)))

    return seen, [m.register_forward_hook(record) for m in net.modules() if isinstance(m, torch.nn.Conv2d)]


def test_lpips_float32_is_the_plain_layer_stack_and_lower_precisions_run_in_their_dtype(rng):
    truths = smooth_images(rng, 2, 32, 40)
    x, y = (torch.from_numpy(a).permute(0, 3, 1, 2).float() / 255 for a in (render_like(truths, rng, 1.0), truths))
    net = LPIPS("vgg", weights="random", seed=1)
    # float32: the layers called one by one, no autocast, no cast: bit for bit the reference path.
    h, taps = [((2 * t - 1) - net.shift) / net.scale for t in (x, y)], [[], []]
    for index, layer in enumerate(net.features[:max(net.taps) + 1]):
        h = [layer(v) for v in h]
        if index in net.taps:
            for side in (0, 1):
                taps[side].append(_unit(h[side]))
    by_hand = sum(lin((fx - fy).pow(2)).mean(dim=(1, 2, 3)) for fx, fy, lin in zip(*taps, net.lins))
    seen, _ = conv_dtypes(net.features)
    reference = net(x, y)
    assert torch.equal(reference, by_hand) and {dtype for dtype, _ in seen} == {torch.float32}

    # float16 without channels-last is left out: the CPU's float16 kernels are slow in that layout.
    for precision, dtype, channels_last in (("bfloat16", torch.bfloat16, False), ("bfloat16", torch.bfloat16, True),
                                            ("float16", torch.float16, True)):
        low = LPIPS("vgg", weights="random", seed=1, precision=precision, channels_last=channels_last)
        seen, _ = conv_dtypes(low.features)
        values = low(x, y)
        assert {d for d, _ in seen} == {dtype}
        assert all(cl for _, cl in seen) or not channels_last  # without it the CPU's kernels may pick either
        assert values.dtype == torch.float32
        assert not torch.equal(values, reference)  # it did compute in the lower precision
        torch.testing.assert_close(values, reference, rtol=0, atol=1e-3)  # issue 39's LPIPS bound
    with pytest.raises(ValueError, match="precision must be one of"):
        LPIPS("vgg", weights="random", precision="float8")


def test_half_precision_taps_are_normalised_in_float32_without_overflow():
    generator = torch.Generator().manual_seed(0)
    # Squares summed over 512 channels reach ~1.5e7: past float16's largest value (65504) had they been summed in it.
    values = torch.rand((2, 512, 3, 4), generator=generator, dtype=torch.float64) * 300
    values[0, :, 0, 0] = 0  # a pixel every channel of which is zero: eps keeps the quotient finite
    for dtype in (torch.float16, torch.bfloat16):
        tap = values.to(dtype)
        exact = tap.double().pow(2).sum(1, keepdim=True).sqrt() + 1e-10
        norm, unit = _channel_norm(tap), _unit(tap)
        assert norm.dtype == unit.dtype == torch.float32 and torch.isfinite(unit).all()
        torch.testing.assert_close(norm.double(), exact, rtol=1e-6, atol=0)
        torch.testing.assert_close(unit.double(), tap.double() / exact, rtol=1e-6, atol=0)
        assert unit[0, :, 0, 0].abs().max() == 0


def test_inception_features_in_bfloat16_are_float32_and_close(tmp_path, rng):
    from test_metrics import _TinyInception

    torch.manual_seed(0)
    torch.jit.script(_TinyInception()).save(str(tmp_path / "inception.pt"))
    images = torch.from_numpy(smooth_images(rng, 3, 64, 80)).permute(0, 3, 1, 2).float() / 255
    reference = InceptionFeatures(tmp_path / "inception.pt")(images)
    for channels_last in (False, True):
        low = InceptionFeatures(tmp_path / "inception.pt", precision="bfloat16", channels_last=channels_last)(images)
        assert low.dtype == torch.float32 and low.shape == reference.shape
        assert not torch.equal(low, reference)
        torch.testing.assert_close(low, reference, rtol=2e-2, atol=1e-3)  # bfloat16 keeps ~3 significant digits
    assert torch.equal(InceptionFeatures(tmp_path / "inception.pt", channels_last=True)(images), reference)


def chunked_levels(root, truths: np.ndarray, renders: dict[int, np.ndarray]) -> dict:
    """Each level's (N, H, W, 3) uint8 renders of camera cam00's frames 0..N-1 as the render stage stores them."""
    encoder = ChunkEncoder("png")
    for level, images in renders.items():
        for frame, image in enumerate(images):
            path = chunk_path(root / f"lod{level}", "cam00", frame // 8 * 8)
            encoder.add(path, frame, image)
            if frame % 8 == 7 or frame == len(images) - 1:
                encoder.finish_chunk(path, "cam00", level)
    encoder.close()
    write_manifest(root, {"split": "novel_view", "cameras": ["cam00"], "frames": list(range(len(truths))),
                          "levels": sorted(renders), "chunk_frames": 8, "codec": "png", "every_view": False})
    return {level: root / f"lod{level}" for level in renders}


def capture_of(tmp_path, rng, truths: np.ndarray):
    """A one-camera capture whose ground truth is `truths` (the frame's mask a box inside it)."""
    from test_metrics import _tiny_capture
    from pig._io import write_png

    frames, height, width = truths.shape[:3]
    capture_dir, _ = _tiny_capture(tmp_path, rng, width=width, height=height, frames=frames)
    for frame, image in enumerate(truths):
        write_png(capture_dir / "images" / "cam00" / f"{frame:08d}.png", image.astype(np.float64) / 255)
    return capture_dir


def test_evaluate_with_bfloat16_networks_on_the_cpu_stays_within_the_bounds(tmp_path, rng):
    from test_metrics import _TinyInception

    truths = smooth_images(rng, 5, 32, 48)
    capture_dir = capture_of(tmp_path, rng, truths)
    levels = chunked_levels(tmp_path / "chunked", truths, {0: render_like(truths, rng, 0.8),
                                                          1: render_like(truths, rng, 2.0)})
    torch.manual_seed(0)
    torch.jit.script(_TinyInception()).save(str(tmp_path / "inception.pt"))
    results = {}
    for precision in ("float32", "bfloat16"):
        low = precision != "float32"
        cfg = EvaluateConfig(batch_size=4, encode_workers=2, lpips_precision=precision,
                             fid_precision="float16" if low else "float32", channels_last=low)
        lpips = LPIPS("vgg", weights="random", precision=cfg.lpips_precision, channels_last=cfg.channels_last)
        inception = InceptionFeatures(tmp_path / "inception.pt", precision=cfg.fid_precision,
                                      channels_last=cfg.channels_last)
        results[precision] = evaluate_levels(Capture.load(capture_dir, cache_mb=0), "novel_view", levels, cfg, lpips,
                                             inception, torch.device("cpu"))
    for level in levels:
        (ref, ref_summary), (low, low_summary) = results["float32"][level], results["bfloat16"][level]
        for column in ("psnr", "ssim", "psnr_blank", "ssim_blank"):  # never leave float32
            np.testing.assert_array_equal(low[column], ref[column])
        assert not np.array_equal(low["lpips"], ref["lpips"])
        np.testing.assert_allclose(low["lpips"], ref["lpips"], rtol=0, atol=1e-3)
        assert low_summary["fid"] != ref_summary["fid"]
        assert low_summary["fid"] == pytest.approx(ref_summary["fid"], rel=5e-3) and ref_summary["fid"] > 0


def test_precision_options_are_checked_and_noted():
    preset = {"_path": "p.yaml", "evaluate": {"lpips_precision": "float16", "channels_last": True}}
    cfg = load_section(preset, "evaluate", EvaluateConfig)
    assert (cfg.lpips_precision, cfg.fid_precision, cfg.channels_last) == ("float16", "float32", True)
    assert precision_note(cfg) == "LPIPS network in float16 (features widened to float32)"
    assert precision_note(EvaluateConfig()) == ""
    with pytest.raises(ConfigError, match="lpips_precision"):
        load_section({"evaluate": {"lpips_precision": "half"}}, "evaluate", EvaluateConfig)


@pytest.mark.parametrize("lpips_window", [False, True])
def test_the_evaluate_pass_reads_the_device_only_after_its_last_batch(tmp_path, rng, lpips_window):
    # A host synchronisation per batch would stall a GPU pass at every batch; all of them come after the loop, so
    # twice the batches make the same synchronisations (pig.host_syncs counts them on any device). LPIPS's window
    # comes from the loader's boxes on the host, not from the device.
    from test_metrics import _TinyInception

    from pig.host_syncs import HostSyncs

    torch.manual_seed(0)
    torch.jit.script(_TinyInception()).save(str(tmp_path / "inception.pt"))
    lpips, inception = LPIPS("alex", weights="random"), InceptionFeatures(tmp_path / "inception.pt")
    counts = []
    for views in (4, 8):
        truths = smooth_images(rng, views, 32, 48)
        capture_dir = capture_of(tmp_path / f"v{views}", rng, truths)
        levels = chunked_levels(tmp_path / f"v{views}" / "chunked", truths,
                                {0: render_like(truths, rng, 0.8), 1: render_like(truths, rng, 2.0)})
        with HostSyncs() as syncs:
            evaluate_levels(Capture.load(capture_dir, cache_mb=0), "novel_view", levels,
                            EvaluateConfig(batch_size=2, encode_workers=2, lpips_window=lpips_window), lpips,
                            inception, torch.device("cpu"))
        counts.append(syncs.by_phase_op())
    assert counts[0] == counts[1] and sum(counts[0].values()) > 0
