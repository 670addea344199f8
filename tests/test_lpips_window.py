"""LPIPS over the window of a frame where two images can differ (LPIPS.window, evaluate.lpips_window): the window's
geometry against closed forms and the network's own shapes, its distance against the whole frame's in float64, and
the evaluate pass with the window against the pass without it."""
import cv2
import numpy as np
import pytest
import torch

from pig.data.capture import Capture
from pig.metrics.lpips import LPIPS, MIN_SIDE
from pig.stages.evaluate import EvaluateConfig, LoadedBatch, evaluate_levels, nonzero_box, union_box


@pytest.mark.parametrize("net, field", [("vgg", 196), ("alex", 163)])
def test_receptive_field_and_tap_sizes_are_the_networks(net, field):
    # The deepest tap's receptive field of VGG16 conv5_3 and AlexNet conv5 (the published 196 and 163 pixels), on
    # the grid of 16 pixels their pools leave; each tap's size as the network computes it.
    metric = LPIPS(net, weights="random")
    assert (metric.field, metric.stride) == (field, 16)
    for height, width in [(MIN_SIDE[net], MIN_SIDE[net]), (181, 243), (230, 265), (64, 47)]:
        taps = metric._activations(torch.rand(1, 3, height, width))
        assert metric.tap_sizes(height, width) == [tuple(tap.shape[-2:]) for tap in taps]


@pytest.mark.parametrize("net, height, width", [("vgg", 225, 233), ("alex", 301, 407)])
def test_windowed_distance_is_the_whole_frames(net, height, width):
    # Float64, random weights, a textured frame shared by both images (no black to hide an error) and a changed box
    # at the centre, at two corners and one pixel at an edge: the window's distance equals the
    # frame's to rounding, where a margin 16 px short of the field is off by >= 1e-8 (benchmarks/NOTES.md).
    torch.manual_seed(0)
    metric = LPIPS(net, weights="random").double()
    y = torch.rand(1, 3, height, width, dtype=torch.float64)
    boxes = [(140, 150, 200, 230), (0, 5, 0, 7), (height - 11, height, width - 12, width), (150, 151, 0, 1)]
    for box in boxes:
        x = y.clone()
        top, bottom, left, right = box
        x[:, :, top:bottom, left:right] = torch.rand(1, 3, bottom - top, right - left, dtype=torch.float64)
        rows, cols = metric.window(box, height, width)
        assert rows.start % 16 == 0 and cols.start % 16 == 0
        assert rows.start <= top and rows.stop >= bottom and cols.start <= left and cols.stop >= right
        windowed = metric.distance(x[..., rows, cols], metric.reference(y[..., rows, cols]), frame=(height, width))
        whole = metric(x, y)
        assert (whole > 0).all()
        torch.testing.assert_close(windowed, whole, rtol=1e-12, atol=0)
    # The corner box's window is a corner of the frame: the test cuts something.
    rows, cols = metric.window(boxes[1], height, width)
    assert rows.stop < height and cols.stop < width
    # Identical images: zero over any window.
    rows, cols = metric.window((0, 1, 0, 1), height, width)
    assert metric.distance(y[..., rows, cols], metric.reference(y[..., rows, cols]), frame=(height, width)).eq(0).all()


def test_a_window_smaller_than_the_network_takes_the_whole_frame():
    metric = LPIPS("alex", weights="random")
    assert metric.window((0, 1, 0, 1), 20, 31) == (slice(0, 20), slice(0, 31))


def test_nonzero_box_against_argwhere(rng):
    for shape in [(7, 9), (7, 9, 3), (1, 1), (40, 30, 3)]:
        for density in (0.0, 0.002, 0.05, 1.0):
            image = (rng.random(shape) < density).astype(np.uint8) * rng.integers(1, 256, shape).astype(np.uint8)
            points = np.argwhere(image.reshape(*shape[:2], -1).any(-1))
            expected = ((shape[0], 0, shape[1], 0) if len(points) == 0 else
                        (points[:, 0].min(), points[:, 0].max() + 1, points[:, 1].min(), points[:, 1].max() + 1))
            assert nonzero_box(image) == tuple(int(v) for v in expected)
            assert nonzero_box(image > 0) == nonzero_box(image)
    with pytest.raises(ValueError, match="bool or unsigned"):
        nonzero_box(np.zeros((2, 2), np.float32))


def test_changed_box_is_the_union_and_a_black_batch_a_pixel():
    empty = [5, 0, 6, 0]
    batch = LoadedBatch([], torch.zeros(0), torch.zeros(0), {}, boxes=np.array([[empty, [1, 3, 2, 4]],
                                                                                 [[2, 5, 0, 1], empty]]))
    assert batch.changed_box() == (1, 5, 0, 4)
    batch.boxes = np.array([[empty, empty]])
    assert batch.changed_box() == (0, 1, 0, 1) and union_box(batch.boxes) is None
    assert union_box([nonzero_box(np.eye(3, dtype=bool)), (0, 1, 2, 3)]) == (0, 3, 0, 3)


def _capture_with_a_small_subject(tmp_path, rng, frames: int, height: int, width: int):
    """A one-camera capture whose truths are textured only inside a small mask (black elsewhere, as the evaluation
    masks them), and two LODs' renders that spill a few pixels past the mask; returns (capture dir, levels)."""
    from test_metric_precision import chunked_levels, render_like, smooth_images
    from test_metrics import _tiny_capture

    from pig._io import write_png

    capture_dir, _ = _tiny_capture(tmp_path, rng, width=width, height=height, frames=frames)
    mask = np.zeros((height, width), np.uint8)
    mask[200:240, 150:180] = 255
    truths = smooth_images(rng, frames, height, width)
    for frame, image in enumerate(truths):
        write_png(capture_dir / "images" / "cam00" / f"{frame:08d}.png", image.astype(np.float64) / 255)
        cv2.imwrite(str(capture_dir / "masks" / "cam00" / f"{frame:08d}.png"), mask)
    spill = np.zeros((height, width, 1), np.uint8)
    spill[196:244, 146:186] = 1
    renders = {level: render_like(truths, rng, sigma) * spill for level, sigma in ((0, 0.8), (1, 2.0))}
    renders[1][1, 20, 420] = 200  # a floater far from the subject: the window must reach it
    return capture_dir, chunked_levels(tmp_path / "chunked", truths, renders), truths, renders, mask > 0


def test_evaluate_with_the_window_scores_as_without(tmp_path, rng):
    height, width = 420, 700
    capture_dir, levels, truths, renders, mask = _capture_with_a_small_subject(tmp_path, rng, 3, height, width)
    metric = LPIPS("alex", weights="random")
    results = {}
    for windowed in (False, True):
        cfg = EvaluateConfig(batch_size=2, encode_workers=2, lpips_window=windowed)
        results[windowed] = evaluate_levels(Capture.load(capture_dir, cache_mb=0), "novel_view", levels, cfg, metric,
                                            None, torch.device("cpu"))
    for level in levels:
        whole, window = results[False][level][0], results[True][level][0]
        assert (whole["lpips"] > 0).all()
        np.testing.assert_allclose(window["lpips"], whole["lpips"], rtol=1e-5, atol=0)
        for column in ("psnr", "ssim"):
            np.testing.assert_array_equal(window[column], whole[column])
    # Windows smaller than the frame (the floater's batch too), and one that left out the renders' own boxes (the
    # mask's and the spill's only) would miss the floater.
    assert metric.window((196, 244, 146, 421), height, width)[1].stop < width
    as_images = lambda array: torch.from_numpy(array).permute(2, 0, 1)[None].float() / 255
    x, y = as_images(renders[1][1]), as_images(truths[1] * mask[..., None])
    rows, cols = metric.window((196, 244, 146, 186), height, width)
    missed = metric.distance(x[..., rows, cols], metric.reference(y[..., rows, cols]), frame=(height, width))
    assert abs(missed.item() / metric(x, y).item() - 1) > 1e-3
