"""Training objective: silhouette-aware masked 8 L1 + 2 (1 - SSIM) + 2 LPIPS.

Implements Eq. 15; the boundary band (dilate minus erode of the mask) is set to the background in
both render and ground truth, as MMLPHuman-style silhouette-aware masking does.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from pig.metrics.ssim import ssim


def band_radius(height: int, radius_px: float, reference_height: int) -> int:
    """Band radius scaled with image size: `radius_px` at `reference_height` rows (THuman4: 3 at 1150)."""
    return int(round(radius_px * height / reference_height))


def boundary_band(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """(B, H, W) bool mask -> (B, H, W) bool band: dilate minus erode with a (2r+1)^2 square."""
    if radius <= 0:
        return torch.zeros_like(mask)
    m = mask[:, None].float()
    size = 2 * radius + 1
    dilated = F.max_pool2d(m, size, stride=1, padding=radius) > 0.5
    eroded = -F.max_pool2d(-m, size, stride=1, padding=radius) > 0.5
    return (dilated & ~eroded)[:, 0]


def apply_band(images: torch.Tensor, band: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Set band pixels of (B, H, W, 3) images to the (3,) or (B, 3) background."""
    bg = background.to(images).expand(images.shape[0], 3)[:, None, None, :]
    return torch.where(band[..., None], bg, images)


def image_loss(render: torch.Tensor, target: torch.Tensor, band: torch.Tensor, background: torch.Tensor,
               weights: tuple[float, float, float], lpips=None, blur: str = "conv") -> dict[str, torch.Tensor]:
    """Loss terms of (B, H, W, 3) render and target; `lpips` is a module or None (term left out); `blur`
    picks SSIM's implementation (pig.metrics.ssim.ssim_map).

    Returns {"l1", "ssim", "lpips" (if used), "total"}; "ssim" holds 1 - SSIM.
    """
    w_l1, w_ssim, w_lpips = weights
    x = apply_band(render, band, background).permute(0, 3, 1, 2)
    y = apply_band(target, band, background).permute(0, 3, 1, 2)
    terms = {"l1": (x - y).abs().mean(), "ssim": 1 - ssim(x, y, blur=blur)}
    total = w_l1 * terms["l1"] + w_ssim * terms["ssim"]
    if lpips is not None and w_lpips > 0:
        terms["lpips"] = lpips(x, y).mean()
        total = total + w_lpips * terms["lpips"]
    terms["total"] = total
    return terms
