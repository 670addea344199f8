"""Differentiable structural similarity (SSIM) with an 11-tap Gaussian window, sigma 1.5.

Used by the loss (Eq. 15) and the evaluation; equals scikit-image's `structural_similarity(
gaussian_weights=True, sigma=1.5, use_sample_covariance=False)` (which averages the SSIM map
after cropping the 5-pixel border the window reaches past), computed here with valid convolutions.
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F

SIGMA = 1.5
RADIUS = 5  # scikit-image / scipy: int(truncate * sigma + 0.5) with truncate = 3.5
K1, K2 = 0.01, 0.03


def gaussian_window(dtype: torch.dtype, device: torch.device | str | None = None) -> torch.Tensor:
    """Normalised 1-D Gaussian taps (11,), as scipy.ndimage.gaussian_filter1d builds them. Computed on `device`: made
    on the host, their copy to a GPU was a blocking copy in every loss evaluation (a host synchronisation). A compiled
    loss takes one made before compilation (ssim_map's `window`)."""
    offsets = torch.arange(-RADIUS, RADIUS + 1, dtype=torch.float64, device=device)
    taps = torch.exp(-0.5 * (offsets / SIGMA) ** 2)
    return (taps / taps.sum()).to(dtype=dtype, device=device)


def _blur_valid(images: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (B, C, H, W) keeping only pixels whose window lies inside."""
    channels = images.shape[1]
    size = taps.numel()
    rows = taps.view(1, 1, size, 1).expand(channels, 1, size, 1)
    cols = taps.view(1, 1, 1, size).expand(channels, 1, 1, size)
    return F.conv2d(F.conv2d(images, rows, groups=channels), cols, groups=channels)


def _blur_shifted(images: torch.Tensor, taps: torch.Tensor | Sequence[float]) -> torch.Tensor:
    """`_blur_valid` as weighted sums of shifted slices: slow eagerly, but torch.compile fuses each pass into one
    memory-bound kernel (3.3 against 11.9 ms for the grouped convolutions, SSIM of 4 x 1330 x 1150 forward and
    backward on an H100; benchmarks/NOTES.md, "Fit")."""
    size = len(taps)
    height, width = images.shape[-2:]
    rows = sum(taps[i] * images[..., i:height - size + 1 + i, :] for i in range(size))
    return sum(taps[i] * rows[..., i:width - size + 1 + i] for i in range(size))


BLURS = {"conv": _blur_valid, "shift": _blur_shifted}


def ssim_map(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, blur: str = "conv",
             window: torch.Tensor | None = None) -> torch.Tensor:
    """Per-pixel SSIM (B, C, H-10, W-10) of images (B, C, H, W), on the interior; `blur` "conv" (grouped
    convolutions) or "shift" (shifted sums, for torch.compile) computes the same Gaussian window.

    `window`: gaussian_window on x's device, made here when None. Under torch.compile pass one made before: made
    inside the graph it cost 17 GiB and 6 ms a step, and as Python constants inductor recomputes three of the row
    pass's taps in each of the column pass's (44 loads an output against 22, 5 ms; benchmarks/NOTES.md, "SSIM's
    window as a tensor made once")."""
    if blur not in BLURS:
        raise ValueError(f"ssim: blur must be one of {sorted(BLURS)}, found {blur!r}")
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"ssim expects two (B, C, H, W) tensors of one shape, found {tuple(x.shape)} and {tuple(y.shape)}")
    if min(x.shape[-2:]) < 2 * RADIUS + 1:
        raise ValueError(f"ssim needs images of at least {2 * RADIUS + 1} x {2 * RADIUS + 1} pixels, found {tuple(x.shape[-2:])}")
    # Contiguous NCHW: a permuted (B, H, W, C) image (the loss passes those) sends the grouped
    # convolutions to cuDNN's NHWC engine with layout transforms, measured ~5 ms per call at 4 x 1330 x 1150
    # on an H200 (benchmarks/NOTES.md, "Fit stage on the GPU: where the time goes").
    x, y = x.contiguous(), y.contiguous()
    if window is None:
        window = gaussian_window(x.dtype, x.device)
    elif window.shape != (2 * RADIUS + 1,) or window.device != x.device:
        raise ValueError(f"ssim: window must be gaussian_window's ({2 * RADIUS + 1},) taps on {x.device}, found "
                         f"{tuple(window.shape)} on {window.device}")
    window = window.to(x.dtype)  # the grouped convolutions take one dtype
    # One batched filter pass over the five moments instead of five passes.
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    mu_x, mu_y, xx, yy, xy = BLURS[blur](stacked, window).chunk(5, dim=1)
    var_x = xx - mu_x * mu_x
    var_y = yy - mu_y * mu_y
    cov = xy - mu_x * mu_y
    c1 = (K1 * data_range) ** 2
    c2 = (K2 * data_range) ** 2
    numerator = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    denominator = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    return numerator / denominator


def ssim(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, reduction: str = "mean", blur: str = "conv",
         window: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM of images (B, C, H, W): "mean" -> scalar over the batch, "none" -> (B,); `blur` and `window` as in
    ssim_map."""
    per_image = ssim_map(x, y, data_range, blur, window).flatten(1).mean(1)
    if reduction == "none":
        return per_image
    if reduction == "mean":
        return per_image.mean()
    raise ValueError(f"ssim: reduction must be 'none' or 'mean', found {reduction!r}")
