"""The synthetic capture generator: a skirted, textured stand-in body in motion, rendered in the THuman4 layout.

`capture` builds the scene and writes the capture (generate_capture, build_scene); `config` holds the preset's
`synthetic` section; `motion`, `garment`, `rig`, `texture` and `render` make the body motion, the skirt, the cameras,
the albedo and the images; `workers` runs the rendering in processes that import no torch. The config is imported
here directly and the generator on first use, so that the workflow reads the config without importing torch when it
builds its DAG.
"""
from __future__ import annotations

import importlib

from .config import SyntheticConfig, SyntheticError

__all__ = ["SyntheticConfig", "SyntheticError", "build_scene", "generate_capture"]
_FROM_CAPTURE = {"build_scene", "generate_capture"}


def __getattr__(name: str):
    if name in _FROM_CAPTURE:
        return getattr(importlib.import_module(".capture", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
