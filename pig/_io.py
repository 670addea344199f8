"""Atomic file and folder writing for every layer (data, body, avatar, stages) and the benchmarks: write a
temporary name, then rename. At the bottom of the package's layers: it imports nothing of pig.

A killed stage never leaves a half-written PNG, CSV, JSON, plot or folder under its final name; the
hidden temporaries a kill leaves carry the writer's process id, so the next run can remove them. A temporary is
created here, exclusively and without following links, under a name with a random part: a file or symbolic link
that someone planted beside the destination is never written through, nor renamed into place.
"""
from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import re
import secrets
import shutil
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np


# Tries at a fresh random name before giving up: only a folder crowded with planted names needs a second.
NAME_TRIES = 16


def _token() -> str:
    """The random part of a temporary's name (8 hex digits)."""
    return secrets.token_hex(4)


def create_temporary(path: Path) -> tuple[Path, int]:
    """(name, write-only descriptor) of a new empty hidden temporary `.{stem}.{pid}.{random}.tmp{suffix}` beside
    `path` (the suffix kept: writers pick the format from it), created exclusively and without following links,
    so that nothing planted under the name is written through; the caller closes the descriptor."""
    path.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(NAME_TRIES):
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.{_token()}.tmp{path.suffix}")
        try:
            return tmp, os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o666)
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, f"{path.parent}: {NAME_TRIES} random temporary names for {path.name} "
                          "were all taken; remove the hidden files beside it that nobody is writing", str(path))


def _temporary(path: Path) -> Path:
    """A new empty temporary beside `path` (`create_temporary`), for writers that open it by name."""
    tmp, fd = create_temporary(path)
    os.close(fd)
    return tmp


def _temporary_dir(path: Path, kind: str = "tmp") -> Path:
    """A new empty hidden folder `.{name}.{pid}.{random}.tmp` (the folder being built) or `.{name}.{pid}.{random}.old`
    (one to rename the folder it replaces onto) beside `path`, made here: a name someone planted is never used."""
    path.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(NAME_TRIES):
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{_token()}.{kind}")
        try:
            tmp.mkdir()
            return tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, f"{path.parent}: {NAME_TRIES} random temporary names for {path.name} "
                          "were all taken; remove the hidden folders beside it that nobody is writing", str(path))


def _still_ours(tmp: Path, created: os.stat_result) -> None:
    """Refuse to rename `tmp` into place when it is no longer the regular file this process created there."""
    try:
        now = os.lstat(tmp)
    except FileNotFoundError:
        raise OSError(f"{tmp}: the temporary vanished while it was written; nothing was replaced") from None
    if not stat.S_ISREG(now.st_mode) or (now.st_dev, now.st_ino) != (created.st_dev, created.st_ino):
        raise OSError(f"{tmp}: the temporary was replaced by another file or link while it was written; "
                      "nothing was replaced")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_orphans(path: str | Path) -> list[Path]:
    """Remove the temporaries of `path` that killed writers left beside it; returns what was removed.

    Matches this module's file and folder temporaries, with or without their random part (the folder form is
    also the earlier checkpoint writer's), and the earlier `.{name}.tmp-{pid}` / `.{name}.old-{pid}` folders of
    the preprocess stage; a temporary whose process is still running (a concurrent run) is kept.
    """
    path = Path(path)
    stem, suffix, name = (re.escape(part) for part in (path.stem, path.suffix, path.name))
    random = r"(?:\.[0-9a-f]{8})?"  # the random part of this module's names (absent from earlier ones)
    pattern = re.compile(rf"\.(?:{stem}\.(\d+){random}\.tmp{suffix}|{name}\.(\d+){random}\.(?:tmp|old)"
                         rf"|{name}\.(?:tmp|old)-(\d+))")
    removed = []
    if not path.parent.is_dir():
        return removed
    for entry in path.parent.iterdir():
        match = pattern.fullmatch(entry.name)
        if match is None or _alive(int(next(pid for pid in match.groups() if pid))):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()
        removed.append(entry)
    return removed


class NoSpaceError(OSError):
    """A write failed because the file system is full; the message names the file."""

    def __init__(self, message: str):
        super().__init__(message)
        self.errno = errno.ENOSPC


# Below this many free bytes a writer's error without an errno is taken for a full disk: torch.save reports one
# as a RuntimeError "unexpected pos ...", OpenEXR as "Failed to write pixel data", OpenCV's imwrite as False.
LOW_SPACE_BYTES = 1 << 20


def _no_space(err: BaseException, folder: Path) -> bool:
    if isinstance(err, OSError) and err.errno is not None:
        return err.errno in (errno.ENOSPC, errno.EDQUOT)
    if not isinstance(err, (OSError, RuntimeError)):
        return False
    try:
        stat = os.statvfs(folder)
    except OSError:
        return False
    return stat.f_bavail * stat.f_frsize < LOW_SPACE_BYTES


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A hidden temporary sibling of `path` to write to; renamed onto `path` when the block succeeds, removed
    when it raises. For writers that take a file name (torch.save, cv2.imwrite, OpenEXR, h5py). A write that
    fails on a full file system raises NoSpaceError naming `path`, whichever writer it was."""
    path = Path(path)
    tmp, fd = create_temporary(path)
    try:
        created = os.fstat(fd)
    finally:
        os.close(fd)
    try:
        yield tmp
        _still_ours(tmp, created)
        os.replace(tmp, path)
    except Exception as err:
        if _no_space(err, tmp.parent):
            raise NoSpaceError(f"{path}: no space left on the device while writing it ({err}); free "
                               "some space or choose an output folder on another disk, then rerun") from err
        raise
    finally:
        tmp.unlink(missing_ok=True)


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """A new hidden temporary folder beside `path` to build in; when the block succeeds it takes the place of
    `path` (an older folder there is removed only once the new one is in place), when it raises it is removed."""
    path = Path(path)
    tmp = _temporary_dir(path)
    try:
        yield tmp
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def replace_dir(built: Path, path: Path) -> None:
    """Rename the folder `built` to `path`; an older folder there is removed only once the new one is in place."""
    if os.path.lexists(path):
        if path.is_symlink() or not path.is_dir():
            raise OSError(f"{path}: a file or link lies where the folder goes; nothing was replaced (move it away)")
        old = _temporary_dir(path, "old")  # an empty folder, which the rename replaces
        os.replace(path, old)
        os.replace(built, path)
        shutil.rmtree(old)
    else:
        os.replace(built, path)


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _json_ready(data: Any) -> Any:
    """`data` with NaN and +-inf (Python or numpy floats) as None, numpy scalars and arrays as Python values."""
    if isinstance(data, dict):
        return {key: _json_ready(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [_json_ready(value) for value in data]
    if isinstance(data, np.ndarray):
        return _json_ready(data.tolist())
    if isinstance(data, np.generic):
        data = data.item()
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def write_json(path: str | Path, data: Any) -> None:
    """Strict JSON: non-finite numbers are written as null (JSON has no NaN); readers take null back as NaN."""
    write_text(path, json.dumps(_json_ready(data), indent=2, allow_nan=False) + "\n")


def nan_for_null(record: dict) -> dict:
    """A flat record read from `write_json`'s JSON (an evaluate summary, a render timing) with null as NaN."""
    return {key: math.nan if value is None else value for key, value in record.items()}


def read_record(path: str | Path, expected: str) -> dict:
    """A flat JSON object written by `write_json` (an evaluate summary, a render timing), null read back as NaN;
    a missing, unreadable or non-object file is an error naming `path` and the `expected` record."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; expected {expected}")
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not valid JSON ({err}); expected {expected}") from None
    if not isinstance(record, dict):
        raise ValueError(f"{path}: expected {expected} as a JSON object, found {type(record).__name__}")
    return nan_for_null(record)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """(H, W, 3) RGB or (H, W, 4) RGBA, float in [0, 1] or uint8 -> 8-bit PNG."""
    path = Path(path)
    if image.dtype != np.uint8:
        image = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    bgr = image[..., [2, 1, 0, 3]] if image.shape[-1] == 4 else image[..., ::-1]  # OpenCV's channel order
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(bgr)):
            raise OSError(f"{path}: OpenCV could not write the PNG")


def write_figure(path: str | Path, figure, dpi: float | None = None) -> None:
    """Save a matplotlib figure (format from the suffix) and close it."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path) as tmp:
            figure.savefig(tmp, dpi=dpi)
    finally:
        plt.close(figure)


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
