"""Front-to-back alpha compositing of projected splats in pure PyTorch (the CPU rasterizer).

Flat form of 3DGS compositing (renders Eqs. 8-11): (splat, pixel) pairs sorted by (pixel, depth),
transmittance as a per-pixel exclusive cumulative sum of log(1 - alpha) in float64; closed-form backward.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .projection import ALPHA_THRESHOLD, TRANSMITTANCE_FLOOR, Splats

MAX_ALPHA = 0.999  # gsplat's clamp; keeps log(1 - alpha) finite
DEFAULT_MAX_PAIRS = 2_000_000  # pairs enumerated at once: ~0.2 GB of temporaries


class Spans(NamedTuple):
    """One entry per (splat, pixel row): the pixels of that row where the splat's alpha may reach 1/255.

    Sorted by row of the tall image (all images stacked), splats in depth order within a row.
    """

    splat: Tensor  # (R,) long
    row: Tensor  # (R,) long, row of the tall image
    dy: Tensor  # (R,) splat mean y minus the row's pixel-centre y, as gsplat computes it
    x0: Tensor  # (R,) long, first pixel column
    nx: Tensor  # (R,) long, number of pixels (>= 1)


def composite(
    splats: Splats, num_images: int, width: int, height: int, max_pairs: int = DEFAULT_MAX_PAIRS
) -> tuple[Tensor, Tensor]:
    """Composite splats into `num_images` images -> (features (I,H,W,4) premultiplied, alpha (I,H,W,1)).

    The images are stacked into one tall image of I*H rows and cut into bands of rows holding
    about `max_pairs` pairs, which bounds the temporaries; for the backward pass each band keeps
    about 24 bytes per pair that survives the alpha and transmittance cut-offs.
    """
    geometry = torch.cat([splats.means2d, splats.conics, splats.opacities[:, None]], dim=1)
    with torch.no_grad():
        spans = row_spans(geometry, splats.radii, splats.camera, width, height)
        bands = _bands(spans, num_images * height, max_pairs)
    pieces = []
    for start, stop in bands:
        lo, hi = torch.searchsorted(spans.row, torch.tensor([start, stop], device=spans.row.device)).tolist()
        band = Spans(*(t[lo:hi] for t in spans))
        pieces.append(_BandComposite.apply(geometry, splats.features, *band, start, stop, width))
    out = torch.cat(pieces, dim=0).reshape(num_images, height, width, 5)
    return out[..., :4], out[..., 4:]


def row_spans(geometry: Tensor, radii: Tensor, camera: Tensor, width: int, height: int) -> Spans:
    """Per (splat, row) the pixel columns whose centres may have alpha >= 1/255 (a tight superset).

    On row y the condition sigma(dx) = a dx^2/2 + b dy dx + c dy^2/2 <= log(o * 255) is a quadratic
    in dx = mean_x - pixel_x; its roots bound the span, widened by a margin for float32 rounding.
    """
    g = geometry.detach()
    mx, my, o = g[:, 0], g[:, 1], g[:, 5]
    y0 = torch.ceil(my - radii[:, 1] - 0.5).long().clamp(0, height)
    y1 = torch.floor(my + radii[:, 1] - 0.5).long().clamp(-1, height - 1)
    rows_per_splat = (y1 - y0 + 1).clamp(min=0)
    splat = torch.repeat_interleave(torch.arange(len(g), device=g.device), rows_per_splat)
    first = torch.cumsum(rows_per_splat, 0) - rows_per_splat
    image_row = _take(y0, splat) + torch.arange(len(splat), device=g.device) - _take(first, splat)
    dy = _take(my, splat) - (image_row.to(g.dtype) + 0.5)

    a, b, c = (_take(g[:, k].double(), splat) for k in (2, 3, 4))
    dy64 = dy.double()
    limit = torch.log(_take(o.double(), splat) / ALPHA_THRESHOLD)
    disc = (b * dy64) ** 2 - a * (c * dy64 * dy64 - 2.0 * limit)
    half = torch.sqrt(disc.clamp(min=0.0)) / a
    centre = _take(mx, splat).double() + b * dy64 / a  # pixel x where sigma is smallest on this row
    margin = 0.01 + 1e-4 * half
    x0 = torch.ceil(centre - half - margin - 0.5).clamp(0, width).long()
    x1 = torch.floor(centre + half + margin - 0.5).clamp(-1, width - 1).long()
    keep = ((disc >= 0) & (x1 >= x0)).nonzero(as_tuple=True)[0]
    row = _take(image_row, keep) + _take(camera, _take(splat, keep)) * height
    order = torch.sort(row, stable=True).indices  # splats stay in depth order within a row
    keep = _take(keep, order)
    return Spans(_take(splat, keep), _take(row, order), _take(dy, keep), _take(x0, keep), _take(x1 - x0 + 1, keep))


def _bands(spans: Spans, rows: int, max_pairs: int) -> list[tuple[int, int]]:
    """Consecutive row ranges [start, stop) with about max_pairs pairs each (a row is never split)."""
    per_row = torch.zeros(rows, dtype=torch.long, device=spans.row.device).index_add_(0, spans.row, spans.nx)
    before = torch.cumsum(per_row, 0) - per_row
    band_of_row = (before // max(1, max_pairs)).cpu()
    _, counts = torch.unique_consecutive(band_of_row, return_counts=True)
    stops = torch.cumsum(counts, 0).tolist()
    return list(zip([0] + stops[:-1], stops))


class _BandComposite(torch.autograd.Function):
    """Rows [start, stop) of the tall image -> (rows * W, 5): premultiplied rgb, depth, alpha.

    The backward pass is gsplat's closed form: with w_i = alpha_i T_i and G the output gradient,
    dL/dalpha_i = T_i G.f_i - (sum_{k>i} w_k G.f_k - T_final dL/dA) / (1 - alpha_i).
    """

    @staticmethod
    def forward(ctx, geometry, features, splat, row, dy, x0, nx, start: int, stop: int, width: int):
        npix = (stop - start) * width
        # Pairs come out span by span, rows ascending and splats depth-sorted within a row, so a
        # stable sort by pixel gives (pixel, depth) order, ties by Gaussian index as in gsplat.
        entry = torch.repeat_interleave(torch.arange(len(nx), device=nx.device), nx)
        x = _take(x0 - torch.cumsum(nx, 0) + nx, entry) + torch.arange(len(entry), device=nx.device)
        pix = _take((row - start) * width, entry) + x
        order = torch.sort(pix.int() if npix < 2**31 else pix, stable=True).indices
        entry, pix = _take(entry, order), _take(pix, order)

        _, _, sigma, raw = _pair_terms(geometry, splat, dy, entry, pix, width)
        alpha = raw.clamp_max(MAX_ALPHA)
        # gsplat skips pairs with alpha < 1/255: zero alpha leaves T and the sums unchanged.
        alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_THRESHOLD), alpha, torch.zeros_like(alpha))
        log_one_minus = torch.log1p(-alpha.double())
        log_t = _exclusive_in_runs(log_one_minus, pix)
        # gsplat stops a pixel at the first pair whose next T is <= 1e-4 and skips the rest;
        # log T falls along a run, so the surviving pairs are a prefix of each pixel's run.
        alive = (log_t + log_one_minus > math.log(TRANSMITTANCE_FLOOR)).nonzero(as_tuple=True)[0]
        entry, pix, alpha = _take(entry, alive), _take(pix, alive), _take(alpha, alive)
        log_one_minus, transmittance = _take(log_one_minus, alive), torch.exp(_take(log_t, alive)).to(alpha.dtype)

        sid = _take(splat, entry)
        weights = alpha * transmittance
        out = torch.zeros(5, npix, dtype=features.dtype, device=features.device)
        for k, column in enumerate(features.t().contiguous()):
            out[k].index_add_(0, pix, weights * _take(column, sid))
        final = torch.exp(torch.zeros(npix, dtype=torch.float64, device=pix.device).index_add_(0, pix, log_one_minus))
        out[4] = (1.0 - final).to(out.dtype)
        ctx.save_for_backward(geometry, features, splat, dy, entry, pix, alpha, transmittance, final)
        ctx.width = width
        return out.t()

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):
        geometry, features, splat, dy, entry, pix, alpha, transmittance, final = ctx.saved_tensors
        sid = _take(splat, entry)
        weights = alpha * transmittance
        grad_out = grad_out.t().contiguous()
        g_dot_f = torch.zeros_like(alpha)
        grad_features = torch.zeros_like(features.t())
        for k, column in enumerate(features.t().contiguous()):
            grad_k = _take(grad_out[k], pix)
            g_dot_f += grad_k * _take(column, sid)
            grad_features[k].index_add_(0, sid, weights * grad_k)

        # Light the later pairs of the same pixel send through this one: sum_{k>i} w_k G.f_k.
        behind = _exclusive_suffix_in_runs((weights * g_dot_f).double(), pix)
        through_final = _take(grad_out[4].double() * final, pix)
        grad_alpha = transmittance * g_dot_f + ((through_final - behind) / (1.0 - alpha.double())).to(alpha.dtype)

        g, dx, sigma, raw = _pair_terms(geometry, splat, dy, entry, pix, ctx.width)
        pair_dy = _take(dy, entry)
        # As gsplat: no gradient through the 0.999 clamp, none for skipped pairs (alpha set to 0).
        grad_raw = torch.where((raw <= MAX_ALPHA) & (alpha > 0), grad_alpha, torch.zeros_like(grad_alpha))
        grad_sigma = -raw * grad_raw
        per_pair = [
            grad_sigma * (g[2] * dx + g[3] * pair_dy),
            grad_sigma * (g[3] * dx + g[4] * pair_dy),
            0.5 * grad_sigma * dx * dx,
            grad_sigma * dx * pair_dy,
            0.5 * grad_sigma * pair_dy * pair_dy,
            torch.exp(-sigma) * grad_raw,
        ]
        grad_geometry = torch.zeros_like(geometry.t())
        for k, values in enumerate(per_pair):
            grad_geometry[k].index_add_(0, sid, values)
        return grad_geometry.t(), grad_features.t(), None, None, None, None, None, None, None, None


def _take(values: Tensor, index: Tensor) -> Tensor:
    """values[index] along dim 0 (index_select: several times faster than advanced indexing on CPU)."""
    return values.index_select(0, index)


def _pair_terms(
    geometry: Tensor, splat: Tensor, dy: Tensor, entry: Tensor, pix: Tensor, width: int
) -> tuple[list[Tensor], Tensor, Tensor, Tensor]:
    """Per pair: splat geometry columns, dx = mean_x - pixel centre x, sigma = d^T conic d / 2, o exp(-sigma)."""
    sid = _take(splat, entry)
    g = [_take(column, sid) for column in geometry.t().contiguous()]
    pair_dy = _take(dy, entry)
    dx = g[0] - (pix % width).to(g[0].dtype) - 0.5
    sigma = 0.5 * (g[2] * dx * dx + g[4] * pair_dy * pair_dy) + g[3] * dx * pair_dy
    return g, dx, sigma, g[5] * torch.exp(-sigma)


def _runs(pix: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """For a sorted pixel-id list: each pair's run number, and the first and last index of each run."""
    if len(pix) == 0:
        return pix, pix, pix
    change = (pix[1:] != pix[:-1]).nonzero(as_tuple=True)[0]
    run = torch.zeros_like(pix)
    run[change + 1] = 1
    firsts = torch.cat([change.new_zeros(1), change + 1])
    lasts = torch.cat([change, change.new_full((1,), len(pix) - 1)])
    return torch.cumsum(run, 0), firsts, lasts


def _exclusive_in_runs(values: Tensor, pix: Tensor) -> Tensor:
    """Sum of the earlier values of the same run (float64 values: one global running sum)."""
    run, firsts, _ = _runs(pix)
    exclusive = torch.cumsum(values, 0) - values
    return exclusive - _take(_take(exclusive, firsts), run)


def _exclusive_suffix_in_runs(values: Tensor, pix: Tensor) -> Tensor:
    """Sum of the later values of the same run (float64 values: one global running sum)."""
    run, _, lasts = _runs(pix)
    inclusive = torch.cumsum(values, 0)
    return _take(_take(inclusive, lasts), run) - inclusive
