"""Eq. 15's LPIPS term in its forms (`full`, `mmlphuman`) and with its speed levers, on the CPU with random weights:
`full` is the term as fits computed it before the forms existed; MMLPHuman's crop against a canvas built with numpy
and resized with OpenCV; what each form sees of floaters; the schedule; TrainingLPIPS against the float32 reference."""
import math

import cv2
import numpy as np
import pandas as pd
import pytest
import torch
from torch._dynamo.utils import counters

from pig.avatar.lpips_crop import crop_views, crop_views_sliced, mask_boxes
from pig.avatar.losses import lpips_views
from pig.avatar.training import FitConfig, LossTerms
from pig.config import ConfigError, derive_preset, load_preset, load_section
from pig.metrics.lpips import LPIPS, TrainingLPIPS
from op_names import OpNames

BG = (0.2, 0.5, 0.9)


def _masks(height: int, width: int, boxes: list) -> torch.Tensor:
    """(B, H, W) masks, each a filled rectangle (top, left, bottom, right) inclusive, or None for an empty one."""
    masks = torch.zeros(len(boxes), height, width, dtype=torch.bool)
    for k, box in enumerate(boxes):
        if box is not None:
            top, left, bottom, right = box
            masks[k, top:bottom + 1, left:right + 1] = True
    return masks


def _reference_crop(image: np.ndarray, mask: np.ndarray, size: int, offset=None) -> np.ndarray | None:
    """MMLPHuman's crop of one (H, W, 3) float64 image from its stated steps, with numpy and OpenCV: the box from the
    first to the last masked row and column (the last left out), a background square with the box centred on the
    shorter side, then a bilinear resize to size x size (cv2.INTER_LINEAR: half-pixel centres, edges clamped, no
    antialiasing, as F.interpolate), or the window at `offset` (fractions) when the square is larger. None if empty."""
    rows, cols = np.nonzero(mask.any(1))[0], np.nonzero(mask.any(0))[0]
    if rows.size == 0:
        return None
    top, left, h, w = rows[0], cols[0], rows[-1] - rows[0], cols[-1] - cols[0]
    side = max(h, w)
    if side == 0:
        return None
    canvas = np.empty((side, side, 3))
    canvas[:] = BG
    v0, u0 = (side - h) // 2, (side - w) // 2
    canvas[v0:v0 + h, u0:u0 + w] = image[top:top + h, left:left + w]
    if offset is not None and side > size:
        dv, du = (min(int(np.floor(o * (side - size + 1))), side - size) for o in offset)
        return canvas[dv:dv + size, du:du + size]
    return cv2.resize(canvas, (size, size), interpolation=cv2.INTER_LINEAR)


# Hand-built masks in a 60 x 80 frame, crop 32: a 9 x 4 box (smaller than the crop), 50 x 70 (larger), one on the
# frame's top and left border, one spanning the frame's full height, a single pixel, and an empty mask.
BOXES = [(10, 20, 19, 24), (5, 4, 55, 74), (0, 0, 40, 12), (0, 30, 59, 45), (30, 30, 30, 30), None]


@pytest.mark.parametrize("windows", [False, True])
@pytest.mark.parametrize("crop", [crop_views, crop_views_sliced])
def test_mmlphuman_crop_geometry_against_numpy_and_opencv(crop, windows):
    gen = torch.Generator().manual_seed(0)
    images = torch.rand(len(BOXES), 3, 60, 80, generator=gen, dtype=torch.float64)
    masks = _masks(60, 80, BOXES)
    offsets = torch.rand(len(BOXES), 2, generator=gen, dtype=torch.float64) if windows else None
    crops, valid = crop(images, masks, torch.tensor(BG, dtype=torch.float64), 32, offsets)
    assert crops.shape == (len(BOXES), 3, 32, 32) and valid.tolist() == [True, True, True, True, False, False]
    for k in range(len(BOXES)):
        expected = _reference_crop(images[k].permute(1, 2, 0).numpy(), masks[k].numpy(), 32,
                                   None if offsets is None else offsets[k].tolist())
        got = crops[k].permute(1, 2, 0).numpy()
        if expected is None:  # an empty box: a background square, left out of the term
            np.testing.assert_allclose(got, np.broadcast_to(BG, got.shape), atol=1e-12)
        else:
            np.testing.assert_allclose(got, expected, atol=1e-9)
    # The boxes as MMLPHuman takes them: (top, left, last row - first, last column - first).
    assert [t.tolist() for t in mask_boxes(masks)] == [[10, 5, 0, 0, 30, 0], [20, 4, 0, 30, 30, 0],
                                                       [9, 50, 40, 59, 0, 0], [4, 70, 12, 15, 0, 0]]


def test_crop_is_differentiable_with_the_gradient_of_its_slices():
    """The fixed-shape crop's gradient with respect to the image equals the sliced crop's (a vector-Jacobian
    product with the same random cotangent), both in float64, windows on and off."""
    gen = torch.Generator().manual_seed(1)
    masks = _masks(60, 80, BOXES[:4])
    for offsets in (None, torch.rand(4, 2, generator=gen, dtype=torch.float64)):
        cotangent = torch.rand(4, 3, 32, 32, generator=gen, dtype=torch.float64)
        grads = []
        for crop in (crop_views, crop_views_sliced):
            image = torch.rand(4, 3, 60, 80, generator=torch.Generator().manual_seed(2), dtype=torch.float64,
                               requires_grad=True)
            (crop(image, masks, torch.tensor(BG, dtype=torch.float64), 32, offsets)[0] * cotangent).sum().backward()
            grads.append(image.grad)
        torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=1e-12)


def _alex(dtype=torch.float64) -> LPIPS:
    return LPIPS("alex", weights="random", seed=0).to(dtype)


def _batch(height=64, width=72, count=3, seed=0):
    gen = torch.Generator().manual_seed(seed)
    render = torch.rand(count, height, width, 3, generator=gen, dtype=torch.float64)
    target = torch.rand(count, height, width, 3, generator=gen, dtype=torch.float64)
    masks = torch.zeros(count, height, width, dtype=torch.bool)
    masks[:, 8:56, 20:52] = True
    return render, target, masks


def test_full_form_is_the_term_fits_had_before_the_forms_values_and_gradients():
    """`full` (the default form): the mean over views of LPIPS of the banded whole frames, as LossTerms computed
    it before (written out here from LPIPS.forward), value and gradient with respect to the render, in float64."""
    render, target, masks = _batch()
    background = torch.tensor(BG, dtype=torch.float64)
    band = torch.zeros_like(masks)
    band[:, 6:10, :] = True
    net = _alex()
    cfg = FitConfig(weight_lpips=2.0, lpips_net="alex", lpips_weights="random")
    assert cfg.lpips_form == "full"
    x = render.clone().requires_grad_(True)
    term = LossTerms(cfg, background, net, compiled=False)(x, target, masks, 64, band)["lpips"]
    (grad,) = torch.autograd.grad(term, x)

    r = render.clone().requires_grad_(True)
    banded = [torch.where(band[..., None], background, im).permute(0, 3, 1, 2) for im in (r, target)]
    expected = net(*banded).mean()  # the old code's `.float()` is a no-op in float32 fits
    (expected_grad,) = torch.autograd.grad(expected, r)
    torch.testing.assert_close(term, expected, rtol=1e-12, atol=0)
    torch.testing.assert_close(grad, expected_grad, rtol=1e-10, atol=1e-14)
    assert grad.abs().max() > 0


def test_floaters_outside_the_mask_box_are_seen_by_full_only():
    """A render equal to its target but for floaters: outside the mask's box, `full` scores them (> 0) and
    `mmlphuman` sees exactly nothing (its crop is the box and background); inside the box but off the mask, both
    see them. The L1 and SSIM terms score the whole frame in either form."""
    net = _alex()
    target = torch.rand(1, 3, 64, 72, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    masks = torch.zeros(1, 64, 72, dtype=torch.bool)
    masks[0, 20:44, 30:42] = True
    background = torch.tensor(BG, dtype=torch.float64)
    outside, inside = target.clone(), target.clone()
    outside[:, :, 2:10, 2:12] = 1.0  # left of and above the box
    inside[:, :, 22:30, 30:33] = 1.0  # inside the box's rows and columns...
    masks[0, 22:30, 30:33] = False  # ...where the mask has a hole
    for form in ("full", "mmlphuman"):
        assert lpips_views(net, target, target, masks, background, form, 32).item() == 0
    assert lpips_views(net, outside, target, masks, background, "full", 32).item() > 1e-4
    assert lpips_views(net, outside, target, masks, background, "mmlphuman", 32).item() == 0
    assert lpips_views(net, inside, target, masks, background, "mmlphuman", 32).item() > 1e-4


def test_views_with_an_empty_mask_are_left_out_of_the_mean():
    net = _alex()
    render, target, masks = _batch(count=3)
    x, y = (t.permute(0, 3, 1, 2) for t in (render, target))
    background = torch.tensor(BG, dtype=torch.float64)
    masks[1] = False
    crops = [crop_views(t, masks, background, 32)[0] for t in (x, y)]
    per_view = net(*crops)
    expected = (per_view[0] + per_view[2]) / 2
    torch.testing.assert_close(lpips_views(net, x, y, masks, background, "mmlphuman", 32), expected, rtol=1e-12, atol=0)
    masks[:] = False
    assert lpips_views(net, x, y, masks, background, "mmlphuman", 32).item() == 0


@pytest.mark.parametrize("windows", [False, True])
def test_renders_and_targets_are_cropped_with_one_box_and_set_of_taps(windows):
    """The `mmlphuman` term crops renders and targets by the same masks and windows: their boxes, canvas positions
    and bilinear taps are computed once (mask_boxes' two `amin`s once, not twice: ~170 ops of the ~950 a GPU step
    launches eagerly, benchmarks/NOTES.md), and the term and its gradient are those of two `crop_views`, bit for
    bit."""
    net = _alex()
    render, target, masks = _batch(count=3)
    masks[1, 30:40, 10:60] = True  # a box larger than the crop: the windows move
    x, y = (t.permute(0, 3, 1, 2) for t in (render, target))
    background = torch.tensor(BG, dtype=torch.float64)
    offsets = torch.rand(3, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) if windows else None
    xg = x.clone().requires_grad_(True)
    with OpNames() as ops:
        term = lpips_views(net, xg, y, masks, background, "mmlphuman", 32, offsets)
    (grad,) = torch.autograd.grad(term, xg)
    xr = x.clone().requires_grad_(True)
    (cx, valid), (cy, _) = (crop_views(t, masks, background, 32, offsets) for t in (xr, y))
    weights = valid.to(torch.float64)
    expected = (net(cx, cy) * weights).sum() / weights.sum().clamp(min=1)
    (expected_grad,) = torch.autograd.grad(expected, xr)
    assert torch.equal(term, expected) and torch.equal(grad, expected_grad) and grad.abs().max() > 0
    assert ops.names["amin"] == 2 and ops.names["gather"] == 8  # one box (rows, columns); 4 taps x 2 batches


def test_schedule_and_windows_follow_the_run():
    """Before `lpips_start` the term is 0 and the total is L1 + SSIM; from `lpips_patches_from` on the crops are
    random windows (the boxes here are larger than the crop), drawn from (seed, iteration): the same at a repeat."""
    render, target, masks = _batch(count=2)
    background = torch.tensor(BG, dtype=torch.float64)
    band = torch.zeros_like(masks)
    cfg = FitConfig(weight_lpips=2.0, lpips_net="alex", lpips_weights="random", lpips_form="mmlphuman", lpips_crop=32,
                    lpips_start=0.25, lpips_patches_from=0.5)
    loss = LossTerms(cfg, background, _alex(), compiled=False)
    loss.at(10, 0.2)
    early = loss(render, target, masks, 64, band)
    assert early["lpips"].item() == 0
    torch.testing.assert_close(early["total"], 8 * early["l1"] + 2 * early["ssim"], rtol=1e-12, atol=0)
    x, y = (t.permute(0, 3, 1, 2) for t in (render, target))
    resized = lpips_views(loss.lpips, x, y, masks, background, "mmlphuman", 32)
    loss.at(30, 0.3)
    assert loss(render, target, masks, 64, band)["lpips"].item() == pytest.approx(resized.item(), rel=1e-12)
    values = []
    for iteration in (60, 61, 60):
        loss.at(iteration, 0.6)
        values.append(loss(render, target, masks, 64, band)["lpips"].item())
    assert values[0] == values[2] and values[0] != values[1] and values[0] != pytest.approx(resized.item(), rel=1e-6)


def test_a_subset_of_views_scores_that_many_of_them():
    """`lpips_views: 1` of 3: the term is one view's own distance, and over iterations not always the same view."""
    render, target, masks = _batch(count=3)
    background = torch.tensor(BG, dtype=torch.float64)
    band = torch.zeros_like(masks)
    net = _alex()
    per_view = [lpips_views(net, *(t[k:k + 1].permute(0, 3, 1, 2) for t in (render, target)), masks[k:k + 1],
                            background, "full").item() for k in range(3)]
    loss = LossTerms(FitConfig(weight_lpips=2.0, lpips_net="alex", lpips_weights="random", lpips_views=1), background, net,
                     compiled=False)
    picked = []
    for iteration in range(6):
        loss.at(iteration, 0.5)
        value = loss(render, target, masks, 64, band)["lpips"].item()
        picked.append(min(range(3), key=lambda k: abs(per_view[k] - value)))
        assert value == pytest.approx(per_view[picked[-1]], rel=1e-12)
    assert len(set(picked)) > 1


def test_training_lpips_levers_against_the_float32_reference():
    """TrainingLPIPS: the head in the features' dtype (float64 here) is the reference's algebra (1e-12); the bf16
    backbone and head stay within 2 % of the float32 reference distance (bf16 keeps 8 bits; measured 0.03 %); the
    compiled module matches the eager one (float32 reordering, 1e-5) and compiles once for one input shape."""
    gen = torch.Generator().manual_seed(4)
    x64 = torch.rand(3, 3, 48, 48, generator=gen, dtype=torch.float64)
    y64 = torch.rand(3, 3, 48, 48, generator=gen, dtype=torch.float64)
    net64 = _alex()
    torch.testing.assert_close(TrainingLPIPS(net64, bf16_head=True)(x64, y64), net64(x64, y64), rtol=1e-12, atol=0)

    net = _alex(torch.float32)
    x, y = x64.float(), y64.float()
    reference = net(x, y)
    fast = TrainingLPIPS(net, bf16=True, bf16_head=True)(x, y)
    assert fast.dtype == torch.float32 and ((fast - reference).abs() / reference).max() < 0.02

    graphs = counters["stats"]["unique_graphs"]
    compiled = TrainingLPIPS(net, bf16_head=True, compiled=True)
    xg = x.clone().requires_grad_(True)
    for _ in range(2):
        value = compiled(xg, y)
        (grad,) = torch.autograd.grad(value.sum(), xg)
    assert counters["stats"]["unique_graphs"] == graphs + 1  # one graph, no recompilation at the second call
    xe = x.clone().requires_grad_(True)
    eager = net(xe, y)
    (eager_grad,) = torch.autograd.grad(eager.sum(), xe)
    torch.testing.assert_close(value, eager, rtol=0, atol=1e-5)
    assert (grad - eager_grad).abs().max() <= 1e-4 * eager_grad.abs().max()


def test_lpips_form_settings_are_checked_and_paper_uses_mmlphuman():
    paper = load_section(load_preset("paper"), "fit", FitConfig)
    assert (paper.lpips_form, paper.lpips_crop, paper.weight_lpips) == ("mmlphuman", 512, 2.0)
    # MMLPHuman's schedule (config/*.yaml): LPIPS after 6000 and random windows from 300000 of 800000 iterations.
    assert paper.lpips_start == pytest.approx(6000 / 800_000) and paper.lpips_patches_from == pytest.approx(0.375)
    for bad, message in (({"lpips_form": "crop"}, "fit.lpips_form must be one of ('full', 'mmlphuman')"),
                         ({"lpips_start": 2.0}, "fit.lpips_start must lie in [0, 1]"),
                         ({"lpips_crop": 8, "lpips_net": "vgg"}, "fit.lpips_crop must be at least 16")):
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
            FitConfig(**bad)


def test_fit_with_the_mmlphuman_form_trains_with_the_term(small_capture, tmp_path):
    from pig.avatar.training import fit

    derive_preset(tmp_path / "preset.yaml", "test",
                  fit={"iterations": 2, "eval_every": 2, "weight_lpips": 2.0, "lpips_net": "alex",
                       "lpips_weights": "random", "lpips_form": "mmlphuman", "lpips_crop": 32,
                       "lpips_patches_from": 0.5},
                  avatar={"num_anchors": 300}, rasterizer={"backend": "cpu"})
    fit(small_capture, tmp_path / "pig", str(tmp_path / "preset.yaml"))
    steps = pd.read_csv(tmp_path / "pig" / "train_log.csv").iloc[1:]
    assert len(steps) == 2 and (steps["lpips"] > 0).all() and not steps["lpips"].isna().any()
    assert steps["loss"].tolist() == pytest.approx((8 * steps["l1"] + 2 * steps["ssim"] + 2 * steps["lpips"]).tolist(),
                                                   rel=1e-5)
    assert all(math.isfinite(v) for v in steps["loss"])
