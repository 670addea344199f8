"""train_log.png: a fit's loss terms and held-out PSNR against training time, drawn from train_log.csv's rows.

Left, the loss (Eq. 15) and its unweighted terms, as means over at most `BINS` equal runs of logged rows (a
CPU fit logs every iteration: thousands of noisy points); right, the probes' PSNR (pig.avatar.probe) as a line
and the full held-out evaluations as their own markers. Both against train_s, the fit's wall time with the
held-out evaluations left out (the x axis of the tables' error-against-time plot).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pig._io import write_figure

BINS = 200
TERMS = {"loss": "Eq. 15 total", "l1": "L1", "ssim": "1 - SSIM", "lpips": "LPIPS"}
PSNRS = {"probe_psnr": ("probe: mask boxes of a few novel views", "-", "o"),
         "heldout_psnr": ("full held-out evaluation: whole novel-view frames", "none", "s"),
         "heldout_psnr_iterate": ("full, the iterate's own weights (weight average on)", "none", "x")}


def _series(rows: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(time, value) of the rows that have `key`; time is train_s, or wall_s in rows logged before train_s."""
    picked = [r for r in rows if r.get(key, "") not in ("", None)]
    time = [r.get("train_s", "") if r.get("train_s", "") != "" else r["wall_s"] for r in picked]
    return np.asarray(time, dtype=float), np.asarray([r[key] for r in picked], dtype=float)


def binned(x: np.ndarray, y: np.ndarray, bins: int = BINS) -> tuple[np.ndarray, np.ndarray]:
    """Means of x and y over `bins` consecutive runs of points of near-equal length (all points where fewer)."""
    if len(x) <= bins:
        return x, y
    runs = np.array_split(np.arange(len(x)), bins)
    return np.array([x[r].mean() for r in runs]), np.array([y[r].mean() for r in runs])


def plot_train_log(path: Path, rows: list[dict], title: str = "") -> None:
    """Draw `rows` (train_log.csv's, "" where a value is absent) to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_loss, ax_psnr) = plt.subplots(1, 2, figsize=(11, 4.2), dpi=100)
    for key, label in TERMS.items():
        x, y = _series(rows, key)
        if len(x) and (y > 0).any():
            bx, by = binned(x, y)
            ax_loss.plot(bx, by, lw=1, label=label)
    ax_loss.set_yscale("log")
    ax_loss.set_ylabel(f"training loss (unitless), binned into <= {BINS} means")
    for key, (label, line, marker) in PSNRS.items():
        x, y = _series(rows, key)
        if len(x):
            ax_psnr.plot(x, y, linestyle=line, marker=marker, markersize=4, label=f"{label} ({len(x)})")
    ax_psnr.set_ylabel("held-out novel-view PSNR [dB], finest LOD")
    for ax in (ax_loss, ax_psnr):
        ax.set_xlabel("training wall time, held-out evaluations left out [s]")
        ax.grid(alpha=0.3)
        if ax.get_lines():
            ax.legend(fontsize=8, loc="upper right" if ax is ax_loss else "lower right")  # "best" searches: slow
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.12, top=0.9, wspace=0.22)  # fixed: tight_layout doubles a draw
    write_figure(path, fig)
