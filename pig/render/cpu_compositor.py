"""Front-to-back alpha compositing of projected splats in pure PyTorch (the CPU rasterizer).

Flat form: (splat, pixel) pairs inside each splat's box, sorted by (pixel, depth); transmittance
is an exclusive per-pixel cumulative sum of log(1 - alpha) in float64; 3DGS compositing, Eqs. 8-11.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .projection import ALPHA_THRESHOLD, TRANSMITTANCE_FLOOR, Splats

MAX_ALPHA = 0.999  # gsplat's clamp; keeps log(1 - alpha) finite
DEFAULT_MAX_PAIRS = 2_000_000  # pairs per band; about 0.5 GB of autograd state on the CPU


def composite(
    splats: Splats, num_images: int, width: int, height: int, max_pairs: int = DEFAULT_MAX_PAIRS
) -> tuple[Tensor, Tensor]:
    """Composite splats into `num_images` images -> (features (I,H,W,4) premultiplied, alpha (I,H,W,1)).

    Images are stacked into one tall image of I*H rows, cut into bands of rows holding about
    `max_pairs` pairs each; under autograd each band is checkpointed, so peak memory is one band.
    """
    rows = num_images * height
    params = torch.cat([splats.means2d, splats.conics, splats.opacities[:, None], splats.features], dim=1)
    with torch.no_grad():
        # Pixel index ranges [x0, x1] x [y0, y1] whose centres (+0.5) lie in the box; may be empty.
        x0 = torch.ceil(splats.means2d[:, 0] - splats.radii[:, 0] - 0.5).long().clamp(0, width)
        x1 = torch.floor(splats.means2d[:, 0] + splats.radii[:, 0] - 0.5).long().clamp(-1, width - 1)
        y0 = torch.ceil(splats.means2d[:, 1] - splats.radii[:, 1] - 0.5).long().clamp(0, height)
        y1 = torch.floor(splats.means2d[:, 1] + splats.radii[:, 1] - 0.5).long().clamp(-1, height - 1)
        nx = (x1 - x0 + 1).clamp(min=0)
        first_row = splats.camera * height  # row of the tall image where the splat's image starts
        boxes = torch.stack([x0, nx, y0 + first_row, y1 + first_row, first_row], dim=1)
        bands = _bands(boxes, rows, max_pairs)

    pieces = []
    for start, stop in bands:
        if torch.is_grad_enabled() and params.requires_grad and len(bands) > 1:
            out = checkpoint(_composite_band, params, boxes, start, stop, width, use_reentrant=False)
        else:
            out = _composite_band(params, boxes, start, stop, width)
        pieces.append(out)
    out = torch.cat(pieces, dim=0).reshape(num_images, height, width, 5)
    return out[..., :4], out[..., 4:]


def _bands(boxes: Tensor, rows: int, max_pairs: int) -> list[tuple[int, int]]:
    """Consecutive row ranges [start, stop) with about max_pairs box pairs each (a row is never split)."""
    _, nx, y0, y1, _ = boxes.unbind(1)
    nonempty = (nx > 0) & (y1 >= y0)
    diff = torch.zeros(rows + 1, dtype=torch.long, device=boxes.device)
    diff.index_add_(0, y0[nonempty], nx[nonempty])
    diff.index_add_(0, y1[nonempty] + 1, -nx[nonempty])
    per_row = torch.cumsum(diff[:rows], 0)
    before = torch.cumsum(per_row, 0) - per_row
    band_of_row = (before // max(1, max_pairs)).cpu()
    _, counts = torch.unique_consecutive(band_of_row, return_counts=True)
    stops = torch.cumsum(counts, 0).tolist()
    return list(zip([0] + stops[:-1], stops))


def _composite_band(params: Tensor, boxes: Tensor, start: int, stop: int, width: int) -> Tensor:
    """Rows [start, stop) of the tall image: (rows * W, 5) = premultiplied rgb, depth, alpha."""
    npix = (stop - start) * width
    with torch.no_grad():
        sid, pix = _pairs_in_band(boxes, start, stop, width)
        sigma, alpha = _sigma_alpha(params.detach(), boxes, sid, pix, start, width)
        hit = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
        sid, pix, alpha = sid[hit], pix[hit], alpha[hit]
        # Splats are depth-sorted and pairs come out splat by splat, so a stable sort by pixel
        # gives (pixel, depth) order with ties by Gaussian index, as gsplat's radix sort does.
        order = torch.sort(pix, stable=True).indices
        sid, pix, alpha = sid[order], pix[order], alpha[order]
        first, segment = _segments(pix)
        log_one_minus = torch.log1p(-alpha.double())
        log_t_after = _segment_cumsum_exclusive(log_one_minus, first, segment) + log_one_minus
        # gsplat stops a pixel at the first pair whose next T is <= 1e-4 and skips the rest;
        # log T decreases along a run, so the kept pairs are a prefix of each pixel's run.
        alive = log_t_after > math.log(TRANSMITTANCE_FLOOR)
        sid, pix = sid[alive], pix[alive]
        first, segment = _segments(pix)

    _, alpha = _sigma_alpha(params, boxes, sid, pix, start, width)
    log_one_minus = torch.log1p(-alpha.double())
    transmittance = torch.exp(_segment_cumsum_exclusive(log_one_minus, first, segment)).to(alpha.dtype)
    weights = alpha * transmittance
    out = torch.zeros(npix, 4, dtype=params.dtype, device=params.device)
    out = out.index_add(0, pix, weights[:, None] * params[sid, 6:10])
    log_final = torch.zeros(npix, dtype=torch.float64, device=params.device).index_add(0, pix, log_one_minus)
    return torch.cat([out, (1.0 - torch.exp(log_final)).to(params.dtype)[:, None]], dim=1)


def _pairs_in_band(boxes: Tensor, start: int, stop: int, width: int) -> tuple[Tensor, Tensor]:
    """(splat index, pixel index within the band) for every pixel centre inside a splat's box."""
    x0, nx, y0, y1, _ = boxes.unbind(1)
    y0, y1 = y0.clamp(min=start), y1.clamp(max=stop - 1)
    counts = nx * (y1 - y0 + 1).clamp(min=0)
    touching = (counts > 0).nonzero(as_tuple=True)[0]
    counts = counts[touching]
    sid = torch.repeat_interleave(touching, counts)
    offsets = torch.cumsum(counts, 0) - counts
    local = torch.arange(sid.shape[0], device=boxes.device) - torch.repeat_interleave(offsets, counts)
    width_of = nx[sid]
    x = x0[sid] + local % width_of
    y = y0[sid] - start + local // width_of
    return sid, y * width + x


def _sigma_alpha(
    params: Tensor, boxes: Tensor, sid: Tensor, pix: Tensor, start: int, width: int
) -> tuple[Tensor, Tensor]:
    """gsplat's Mahalanobis half-distance sigma and alpha = min(0.999, o exp(-sigma)) at pixel centres."""
    p = params[sid, :6]
    # Pixel row within the splat's own image, in integers, so float precision never depends on
    # the row's position in the tall image.
    row = torch.div(pix, width, rounding_mode="floor") + (start - boxes[sid, 4])
    dx = p[:, 0] - (pix % width).to(p.dtype) - 0.5
    dy = p[:, 1] - row.to(p.dtype) - 0.5
    sigma = 0.5 * (p[:, 2] * dx * dx + p[:, 4] * dy * dy) + p[:, 3] * dx * dy
    return sigma, torch.clamp_max(p[:, 5] * torch.exp(-sigma), MAX_ALPHA)


def _segments(pix: Tensor) -> tuple[Tensor, Tensor]:
    """Index of the first pair of each pixel's run, and each pair's run number."""
    starts = torch.ones_like(pix, dtype=torch.bool)
    starts[1:] = pix[1:] != pix[:-1]
    return starts.nonzero(as_tuple=True)[0], torch.cumsum(starts, 0) - 1


def _segment_cumsum_exclusive(values: Tensor, first: Tensor, segment: Tensor) -> Tensor:
    """Exclusive cumulative sum restarting at each run (values in float64: one global sum)."""
    exclusive = torch.cumsum(values, 0) - values
    return exclusive - exclusive[first][segment]
