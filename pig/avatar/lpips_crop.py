"""The square crop of the silhouette's box that Eq. 15's LPIPS term sees in the `mmlphuman` form (Section 3.5).

MMLPHuman (train.py and utils/image_utils.py `crop_image`, github.com/1231234zhan/mmlphuman at 56e3db4) scores
LPIPS on one fixed-size square per view: the box of the ground-truth mask, padded with the background to a square
on its shorter side (content centred), then resized bilinearly to `size` x `size`, or, once random patches are on
and the square is larger than `size`, a random `size` window of it at full resolution. `crop_views` does this for a
batch with fixed-shape operations (no host synchronisation, one output shape), so that the loss stays compilable;
`crop_views_sliced` follows MMLPHuman's steps literally, one view at a time, reading each box back to the host.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["mask_boxes", "crop_views", "crop_view_sets", "crop_views_sliced"]


def mask_boxes(masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, H, W) bool masks -> (top, left, rows, cols), each (B,) int64: the crop's box as MMLPHuman takes it.

    Rows run from the first masked row to the last one, the last one left out (MMLPHuman slices `[min:max]` with
    the inclusive maximum), so `rows` is last - first; columns alike. An empty mask gives a box of 0 x 0.
    """
    height, width = masks.shape[1:]

    def extent(present: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
        index = torch.arange(size, device=masks.device)
        first = torch.where(present, index, size).amin(1)
        last = torch.where(present, index, -1).amax(1)
        return torch.where(last >= 0, first, 0), (last - first).clamp(min=0)

    top, rows = extent(masks.any(2), height)
    left, cols = extent(masks.any(1), width)
    return top, left, rows, cols


def _canvas_coordinates(side: torch.Tensor, size: int, offsets: torch.Tensor | None) -> torch.Tensor:
    """(B, size) positions on the square canvas of side `side` (B,) that output pixels sample: a bilinear resize
    (PyTorch's half-pixel centres, edges clamped), or, where `offsets` (B,) uniforms in [0, 1) are given and the
    canvas is larger than `size`, a window at a random whole-pixel offset."""
    # float64: a pixel position of a 1330-pixel frame keeps ~1e-13 of a pixel (float32: ~1e-4).
    i = torch.arange(size, device=side.device, dtype=torch.float64)
    scale = side.double()[:, None] / size
    resized = ((i + 0.5) * scale - 0.5).clamp(min=0).minimum(side.double()[:, None] - 1)
    if offsets is None:
        return resized
    start = torch.floor(offsets * (side - size + 1).clamp(min=1)).clamp(max=(side - size).clamp(min=0))
    return torch.where((side > size)[:, None], start[:, None] + i, resized)


def crop_views(images: torch.Tensor, masks: torch.Tensor, background: torch.Tensor, size: int,
               offsets: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """MMLPHuman's crop of (B, 3, H, W) images by their (B, H, W) masks -> ((B, 3, size, size) crops, (B,) bool).

    `background` (3,) or (B, 3) fills the square around the box. `offsets` (B, 2) uniforms in [0, 1) (rows,
    columns) turn on the random windows; None resizes every square. The bool is False for a view whose box is empty
    (an empty or one-pixel mask), where MMLPHuman's crop fails: its crop is background and should not be scored.
    Differentiable with respect to `images`.
    """
    (crops,), valid = crop_view_sets([images], masks, background, size, offsets)
    return crops, valid


def crop_view_sets(image_sets: list[torch.Tensor], masks: torch.Tensor, background: torch.Tensor, size: int,
                   offsets: torch.Tensor | None = None) -> tuple[list[torch.Tensor], torch.Tensor]:
    """`crop_views` of each (B, 3, H, W) batch of `image_sets` (renders and their targets, of one dtype) by the same
    masks and windows: the boxes, canvas positions and bilinear taps computed once for all, each crop the same as
    `crop_views` of it alone."""
    batch, _, height, width = image_sets[0].shape
    top, left, rows, cols = mask_boxes(masks)
    side = torch.maximum(rows, cols)
    # The canvas holds the box's pixels, centred on the shorter side, and the background elsewhere: sampling the image
    # with every pixel outside the box set to the background, and the background beyond the image, is sampling it.
    r = torch.arange(height, device=masks.device)[None, :, None]
    c = torch.arange(width, device=masks.device)[None, None, :]
    inside = ((r >= top[:, None, None]) & (r < (top + rows)[:, None, None]) & (c >= left[:, None, None])
              & (c < (left + cols)[:, None, None]))
    v = _canvas_coordinates(side, size, None if offsets is None else offsets[:, 0])
    u = _canvas_coordinates(side, size, None if offsets is None else offsets[:, 1])
    v = v - torch.div(side - rows, 2, rounding_mode="floor")[:, None] + top[:, None]
    u = u - torch.div(side - cols, 2, rounding_mode="floor")[:, None] + left[:, None]
    taps = _bilinear_taps(v, u, height, width, image_sets[0].dtype)
    crops = []
    for images in image_sets:
        bg = background.to(images).expand(batch, 3)[:, :, None, None]
        shifted = torch.where(inside[:, None], images - bg, 0)
        crops.append(_bilinear(shifted, taps) + bg)
    return crops, side > 0


def _bilinear_taps(v: torch.Tensor, u: torch.Tensor, height: int, width: int, dtype: torch.dtype
                   ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The four taps of a bilinear sampling of (H, W) images at rows `v` x columns `u` (B, S) float64: per tap the
    flat pixel index (B, S S) and its weight (B, 1, S, S) in `dtype`, 0 outside the image. Weights from float64
    positions, not grid_sample, whose float32 normalised coordinates miss whole pixels by ~1e-4 at 1330 pixels: a
    window at whole-pixel offsets is then an exact copy."""
    v0, u0 = v.floor(), u.floor()
    fv, fu = (v - v0).to(dtype), (u - u0).to(dtype)
    taps = []
    for dv, wv in ((0, 1 - fv), (1, fv)):
        rows = v0.long() + dv
        wv = wv * ((rows >= 0) & (rows < height))
        for du, wu in ((0, 1 - fu), (1, fu)):
            cols = u0.long() + du
            wu = wu * ((cols >= 0) & (cols < width))
            index = rows.clamp(0, height - 1)[:, :, None] * width + cols.clamp(0, width - 1)[:, None, :]
            taps.append((index.flatten(1), (wv[:, :, None] * wu[:, None, :])[:, None]))
    return taps


def _bilinear(image: torch.Tensor, taps: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """(B, C, H, W) sampled at the bilinear `taps` of `_bilinear_taps` -> (B, C, S, S)."""
    batch, channels = image.shape[:2]
    size = taps[0][1].shape[-1]
    flat = image.flatten(2)
    out = torch.zeros(batch, channels, size, size, dtype=image.dtype, device=image.device)
    for index, weight in taps:
        values = flat.gather(2, index[:, None].expand(batch, channels, -1)).view(out.shape)
        out = out + values * weight
    return out


def crop_views_sliced(images: torch.Tensor, masks: torch.Tensor, background: torch.Tensor, size: int,
                      offsets: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """`crop_views` as MMLPHuman computes it, a view at a time: the box read back to the host, a canvas of its size,
    F.interpolate or a slice. The same result, with a host synchronisation and shapes that change with every view."""
    crops, valid = [], []
    bg = background.to(images).expand(images.shape[0], 3)
    top, left, rows, cols = (t.tolist() for t in mask_boxes(masks))
    for k, image in enumerate(images):
        side = max(rows[k], cols[k])
        valid.append(side > 0)
        if side == 0:
            crops.append(bg[k][:, None, None].expand(3, size, size))
            continue
        canvas = bg[k][:, None, None].expand(3, side, side).clone()
        v0, u0 = (side - rows[k]) // 2, (side - cols[k]) // 2
        canvas[:, v0:v0 + rows[k], u0:u0 + cols[k]] = image[:, top[k]:top[k] + rows[k], left[k]:left[k] + cols[k]]
        if offsets is not None and side > size:
            dv, du = (min(int(o * (side - size + 1)), side - size) for o in offsets[k].tolist())
            crops.append(canvas[:, dv:dv + size, du:du + size])
        else:
            crops.append(F.interpolate(canvas[None], size=(size, size), mode="bilinear")[0])
    return torch.stack(crops), torch.tensor(valid, device=images.device)
