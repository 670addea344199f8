"""Probes: a cheap held-out PSNR, evaluated often during a fit for its error-against-time curve.

The full held-out evaluation (pig.avatar.training.HeldOut) renders whole frames of every novel-view camera on a few
frames; on two CPU cores it costs as much as ~15 iterations, so the default run could afford it 3 times. A probe is a
fixed small subset of it: a few novel-view (frame, camera) pairs, each rendered only over the box of its mask and
at 1/`scale` the resolution (the camera's intrinsics scaled, so each rendered pixel covers `scale` x `scale` of the
view's), against the masked truth averaged over those blocks. Its PSNR is of the box, not of the frame: the empty
background that raises a full-frame PSNR is mostly left out, so a probe reads lower than the full evaluation, and
the two are logged in columns of their own (train_log.csv's probe_psnr and heldout_psnr).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from pig.avatar.batches import ViewSource
from pig.metrics.psnr import psnr
from pig.render.api import RasterizerConfig, render_gaussians


def probe_pairs(frames: list[int], cameras: list[str], has, count: int) -> list[tuple[int, str]]:
    """The first `count` (frame, camera) pairs with a view (`has(camera, frame)`), frames from the middle one on
    (then wrapping round to the first), each frame's cameras in split order: a posed frame rather than the
    capture's first, and as few frames as the count allows (each costs one pass of the avatar's decoders)."""
    middle = len(frames) // 2
    ordered = frames[middle:] + frames[:middle]
    return [(f, c) for f in ordered for c in cameras if has(c, f)][:count]


def mask_box(mask: np.ndarray, scale: int) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) of a (H, W) mask's True pixels, widened outwards to multiples of `scale` and cut to the
    largest multiple inside the frame; None where no whole `scale` block remains (an empty mask)."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not rows.size:
        return None
    height, width = mask.shape
    y0, x0 = rows[0] // scale * scale, cols[0] // scale * scale
    y1 = min(-(-(rows[-1] + 1) // scale) * scale, height // scale * scale)
    x1 = min(-(-(cols[-1] + 1) // scale) * scale, width // scale * scale)
    if y1 <= y0 or x1 <= x0:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def box_intrinsics(K: torch.Tensor, box: tuple[int, int, int, int], scale: int) -> torch.Tensor:
    """Intrinsics (3, 3) of the pixels of `box` at 1/`scale` resolution: pixel i of the original spans [i, i+1), so
    pixel coordinates divide by `scale`, then shift by the box's corner."""
    x0, y0, _, _ = box
    out = K.clone()
    out[:2] /= scale
    out[0, 2] -= x0 / scale
    out[1, 2] -= y0 / scale
    return out


class Probe:
    """PSNR at the finest LOD over the mask boxes of `count` held-out views (`probe_pairs` of the novel-view split
    on the fitted frames), at 1/`scale` resolution, black background, masked truth. The views are read once, when
    made; each evaluation is one decoder pass per frame and one small render per view."""

    def __init__(self, capture, model, source: ViewSource, count: int, scale: int):
        split = capture.split["novel_view"]
        frames = [f for f in split["frames"] if f in model.frame_ids]
        # (timestep, camera, viewmat (1, 4, 4), K (1, 3, 3), width, height, truth (1, 3, height, width))
        self.scale, self.views = scale, []
        for frame, camera in probe_pairs(frames, list(split["cameras"]), capture.has, count):
            step = model.timestep_of_frame(frame)
            [[view]] = source.views(source.stage([(step, [camera])]))
            box = mask_box(view.masks[0].cpu().numpy(), scale)
            if box is None:
                continue
            x0, y0, x1, y1 = box
            truth = (view.images[0] * view.masks[0, ..., None])[y0:y1, x0:x1]
            h, w = (y1 - y0) // scale, (x1 - x0) // scale
            truth = truth.reshape(h, scale, w, scale, 3).mean((1, 3)).permute(2, 0, 1)[None]
            self.views.append((step, camera, view.viewmats, box_intrinsics(view.Ks[0], box, scale)[None], w, h, truth))
        self.pairs = [(model.frame_ids[v[0]], v[1]) for v in self.views]  # (frame, camera) evaluated

    @torch.no_grad()
    def psnr(self, model, raster: RasterizerConfig) -> float:
        """Mean over the views of their PSNR in dB; NaN without views."""
        if not self.views:
            return math.nan
        values, gaussians = [], {}
        black = torch.zeros(3, device=self.views[0][-1].device)
        for step, _, viewmat, K, width, height, truth in self.views:
            if step not in gaussians:
                gaussians[step] = model(torch.tensor([step]), model.num_levels - 1)
            g = gaussians[step]
            out = render_gaussians(g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0], viewmat, K, width,
                                   height, black, backend=raster.backend, max_pairs=raster.max_pairs)
            values += psnr(out.color.clamp(0, 1).permute(0, 3, 1, 2), truth).tolist()
        return float(np.mean(values))
