"""Atomic file writing for the stages and benchmarks: write a temporary name, then rename.

A killed stage never leaves a half-written PNG, CSV, JSON or plot under its final name.
"""
from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np


def _temporary(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A hidden temporary sibling of `path` to write to; renamed onto `path` when the block succeeds, removed
    when it raises. For writers that take a file name (torch.save, cv2.imwrite, OpenEXR, h5py)."""
    path = Path(path)
    tmp = _temporary(path)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | Path, data: Any) -> None:
    write_text(path, json.dumps(data, indent=2, allow_nan=True) + "\n")


def write_png(path: str | Path, image: np.ndarray) -> None:
    """(H, W, 3) RGB float in [0, 1] or uint8 -> 8-bit PNG."""
    path = Path(path)
    if image.dtype != np.uint8:
        image = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    tmp = _temporary(path)
    try:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(image[..., ::-1])):
            raise OSError(f"{path}: OpenCV could not write the PNG")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_figure(path: str | Path, figure, dpi: float | None = None) -> None:
    """Save a matplotlib figure (format from the suffix) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    tmp = _temporary(path)
    try:
        figure.savefig(tmp, dpi=dpi)
        os.replace(tmp, path)
    finally:
        plt.close(figure)
        tmp.unlink(missing_ok=True)


def read_png(path: str | Path) -> np.ndarray:
    """8-bit RGB PNG -> (H, W, 3) float32 in [0, 1]."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(f"{path}: missing or not a readable image (expected an RGB PNG written by the render stage)")
    return image[..., ::-1].astype(np.float32) / 255
