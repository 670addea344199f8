"""Which preprocessed capture an artifact belongs to: its fingerprint (`Capture.fingerprint`) and folder.

An avatar's checkpoint stores the fingerprint of the capture it was fitted on, and a renders folder records the
capture it was rendered for (RECORD); `require_same_capture` refuses to pair either with another capture, naming
both. The folder is a label for messages only: a capture moved elsewhere keeps its fingerprint.
"""
from __future__ import annotations

import json
from pathlib import Path

from pig.data.raw import CaptureError

RECORD = "capture.json"  # in a renders folder: {"capture": folder, "fingerprint": {part: sha256}}


class CaptureMismatch(CaptureError):
    """An artifact made from one capture is paired with another."""


def capture_record(capture) -> dict:
    """The record of a loaded `Capture`: {"capture": its folder, "fingerprint": its parts' SHA-256}."""
    return {"capture": str(Path(capture.root).resolve()), "fingerprint": capture.fingerprint()}


def read_capture_record(folder: Path, made_by: str) -> dict:
    """The RECORD of `folder` (written by the `made_by` stage); CaptureError naming the file if absent or malformed."""
    path = Path(folder) / RECORD
    rerun = f"rerun the {made_by} stage, which records the capture it worked on"
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: missing, so nothing says which capture {folder} belongs to; {rerun}") from None
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise CaptureError(f"{path}: not valid JSON ({err}); {rerun}") from None
    fingerprint = record.get("fingerprint") if isinstance(record, dict) else None
    if not isinstance(fingerprint, dict) or not isinstance(record.get("capture"), str):
        raise CaptureError(f"{path}: expected {{\"capture\": folder, \"fingerprint\": {{part: hash}}}}; {rerun}")
    return record


def require_same_capture(artifact: Path, made_from: dict, made_from_name: str | None, capture) -> None:
    """CaptureMismatch naming `artifact`, the capture it was made from (`made_from_name`, or unrecorded) and the
    loaded `capture`, unless `made_from` (a fingerprint) is the fingerprint of `capture`."""
    current = capture.fingerprint()
    parts = sorted(key for key in made_from.keys() | current.keys() if made_from.get(key) != current.get(key))
    if parts:
        source = made_from_name or "a capture whose folder it does not record"
        raise CaptureMismatch(
            f"{artifact}: made from another capture ({source}) than {Path(capture.root)}: their {', '.join(parts)} "
            "differ; use the capture it was made from, or redo it from this one")
