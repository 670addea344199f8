"""Ground truth, render and error of a few held-out views side by side: the picture of a split in the workflow's report.

Rows: the ground truth as evaluated (masked to black), the render at the finest level of detail, and the
per-pixel error |render - truth| averaged over RGB on a fixed colour scale; columns: views spread evenly over the
split. No paper equation: it shows what the evaluate stage scores.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ERROR_SCALE = 0.25  # mean absolute RGB error drawn at full colour; fixed, so that montages compare
PANEL_INCHES = 2.0


@dataclass
class MontageView:
    camera: str
    frame: int
    truth: np.ndarray  # (H, W, 3) float32 in [0, 1], masked to black
    render: np.ndarray  # (H, W, 3) float32 in [0, 1]
    error: np.ndarray  # (H, W) mean absolute RGB error


def finest_level(split_dir: Path) -> tuple[int, int]:
    """(finest LOD index, number of LODs) rendered under renders/{split}/ (folders lod0, lod1, ...)."""
    levels = sorted(int(m.group(1)) for p in split_dir.glob("lod*") if (m := re.fullmatch(r"lod(\d+)", p.name)))
    if not levels:
        raise FileNotFoundError(f"{split_dir}: no lod*/ folders; expected the render stage's output for one split")
    return levels[-1], len(levels)


def spread(items: list, count: int) -> list:
    """`count` items evenly spaced from first to last (all of them when there are fewer)."""
    if count < 1:
        raise ValueError(f"expected at least one view for the montage, asked for {count}")
    if len(items) <= count:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def error_map(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(H, W) mean over RGB of |render - truth|."""
    return np.abs(render.astype(np.float32) - truth.astype(np.float32)).mean(axis=-1)


def montage_views(capture, split_dir: Path, split: str, count: int = 4) -> list[MontageView]:
    """Ground truth, finest-LOD render and error of `count` views of `split` in the loaded `capture`."""
    from pig.data.render_store import RenderReader

    level, _ = finest_level(split_dir)
    reader = RenderReader(split_dir / f"lod{level}")
    views = capture.views(split)
    if not views:
        raise FileNotFoundError(f"{capture.root}: split {split!r} has no view with an image and a mask")
    chosen = []
    for camera, frame in spread(views, count):
        truth = capture.image(camera, frame) * capture.mask(camera, frame)[..., None]
        render = reader.image(camera, frame)
        if render.shape != truth.shape:
            raise ValueError(f"{reader.source(camera, frame)}: render is "
                             f"{render.shape[1]}x{render.shape[0]} (WxH), the capture's image "
                             f"{truth.shape[1]}x{truth.shape[0]}")
        chosen.append(MontageView(camera, frame, truth, render, error_map(render, truth)))
    return chosen


def montage_figure(views: list[MontageView], title: str):
    """A matplotlib figure: ground truth, render and error rows, one column per view, an error colour bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    height, width = views[0].truth.shape[:2]
    panel = (PANEL_INCHES, PANEL_INCHES * height / width)
    figure, axes = plt.subplots(3, len(views), squeeze=False, figsize=(panel[0] * len(views) + 1.0, panel[1] * 3 + 0.8),
                                layout="constrained")
    for column, view in enumerate(views):
        axes[0, column].imshow(view.truth)
        axes[1, column].imshow(view.render)
        shown = axes[2, column].imshow(view.error, cmap="inferno", vmin=0.0, vmax=ERROR_SCALE)
        axes[0, column].set_title(f"{view.camera}, frame {view.frame}", fontsize=9)
        for axis in axes[:, column]:
            axis.set_xticks([])
            axis.set_yticks([])
    for axis, label in zip(axes[:, 0], ("ground truth", "render", "|error|")):
        axis.set_ylabel(label)
    figure.colorbar(shown, ax=axes[2, :].tolist(), shrink=0.9, label="mean |RGB error|")
    figure.suptitle(title, fontsize=10)
    return figure


def split_montage(capture_dir: Path, split_dir: Path, split: str, count: int = 4):
    """The montage figure of a rendered split (renders/{split}/) against the preprocessed capture's ground truth."""
    from pig.data.capture import Capture

    level, levels = finest_level(Path(split_dir))
    capture = Capture.load(capture_dir, cache_mb=0)
    views = montage_views(capture, Path(split_dir), split, count)
    return montage_figure(views, f"{split}: lod{level}, the finest of {levels} rendered; {len(views)} of "
                                 f"{len(capture.views(split))} views")
