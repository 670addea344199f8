"""Where a stage may write: never over its inputs, never over files it did not write itself.

Every folder a stage writes gets a hidden marker file naming the stage. A stage replaces only what lies
in a folder marked with its own name (or in a new or empty folder); anything else needs `--overwrite`.
An output that is, contains or lies inside an input, or that is an existing file, is always refused.
Checks run before anything is written. A long stage may build its folder resumably (`resumable_dir`), one
run per output at a time.
"""
from __future__ import annotations

import fcntl
import json
import os
import shutil
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from pig._io import _temporary_dir, atomic_dir, remove_orphans, replace_dir, write_json

MARKER = ".pig-stage"
PARTIAL_RECORD = ".pig-partial"  # in a resumable work folder: its stage and the settings its files were made with


class OutputError(ValueError):
    """The stage refuses to write to this output location."""


def marked_stage(folder: Path) -> str | None:
    """The stage named by `folder`'s marker; None without a readable one."""
    try:
        stage = json.loads((folder / MARKER).read_text())["stage"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return stage if isinstance(stage, str) else None


def check_apart(output: Path, inputs: Iterable[str | Path]) -> None:
    """Refuse an output that is one of the inputs, contains one, or lies inside one."""
    resolved = output.resolve()
    for given in inputs:
        path = Path(given).resolve()
        if resolved == path:
            raise OutputError(f"{output}: the output is the input {given}; choose another output folder")
        if resolved in path.parents:
            raise OutputError(f"{output}: the output contains the input {given}; choose another output folder")
        if path in resolved.parents:
            raise OutputError(f"{output}: the output lies inside the input {given}; choose a folder outside it")


def check_folder_path(folder: Path) -> None:
    """Refuse a folder path that is, or lies under, an existing file."""
    for path in (folder, *folder.parents):
        if path.is_dir():
            return
        if path.exists():
            where = "is an existing file" if path == folder else f"lies under the file {path}"
            raise OutputError(f"{folder}: the output folder {where}; nothing was written, choose a folder path")


def _foreign(folder: Path, stage: str, files: list[str]) -> str:
    owner = marked_stage(folder)
    if owner is not None:
        return (f"{folder}: holds the {owner} stage's output, not the {stage} stage's; pass --overwrite to replace "
                "it, or choose another output folder")
    shown = ", ".join(files[:3]) + (", ..." if len(files) > 3 else "")
    return (f"{folder}: holds files the {stage} stage did not write ({shown}); pass --overwrite to replace them, "
            "or choose another output folder")


def claim_dir(output: str | Path, stage: str, inputs: Iterable[str | Path] = (), overwrite: bool = False) -> Path:
    """Check that `stage` may replace the folder `output` as a whole (see `build_dir`); writes nothing."""
    output = Path(output)
    if output.is_symlink():  # the replacement would put the new folder in place of the link, not of its target
        raise OutputError(f"{output}: a symbolic link (to {os.readlink(output)}); the {stage} stage replaces its "
                          "output folder as a whole, which would replace the link; give the folder's own path, or "
                          "remove the link")
    check_folder_path(output)
    check_apart(output, inputs)
    if output.is_dir() and not overwrite and marked_stage(output) != stage:
        files = sorted(p.name for p in output.iterdir())
        if files:
            raise OutputError(_foreign(output, stage, files))
    return output


@contextmanager
def build_dir(output: Path, stage: str) -> Iterator[Path]:
    """A temporary folder that replaces `output` when the block succeeds (call `claim_dir` first).

    Removes the temporaries killed runs left beside `output` first and marks the new folder as `stage`'s."""
    remove_orphans(output)
    with atomic_dir(output) as tmp:
        yield tmp
        write_json(tmp / MARKER, {"stage": stage})


@contextmanager
def output_lock(output: Path, stage: str) -> Iterator[None]:
    """Hold the lock file `.{name}.lock` beside `output` for the block; OutputError naming the holder's pid if
    another process holds it. An flock, which the kernel releases when its holder dies: no stale lock after a kill."""
    path = output.with_name(f".{output.name}.lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:  # never through a link: the holder truncates and writes the file
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW, 0o666)
        except OSError as err:
            if os.path.islink(path):
                raise OutputError(f"{path}: the lock file of {output} is a symbolic link; a stage's lock is a plain "
                                  "file, and it writes through no link: remove the link, then run again") from None
            raise
        handle = os.fdopen(fd, "a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "unknown"
            handle.close()
            raise OutputError(f"{output}: another {stage} run (pid {holder}) is writing it; wait for it to finish or "
                              f"stop it, then run again (lock file {path})") from None
        try:  # the previous holder may have removed the file between our open and our lock: lock the current one
            current = os.fstat(handle.fileno()).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            current = False
        if current:
            break
        handle.close()
    try:
        handle.truncate(0)
        handle.write(str(os.getpid()))
        handle.flush()
        yield
    finally:
        path.unlink(missing_ok=True)
        handle.close()


def _partial_record(partial: Path) -> dict | None:
    try:
        return json.loads((partial / PARTIAL_RECORD).read_text())
    except (OSError, ValueError):
        return None


@contextmanager
def resumable_dir(output: Path, stage: str, settings: dict) -> Iterator[Path]:
    """Like `build_dir`, but the folder is built at `.{name}.partial` beside `output`, which a killed or failed run
    leaves behind: a rerun with the same `settings` (JSON; everything its files depend on) finds the files written
    so far there, a rerun with other settings starts it afresh. Files in it must be written atomically. One run
    per output at a time (`output_lock`). Call `claim_dir` first."""
    with output_lock(output, stage):
        remove_orphans(output)
        partial = output.with_name(f".{output.name}.partial")
        record = {"stage": stage, "settings": json.loads(json.dumps(settings))}
        if partial.is_dir():
            found = _partial_record(partial)
            if not isinstance(found, dict) or found.get("stage") != stage:
                raise OutputError(f"{partial}: a folder the {stage} stage did not write lies where it keeps its "
                                  "unfinished work; move it away")
            if found != record:
                shutil.rmtree(partial)
        if not partial.is_dir():
            fresh = _temporary_dir(output)  # renamed once the record is in: a partial folder always has one
            write_json(fresh / PARTIAL_RECORD, record)
            os.replace(fresh, partial)
        try:
            yield partial
        except BaseException:
            print(f"{stage}: the unfinished work is kept in {partial}; a rerun with the same settings continues "
                  "from it", file=sys.stderr)
            raise
        write_json(partial / MARKER, {"stage": stage})
        replace_dir(partial, output)
        (output / PARTIAL_RECORD).unlink()


def claim_files(folder: str | Path, names: Iterable[str], stage: str, inputs: Iterable[str | Path] = (),
                overwrite: bool = False) -> Path:
    """Check that `stage` may write the files `names` into `folder`, whose other files it leaves alone; then
    create and mark the folder and remove the temporaries killed runs left of those files."""
    folder = Path(folder)
    names = list(names)
    check_folder_path(folder)
    check_apart(folder, inputs)
    owner = marked_stage(folder) if folder.is_dir() else None
    if folder.is_dir() and not overwrite and owner != stage:
        present = [name for name in names if (folder / name).exists()]
        if present or owner is not None:
            raise OutputError(_foreign(folder, stage, present))
    folder.mkdir(parents=True, exist_ok=True)
    if owner != stage:
        write_json(folder / MARKER, {"stage": stage})
    for name in names:
        remove_orphans(folder / name)
    return folder
