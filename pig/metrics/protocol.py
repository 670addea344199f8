"""Evaluation protocols (`evaluate.protocol`): how a peer scores held-out views, so its numbers compare with ours.

`ours` (the default; the paper's Section 4.2 as this project reads it): PSNR, SSIM (11 x 11 Gaussian window,
sigma 1.5) and LPIPS on the full frame; FID on the full frame resized to 299 x 299 by antialiased bilinear.
`animatable_gaussians` (AnimatableGaussians' eval/score.py and eval/comparison_body_only_avatars.py): PSNR and
SSIM on the full frame, SSIM with scikit-image's defaults (7 x 7 uniform window, sample covariance); LPIPS and
FID on a crop to the ground-truth mask's box padded by 50 px, squared by centring it on ones, resized to
512 x 512 (bilinear); FID resized to 299 x 299 as pytorch-fid does (bilinear without antialiasing).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class Protocol:
    name: str
    ssim_window: str  # "gaussian11" (pig.metrics.ssim) or "uniform7" (scikit-image's defaults)
    crop: bool  # LPIPS and FID on the mask-box crop instead of the full frame
    fid_resize: str  # "antialiased_bilinear" (torch, antialias=True) or "pytorch_fid" (bilinear, no antialias)
    note: str


PROTOCOLS = {
    "ours": Protocol("ours", "gaussian11", False, "antialiased_bilinear",
                     "full frame; SSIM 11x11 Gaussian window; FID resize antialiased bilinear"),
    "animatable_gaussians": Protocol(
        "animatable_gaussians", "uniform7", True, "pytorch_fid",
        "AnimatableGaussians: SSIM scikit-image defaults (7x7 uniform); LPIPS and FID on the mask box + 50 px, "
        "squared on white, 512x512; FID resize as pytorch-fid (bilinear, no antialias)"),
}
CROP_PAD, CROP_SIZE = 50, 512


def protocol(name: str) -> Protocol:
    if name not in PROTOCOLS:
        raise ValueError(f"evaluate.protocol: unknown protocol {name!r}; expected one of {sorted(PROTOCOLS)}")
    return PROTOCOLS[name]


def ssim_uniform(x: torch.Tensor, y: torch.Tensor, window: int = 7, data_range: float = 1.0) -> torch.Tensor:
    """(B,) SSIM of (B, C, H, W) images as scikit-image's `structural_similarity` computes it by default: a
    `window` x `window` uniform filter, sample (N - 1) covariances, the map's mean over the pixels whose window
    lies inside the image, then over channels. Computed in float64."""
    if min(x.shape[-2:]) < window:
        raise ValueError(f"ssim_uniform: images of {tuple(x.shape[-2:])} are smaller than the {window}x{window} window")
    x, y = x.double(), y.double()
    channels = x.shape[1]

    def mean(t):
        return F.avg_pool2d(t.reshape(-1, 1, *t.shape[-2:]), window, stride=1).reshape(-1, channels,
                                                                                     *_valid(t, window))

    mx, my = mean(x), mean(y)
    norm = window**2 / (window**2 - 1)
    vx, vy, vxy = norm * (mean(x * x) - mx**2), norm * (mean(y * y) - my**2), norm * (mean(x * y) - mx * my)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return s.mean(dim=(1, 2, 3))


def _valid(t: torch.Tensor, window: int) -> tuple[int, int]:
    return t.shape[-2] - window + 1, t.shape[-1] - window + 1


def mask_box(mask: torch.Tensor, pad: int = CROP_PAD) -> tuple[int, int, int, int]:
    """(top, bottom, left, right) of a (H, W) mask's box widened by `pad`, clipped to the image; rows
    top..bottom-1. The box's end is the last mask pixel + pad, exclusive, as AnimatableGaussians slices it.
    An empty mask gives the whole image."""
    rows, cols = torch.nonzero(mask.any(1)).flatten(), torch.nonzero(mask.any(0)).flatten()
    height, width = mask.shape
    if len(rows) == 0:
        return 0, height, 0, width
    top, bottom = max(int(rows[0]) - pad, 0), min(int(rows[-1]) + pad, height)
    left, right = max(int(cols[0]) - pad, 0), min(int(cols[-1]) + pad, width)
    return top, bottom, left, right


def crop_to_mask_box(images: torch.Tensor, masks: torch.Tensor, pad: int = CROP_PAD, size: int = CROP_SIZE,
                     fill: float = 1.0) -> torch.Tensor:
    """(B, C, size, size) crops of (B, C, H, W) images to each (B, H, W) mask's widened box, centred in a square
    of `fill` (the shorter side's margins split with the extra pixel after), resized by bilinear interpolation
    with half-pixel centres and no antialiasing (OpenCV's INTER_LINEAR)."""
    crops = []
    for image, mask in zip(images, masks):
        top, bottom, left, right = mask_box(mask, pad)
        height, width = bottom - top, right - left
        side = max(height, width)
        square = torch.full((image.shape[0], side, side), fill, dtype=image.dtype, device=image.device)
        v0, u0 = ((side - height) // 2, 0) if height < width else (0, (side - width) // 2)
        square[:, v0:v0 + height, u0:u0 + width] = image[:, top:bottom, left:right]
        crops.append(F.interpolate(square[None], size=(size, size), mode="bilinear", align_corners=False,
                                   antialias=False)[0])
    return torch.stack(crops)
