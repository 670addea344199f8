"""Training objective: silhouette-aware masked 8 L1 + 2 (1 - SSIM) + 2 LPIPS.

Implements Eq. 15; the boundary band (dilate minus erode of the mask) is set to the background in
both render and ground truth, as MMLPHuman-style silhouette-aware masking does. The LPIPS term needs
pretrained weights that may be absent: `lpips_term` says in a plain record whether a fit had it, and
`fit_note` turns that record into the note the result tables carry.
"""
from __future__ import annotations

import sys
from typing import Callable

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from pig.avatar.lpips_crop import crop_view_sets, crop_views_sliced
from pig.metrics.lpips import LPIPS, WeightsMissing
from pig.metrics.ssim import ssim

# The LPIPS term's state in a fit: "on", or why it is not the paper's term; "unknown" for checkpoints written
# before the state was recorded.
LPIPS_STATES = ("on", "weights absent", "weight 0", "random weights", "unknown")
NET_NAMES = {"alex": "AlexNet", "vgg": "VGG"}
# Forms of the LPIPS term (FitConfig.lpips_form): the whole frames, or MMLPHuman's crops of the silhouette's box.
LPIPS_FORMS = ("full", "mmlphuman")


def lpips_term(cfg, device: str | torch.device = "cpu", notify: bool = True) -> tuple[torch.nn.Module | None, dict]:
    """The LPIPS module of Eq. 15 (frozen, on `device`) or None, and the record of its state:
    {"weight", "net", "state" (one of LPIPS_STATES), "detail" (why the weights are absent, else "")}.

    `cfg` is the preset's fit section (pig.avatar.training.FitConfig): weight_lpips, lpips_net, lpips_weights
    ("pretrained" or "random"), lpips_backbone_weights, lpips_linear_weights, seed. Absent pretrained
    weights leave the term out with a one-line notice on stderr (`notify`: a data-parallel fit's rank 0 alone tells);
    "random" looks up no file.
    """
    record = {"weight": float(cfg.weight_lpips), "net": cfg.lpips_net, "state": "on", "detail": ""}
    if cfg.weight_lpips <= 0:
        return None, {**record, "state": "weight 0"}
    if cfg.lpips_weights == "random":
        if notify:
            print(f"fit: LPIPS term with randomly initialised {cfg.lpips_net} weights (seed {cfg.seed}; for timing only)",
                  file=sys.stderr)
        net = LPIPS(cfg.lpips_net, weights="random", seed=cfg.seed)
        return net.to(device), {**record, "state": "random weights"}
    try:
        net = LPIPS(cfg.lpips_net, cfg.lpips_backbone_weights, cfg.lpips_linear_weights)
    except WeightsMissing as err:
        if notify:
            print(f"fit: LPIPS term left out of the loss ({err})", file=sys.stderr)
        return None, {**record, "state": "weights absent", "detail": str(err)}
    return net.to(device), record


def fit_note(record: dict) -> str:
    """The tables' note on a fit's LPIPS term (a record of `lpips_term`); empty when the term was on. No "; " in
    a note: the tables join a row's notes with it."""
    state = record["state"]
    if state == "on":
        return ""
    if state == "weights absent":
        return f"fit without the LPIPS term of Eq. 15 ({NET_NAMES.get(record['net'], record['net'])} weights absent)"
    if state == "weight 0":
        return "fit without the LPIPS term (weight 0)"
    if state == "random weights":
        return "fit with a randomly initialised LPIPS (timing only)"
    if state == "unknown":
        return "fit's LPIPS term unknown (avatar.pt written before fits recorded it, re-run the fit)"
    raise ValueError(f"LPIPS term state {state!r}: expected one of {LPIPS_STATES}")


def lpips_views(lpips, x: torch.Tensor, y: torch.Tensor, masks: torch.Tensor, background: torch.Tensor, form: str,
                crop: int = 512, offsets: torch.Tensor | None = None, sliced: bool = False,
                count: Callable[[], torch.Tensor] | torch.Tensor | float | None = None) -> torch.Tensor:
    """Eq. 15's LPIPS term of (B, 3, H, W) renders `x` and targets `y` (bands applied) in `form` (LPIPS_FORMS).

    "full": the mean over views of `lpips(x, y)` on the whole frames. "mmlphuman": the mean over the views with a
    non-empty mask of the distances of their `crop`-sized squares (pig.avatar.lpips_crop; `offsets` (B, 2) uniforms
    turn on the random windows, `sliced` crops a view at a time as MMLPHuman's code does), 0 where no view has one.
    `lpips` maps two (B, 3, h, w) batches to (B,) distances. `count`: the divisor of the sum in place of this
    batch's count of views (of those with a mask, "mmlphuman"), where the batch is a part of a larger one; a callable
    is called once the distances are queued (pig.avatar.distributed.SummedCount: the wait for a collective comes after
    them).
    """
    divisor = count if callable(count) else (lambda: count)
    if form == "full":
        distances = lpips(x, y)
        return distances.mean() if count is None else distances.sum() / divisor()
    if form != "mmlphuman":
        raise ValueError(f"LPIPS form must be one of {LPIPS_FORMS}, found {form!r}")
    if sliced:
        cx, valid = crop_views_sliced(x, masks, background, crop, offsets)
        cy, _ = crop_views_sliced(y, masks, background, crop, offsets)
    else:  # one box and set of taps for both: the crop's index work once a loss evaluation (benchmarks/NOTES.md)
        (cx, cy), valid = crop_view_sets([x, y], masks, background, crop, offsets)
    weights = valid.to(torch.float32)
    total = (lpips(cx, cy) * weights).sum()
    return total / (weights.sum() if count is None else torch.as_tensor(divisor())).clamp(min=1)


def band_radius(height: int, radius_px: float, reference_height: int) -> int:
    """Band radius scaled with image size: `radius_px` at `reference_height` rows (THuman4: 3 at 1150)."""
    return int(round(radius_px * height / reference_height))


def boundary_band(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """(B, H, W) bool mask -> (B, H, W) bool band: dilate minus erode with a (2r+1)^2 square."""
    if radius <= 0:
        return torch.zeros_like(mask)
    m = mask[:, None].float()
    dilated = _square_max(m, radius) > 0.5
    eroded = -_square_max(-m, radius) > 0.5
    return (dilated & ~eroded)[:, 0]


def boundary_band_host(mask: np.ndarray, radius: int) -> np.ndarray:
    """`boundary_band` of one (H, W) bool mask on the host with OpenCV, the same pixels (tests/test_fit.py): what
    the view loader threads compute with `fit.host_band`, so that the training device does not."""
    if radius <= 0:
        return np.zeros(mask.shape, bool)
    m, kernel = np.ascontiguousarray(mask, dtype=bool).view(np.uint8), np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    # Erosion treats the outside as inside (replicated edge), as the max-pool's padding leaves it out.
    return cv2.dilate(m, kernel).view(bool) & ~cv2.erode(m, kernel, borderType=cv2.BORDER_REPLICATE).view(bool)


def _square_max(m: torch.Tensor, radius: int) -> torch.Tensor:
    """Max over the (2r+1)^2 window of each pixel of (B, 1, H, W), as a column pass then a row pass: the same
    maximum from 2(2r+1) reads a pixel instead of (2r+1)^2 (20 masks at 1330 x 1150, r = 3, on an H100: 2.3 ms
    against 3.2 ms for the square window; benchmarks/NOTES.md, Fit)."""
    size = 2 * radius + 1
    columns = F.max_pool2d(m, (size, 1), stride=1, padding=(radius, 0))
    return F.max_pool2d(columns, (1, size), stride=1, padding=(0, radius))


def apply_band(images: torch.Tensor, band: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Set band pixels of (B, H, W, 3) images to the (3,) or (B, 3) background."""
    bg = background.to(images).expand(images.shape[0], 3)[:, None, None, :]
    return torch.where(band[..., None], bg, images)


def image_loss(render: torch.Tensor, target: torch.Tensor, band: torch.Tensor, background: torch.Tensor,
               weights: tuple[float, float, float], lpips=None, blur: str = "conv",
               ssim_window: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Loss terms of (B, H, W, 3) render and target; `lpips` is a module or None (term left out); `blur`
    picks SSIM's implementation and `ssim_window` is its window (pig.metrics.ssim.ssim_map).

    Returns {"l1", "ssim", "lpips" (if used), "total"}; "ssim" holds 1 - SSIM.
    """
    w_l1, w_ssim, w_lpips = weights
    x = apply_band(render, band, background).permute(0, 3, 1, 2)
    y = apply_band(target, band, background).permute(0, 3, 1, 2)
    terms = {"l1": (x - y).abs().mean(), "ssim": 1 - ssim(x, y, blur=blur, window=ssim_window)}
    total = w_l1 * terms["l1"] + w_ssim * terms["ssim"]
    if lpips is not None and w_lpips > 0:
        terms["lpips"] = lpips(x, y).mean()
        total = total + w_lpips * terms["lpips"]
    terms["total"] = total
    return terms
