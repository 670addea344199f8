"""Reading `.npz` archives (body parameters, body models) without running code from the file.

`numpy.load` unpickles anything that is not a zip or .npy file when pickles are allowed, and otherwise
answers a random-bytes file with advice to allow them. Here a file that is not a zip archive is refused
by its first bytes, members are read as plain arrays, and a member holding pickled objects is only
unpickled when the caller allows it for that key, and then only into numpy arrays and scipy sparse
matrices (some SMPL-X files store `J_regressor` so). Only the members asked for are read, and each only
after its declared sizes (the zip's and the .npy header's) agree and stay under a bound, so a small file
cannot claim gigabytes; data preparation, no paper equation.
"""
from __future__ import annotations

import io
import math
import pickle
import threading
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pig.inputs import require_regular_file

ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header, or the end record of an empty archive
_HEADER_READERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
_NUMPY_GLOBALS = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
                  ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
                  ("numpy", "ndarray"), ("numpy", "dtype")}
_SPARSE_CLASSES = {f"{fmt}_{kind}" for fmt in ("csr", "csc", "coo") for kind in ("matrix", "array")}
# Largest member read, decompressed: an SMPL-X model's largest array (posedirs, float64) is ~120 MB.
MAX_MEMBER_BYTES = 1 << 30
# numpy parses a .npy header with ast.literal_eval, whose AST construction in CPython 3.11 keeps its recursion depth
# in the interpreter, not the thread: two decode threads parsing at once (the evaluate stage's chunk readers) can
# fail with "SystemError: AST constructor recursion depth mismatch" (python/cpython#106905; seen here in an evaluate
# pass). Headers are parsed one at a time.
_HEADER_PARSE = threading.Lock()


class _ArraysOnlyUnpickler(pickle.Unpickler):
    """Rebuilds numpy arrays and scipy sparse matrices; any other global (a function to call) is refused."""

    def find_class(self, module: str, name: str):
        allowed = (module, name) in _NUMPY_GLOBALS or (module.startswith("scipy.sparse") and name in _SPARSE_CLASSES)
        if not allowed:
            raise pickle.UnpicklingError(f"refused to load {module}.{name}")
        return super().find_class(module, name)


def read_npz(path: str | Path, error: type[Exception], expected: str, keys=None,
             pickled: tuple[str, ...] = (), max_bytes: int = MAX_MEMBER_BYTES,
             declared: Callable[[str, tuple, np.dtype], str | None] | None = None) -> dict[str, np.ndarray]:
    """Arrays of the npz at `path` (only `keys` if given, those present, read in that order); `error(message naming
    the file)` on anything that is not a readable npz archive. Keys in `pickled` may hold numpy arrays or scipy
    sparse matrices stored as pickled objects; other object members are an error. A member larger than `max_bytes`
    decompressed is refused before it is read, and so is one for which `declared(key, shape, dtype)` (its .npy
    header's) returns what was expected instead."""
    path = Path(path)
    try:
        require_regular_file(path, error, expected)
        with path.open("rb") as handle:
            return _read_archive(handle, path, error, expected, keys, pickled, max_bytes, declared)
    except FileNotFoundError:
        raise error(f"{path}: file not found; expected {expected}") from None
    except OSError as err:
        raise error(f"{path}: cannot read the file ({err.strerror or err}); expected {expected}") from None


def read_npz_bytes(data: bytes, source: str, error: type[Exception], expected: str, keys=None,
                   max_bytes: int = MAX_MEMBER_BYTES) -> dict[str, np.ndarray]:
    """As `read_npz`, for an npz held in memory (a checkpoint's body model); `source` names it in errors."""
    return _read_archive(io.BytesIO(data), source, error, expected, keys, (), max_bytes)


def _read_archive(handle, source, error, expected, keys, pickled, max_bytes, declared=None) -> dict[str, np.ndarray]:
    try:
        with _zip_archive(handle, source, error, expected) as archive:
            members = {name[:-4]: name for name in archive.namelist() if name.endswith(".npy")}
            wanted = members if keys is None else [k for k in keys if k in members]
            return {key: _member(archive, members[key], key in pickled, source, error, max_bytes, declared)
                    for key in wanted}
    except (OSError, zipfile.BadZipFile, zlib.error, EOFError) as err:
        raise error(f"{source}: not a valid npz archive (truncated or corrupt: {err}); expected {expected}") from None


def _check_declared(info: zipfile.ZipInfo, header_bytes: int, shape, dtype: np.dtype, source, error,
                    max_bytes: int) -> None:
    """Refuse a member whose .npy header disagrees with the zip's declared size, or that exceeds `max_bytes`."""
    key = info.filename[:-4]
    declared = math.prod(shape) * dtype.itemsize
    if declared > max_bytes:
        raise error(f"{source}: member '{key}' declares shape {shape} of {dtype} ({declared:,} bytes), more than "
                    f"the {max_bytes:,} bytes read from one member; not read")
    if header_bytes + declared != info.file_size:
        raise error(f"{source}: member '{key}' declares shape {shape} of {dtype} ({declared:,} bytes) but the "
                    f"archive stores {info.file_size - header_bytes:,} bytes of data for it; corrupt or forged")


def _member(archive: zipfile.ZipFile, name: str, pickled_ok: bool, path, error: type[Exception],
            max_bytes: int, declared=None) -> np.ndarray:
    key = name[:-4]
    info = archive.getinfo(name)
    if info.file_size > max_bytes:
        raise error(f"{path}: member '{key}' declares {info.file_size:,} bytes decompressed, more than the "
                    f"{max_bytes:,} bytes read from one member; not read")
    with archive.open(name) as member:
        shape, _, dtype = _header(member, key, path, error)
        wanted = declared(key, shape, dtype) if declared is not None else None
        if wanted is not None:
            raise error(f"{path}: member '{key}' declares shape {shape} of {dtype}, expected {wanted}; not read")
        if not dtype.hasobject:
            _check_declared(info, member.tell(), shape, dtype, path, error, max_bytes)
            with archive.open(name) as again, _HEADER_PARSE:  # read_array parses the header itself
                try:
                    return np.lib.format.read_array(again, allow_pickle=False)
                except ValueError as err:
                    raise error(f"{path}: member '{key}' is not a valid .npy array ({err})") from None
        if not pickled_ok:
            raise error(f"{path}: '{key}' holds pickled Python objects, which are not loaded (loading them could "
                        "run code); expected a numeric array")
        try:
            return np.asarray(_ArraysOnlyUnpickler(member).load())
        except (zipfile.BadZipFile, zlib.error):
            raise  # a corrupt archive, reported by read_npz
        except Exception as err:  # any failure of the restricted unpickler means the member is not plain data
            raise error(f"{path}: '{key}' holds pickled objects other than numpy arrays or scipy sparse matrices "
                        f"({err}); they are not loaded because loading them could run code") from None


def _zip_archive(handle, path, error: type[Exception], expected: str) -> zipfile.ZipFile:
    """The open file `handle` of `path` (a path, or a name in errors) as a zip archive, after its first bytes showed it is one (`error` otherwise)."""
    head = handle.read(4)
    if head not in ZIP_MAGIC:
        shown = f"starts with {head!r}" if head else "is empty"
        raise error(f"{path}: not a valid npz archive (the file {shown}); expected {expected}, a zip of .npy arrays as "
                    "numpy.savez writes")
    handle.seek(0)
    return zipfile.ZipFile(handle)


def _unreadable(path: Path, err: Exception, error: type[Exception], expected: str) -> Exception:
    """`error` naming `path` for an exception met while opening or reading an npz archive."""
    if isinstance(err, FileNotFoundError):
        return error(f"{path}: file not found; expected {expected}")
    if isinstance(err, (zipfile.BadZipFile, zlib.error, EOFError)):
        return error(f"{path}: not a valid npz archive (truncated or corrupt: {err}); expected {expected}")
    return error(f"{path}: cannot read the file ({getattr(err, 'strerror', None) or err}); expected {expected}")


_ARCHIVE_ERRORS = (OSError, zipfile.BadZipFile, zlib.error, EOFError)


def _header(member, key: str, path, error: type[Exception]) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, Fortran order, dtype) from the .npy header at the start of `member`, which it reads past."""
    try:
        version = np.lib.format.read_magic(member)
        if version not in _HEADER_READERS:
            raise ValueError(f"unsupported .npy format version {version}")
        with _HEADER_PARSE:
            shape, fortran, dtype = _HEADER_READERS[version](member)
    except ValueError as err:
        raise error(f"{path}: member '{key}' is not a valid .npy array ({err})") from None
    return tuple(shape), fortran, dtype


def npz_shapes(path: str | Path, error: type[Exception], expected: str, keys) -> dict[str, tuple[int, ...]]:
    """The declared shapes of the members `keys` (those present) of the npz at `path`, from their .npy headers
    alone; `error` as `read_npz`'s."""
    path = Path(path)
    try:
        require_regular_file(path, error, expected)
        with path.open("rb") as handle, _zip_archive(handle, path, error, expected) as archive:
            members = {name[:-4]: name for name in archive.namelist() if name.endswith(".npy")}
            shapes = {}
            for key in (k for k in keys if k in members):
                with archive.open(members[key]) as member:
                    shapes[key] = _header(member, key, path, error)[0]
            return shapes
    except _ARCHIVE_ERRORS as err:
        raise _unreadable(path, err, error, expected) from None


def read_npz_rows(path: str | Path, error: type[Exception], expected: str, keys, row_keys, length: int,
                  rows: range, max_bytes: int = MAX_MEMBER_BYTES) -> dict[str, np.ndarray]:
    """As `read_npz` (plain arrays only), but a member of `row_keys` whose first dimension is `length` is read at
    `rows` alone (a range of positive step within 0..length-1), streamed a block at a time: its selected rows, not
    the whole member, are what `max_bytes` bounds, and rows past the last selected one are never decompressed."""
    path = Path(path)
    try:
        require_regular_file(path, error, expected)
        with path.open("rb") as handle, _zip_archive(handle, path, error, expected) as archive:
            members = {name[:-4]: name for name in archive.namelist() if name.endswith(".npy")}
            return {key: _member_or_rows(archive, members[key], key in row_keys, length, rows, path, error, max_bytes)
                    for key in keys if key in members}
    except _ARCHIVE_ERRORS as err:
        raise _unreadable(path, err, error, expected) from None


ROW_BLOCK_BYTES = 1 << 24  # rows streamed per read


def _member_or_rows(archive: zipfile.ZipFile, name: str, by_rows: bool, length: int, rows: range, path,
                    error: type[Exception], max_bytes: int) -> np.ndarray:
    key = name[:-4]
    with archive.open(name) as member:
        shape, fortran, dtype = _header(member, key, path, error)
        if dtype.hasobject:
            raise error(f"{path}: '{key}' holds pickled Python objects, which are not loaded (loading them could "
                        "run code); expected a numeric array")
        if not (by_rows and len(shape) >= 1 and shape[0] == length):
            return _member(archive, name, False, path, error, max_bytes)
        if fortran and len(shape) > 1:  # a row's values lie apart in the file: the whole member, bounded, then rows
            return np.ascontiguousarray(_member(archive, name, False, path, error, max_bytes)[rows.start:rows.stop:rows.step])
        header_bytes = member.tell()
        _check_declared(archive.getinfo(name), header_bytes, shape, dtype, path, error, math.inf)  # sizes agree
        tail = shape[1:]
        row_bytes = math.prod(tail) * dtype.itemsize
        if len(rows) * row_bytes > max_bytes:
            raise error(f"{path}: member '{key}' at {len(rows):,} rows of {row_bytes:,} bytes is more than the "
                        f"{max_bytes:,} bytes read from one member; not read")
        out = np.empty((len(rows), *tail), dtype=dtype)
        if not rows or row_bytes == 0:
            return out
        block = max(1, ROW_BLOCK_BYTES // row_bytes)
        member.seek(header_bytes + rows.start * row_bytes)
        filled, index = 0, rows.start
        while index <= rows[-1]:
            count = min(block, rows[-1] + 1 - index)
            data = member.read(count * row_bytes)
            if len(data) != count * row_bytes:
                raise error(f"{path}: member '{key}' ends before row {index + len(data) // row_bytes}; truncated")
            picked = np.frombuffer(data, dtype=dtype).reshape(count, *tail)[(rows.start - index) % rows.step::rows.step]
            out[filled:filled + len(picked)] = picked
            filled, index = filled + len(picked), index + count
        return out
