"""OpenEXR read/write of float32 per-pixel channels (render alpha and expected depth), written atomically.

Storage only; uses the `OpenEXR` 3.x API (`OpenEXR.File`), ZIP-compressed scanlines, full float precision. A
file's declared data window is bounded before its pixels are read.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

from pig._io import atomic_path
from pig.data.images import MAX_PIXELS
from pig.inputs import require_regular_file


def write_exr(path: str | Path, channels: dict[str, np.ndarray]) -> None:
    """Write named (H, W) channels as 32-bit float to `path` via a temporary file and a rename."""
    path = Path(path)
    if not channels:
        raise ValueError(f"{path}: no channels to write")
    shapes = {name: np.shape(values) for name, values in channels.items()}
    if len(set(shapes.values())) != 1 or len(next(iter(shapes.values()))) != 2:
        raise ValueError(f"{path}: expected 2-D (H, W) channels of one shape, found {shapes}")
    data = {name: np.ascontiguousarray(values, dtype=np.float32) for name, values in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, data) as handle:
        handle.write(str(tmp))


def read_exr(path: str | Path, max_pixels: int = MAX_PIXELS) -> dict[str, np.ndarray]:
    """All channels of an EXR file as (H, W) float32 arrays keyed by channel name; ValueError naming the file if its
    header declares more than `max_pixels` pixels (checked before the pixels are read)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: EXR file not found")
    require_regular_file(path, ValueError, "an OpenEXR file")
    try:
        with OpenEXR.File(str(path), header_only=True) as handle:
            low, high = handle.header()["dataWindow"]
        width, height = (int(v) + 1 for v in np.asarray(high, np.int64) - np.asarray(low, np.int64))
        if width * height > max_pixels or width < 1 or height < 1:
            raise ValueError(f"{path}: the EXR header declares a {width}x{height} (WxH) data window, not 1 to "
                             f"{max_pixels:,} pixels; not read")
        with OpenEXR.File(str(path), separate_channels=True) as handle:
            channels = handle.channels()
            return {name: np.asarray(channel.pixels, dtype=np.float32) for name, channel in channels.items()}
    except RuntimeError as err:
        raise ValueError(f"{path}: not a readable OpenEXR file ({err})") from None
