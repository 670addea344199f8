"""Registry of capture formats: name -> reader that turns a subject's raw data into a `RawCapture`.

`open_capture("thuman4", root)` is how the preprocess stage and the workflow reach every reader; data
preparation, no paper equation.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from pig.data import actorshq, avatarrex, dna, easymocap, thuman4
from pig.data.raw import CaptureError, RawCapture
from pig.data.frame_sources import relative_folder


@dataclass(frozen=True)
class CaptureFormat:
    open: Callable[..., RawCapture]  # (root, **options) -> RawCapture
    # root -> the files the reader needs (workflow inputs); raises CaptureError saying where to put the data.
    required_files: Callable[[Path], list[Path]]
    # True when the reader must be given the SMPL-X model (`body_model=` path), e.g. to add its hands_mean.
    needs_body_model: bool = False
    # Reader options a dataset YAML may set under `reader:` (keyword arguments of `open`), with their types.
    options: dict[str, tuple[type, ...]] = field(default_factory=dict)
    # (root, reader options) -> (camera -> (width, height), frame ids) without reading images (`pig doctor`).
    geometry: Callable[[Path, dict], tuple[dict[str, tuple[int, int]], list[int]]] | None = None


FORMATS: dict[str, CaptureFormat] = {
    "thuman4": CaptureFormat(open=thuman4.Thuman4Capture, required_files=thuman4.required_files),
    "dna": CaptureFormat(open=dna.DnaCapture, required_files=dna.required_files, needs_body_model=True),
    "easymocap": CaptureFormat(open=easymocap.EasyMocapCapture, required_files=easymocap.required_files,
                               needs_body_model=True,
                               options={"masks": (str,), "params": (str,), "person": (int, type(None)),
                                        "flat_hand_mean": (bool,)}, geometry=easymocap.geometry),
    "actorshq": CaptureFormat(open=actorshq.ActorsHQCapture, required_files=actorshq.required_files,
                              options={"scale": (str, type(None))}, geometry=actorshq.geometry),
    "avatarrex": CaptureFormat(open=avatarrex.AvatarReXCapture, required_files=avatarrex.required_files,
                               geometry=avatarrex.geometry),
}


def capture_format(name: str) -> CaptureFormat:
    if name not in FORMATS:
        raise CaptureError(f"unknown capture format {name!r}; known formats: {sorted(FORMATS)}")
    return FORMATS[name]


def reader_options(name: str, options, where: str) -> dict[str, Any]:
    """The dataset YAML's `reader:` options for format `name`, checked against the ones its reader takes;
    CaptureError naming `where` otherwise."""
    if options is None:
        return {}
    accepted = capture_format(name).options
    if not isinstance(options, dict):
        raise CaptureError(f"{where}: `reader` must be a mapping of options, found {options!r}")
    for key, value in options.items():
        if key not in accepted:
            raise CaptureError(f"{where}: `reader` option {key!r} is not one of the {name} reader's "
                               f"({sorted(accepted) or 'it takes none'})")
        if not isinstance(value, accepted[key]) or (isinstance(value, bool) and bool not in accepted[key]):
            names = " or ".join("null" if t is type(None) else t.__name__ for t in accepted[key])
            raise CaptureError(f"{where}: `reader` option {key} must be {names}, found {value!r}")
    return dict(options)


def open_capture(format: str, root: str | Path, **options: Any) -> RawCapture:
    """Open the subject at `root` with the reader registered as `format` (options go to the reader)."""
    return capture_format(format).open(Path(root), **options)


def subject_path(dataset: dict[str, Any], subject: str, where: str) -> str:
    """The folder of `subject` under the dataset's `root`: the subject's name, or the relative path its
    `subject_paths` entry gives (a nested layout such as ActorsHQ's `Actor01/Sequence1`), each component one safe
    name (never absolute, never `..`); CaptureError naming `where`, the dataset YAML, otherwise."""
    paths = dataset.get("subject_paths") or {}
    if not isinstance(paths, dict):
        raise CaptureError(f"{where}: `subject_paths` must map subject names to folders under `root`, found {paths!r}")
    return relative_folder(paths.get(subject, subject), f"`subject_paths.{subject}`", where)
