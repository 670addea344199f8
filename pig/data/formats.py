"""Registry of capture formats: name -> reader that turns a subject's raw data into a `RawCapture`.

`open_capture("thuman4", root)` is how the preprocess stage and the workflow reach every reader; data
preparation, no paper equation.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pig.data import dna, thuman4
from pig.data.raw import CaptureError, RawCapture


@dataclass(frozen=True)
class CaptureFormat:
    open: Callable[..., RawCapture]  # (root, **options) -> RawCapture
    # root -> the files the reader needs (workflow inputs); raises CaptureError saying where to put the data.
    required_files: Callable[[Path], list[Path]]
    # True when the reader must be given the SMPL-X model (`body_model=` path), e.g. to add its hands_mean.
    needs_body_model: bool = False


FORMATS: dict[str, CaptureFormat] = {
    "thuman4": CaptureFormat(open=thuman4.Thuman4Capture, required_files=thuman4.required_files),
    "dna": CaptureFormat(open=dna.DnaCapture, required_files=dna.required_files, needs_body_model=True),
}


def capture_format(name: str) -> CaptureFormat:
    if name not in FORMATS:
        raise CaptureError(f"unknown capture format {name!r}; known formats: {sorted(FORMATS)}")
    return FORMATS[name]


def open_capture(format: str, root: str | Path, **options: Any) -> RawCapture:
    """Open the subject at `root` with the reader registered as `format` (options go to the reader)."""
    return capture_format(format).open(Path(root), **options)
