"""Peak signal-to-noise ratio per image: 10 log10(R^2 / MSE) over all pixels and channels.

The standard image-fidelity metric of the paper's evaluation (Section 4.2, Tables 1-3).
"""
from __future__ import annotations

import torch


def psnr(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, reduction: str = "none") -> torch.Tensor:
    """PSNR in dB of images (B, C, H, W); `reduction` "none" -> (B,), "mean" -> scalar.

    Identical images give +inf, as the closed form does.
    """
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"psnr expects two (B, C, H, W) tensors of one shape, found {tuple(x.shape)} and {tuple(y.shape)}")
    mse = (x - y).pow(2).flatten(1).mean(1)
    values = 10 * torch.log10(data_range**2 / mse)
    if reduction == "none":
        return values
    if reduction == "mean":
        return values.mean()
    raise ValueError(f"psnr: reduction must be 'none' or 'mean', found {reduction!r}")
