"""Rendered views of one split as 8-bit lossless chunks: one file per (LOD, camera, run of frames).

A chunk `lod{l}/{camera}/{first frame:08d}.npz` holds the ids of its frames and their lossless image streams back
to back (no pickle). A fit's 56,000 THuman4 views make a few thousand files instead of 112,000 PNG/EXR pairs, and
chunks are written atomically: one present is complete, so a killed render resumes at the missing chunks and
evaluate never reads half a file. A split folder whose views are per-view PNGs (`{camera}/{frame:08d}.png`, the
render stage's `--every-view` option) reads the same way.
"""
from __future__ import annotations

import json
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from pig.body.npz import read_npz
from pig.data.images import decode_image, read_png
from pig.data.raw import CaptureError
from pig._io import atomic_path, write_json

MANIFEST = "manifest.json"
FORMAT = "pig-render-chunks/1"
# Lossless codecs by name: suffix and OpenCV's encoder flags (WebP quality above 100 is its lossless mode).
CODECS = {"webp": (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]), "png": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 3])}
CHUNK_KEYS = ("frames", "offsets", "data", "codec")
CHUNK_EXPECTED = ("a render chunk .npz with 'frames' (F,) int64, 'offsets' (F + 1,) int64, 'data' uint8 image "
                  "streams and 'codec'")


def read_manifest(split_dir: Path) -> dict | None:
    """The render stage's manifest of a split folder; None for a folder of per-view PNGs without one."""
    path = Path(split_dir) / MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CaptureError(f"{path}: not valid JSON ({err}); expected the render stage's manifest") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise CaptureError(f"{path}: expected a render manifest of format {FORMAT!r}")
    return manifest


def write_manifest(split_dir: Path, manifest: dict) -> None:
    write_json(Path(split_dir) / MANIFEST, {"format": FORMAT, **manifest})


def chunk_path(level_dir: Path, camera: str, first_frame: int) -> Path:
    return Path(level_dir) / camera / f"{first_frame:08d}.npz"


def encode_image(image: np.ndarray, codec: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> the codec's lossless stream (uint8)."""
    suffix, flags = CODECS[codec]
    ok, data = cv2.imencode(suffix, np.ascontiguousarray(image[..., ::-1]), flags)
    if not ok:
        raise OSError(f"OpenCV could not encode a {image.shape} image as {codec}")
    return data.reshape(-1)


def write_chunk(path: Path, frames: list[int], streams: list[np.ndarray], codec: str) -> int:
    """Write one chunk atomically from encoded streams; returns its size in bytes."""
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in streams])]).astype(np.int64)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:  # np.savez on a handle keeps the temporary's name
            np.savez(handle, frames=np.asarray(frames, dtype=np.int64), offsets=offsets,
                     data=np.concatenate(streams) if streams else np.zeros(0, np.uint8), codec=np.array(codec))
    return path.stat().st_size


class ChunkEncoder:
    """Encodes views on worker threads (OpenCV releases the GIL) and writes each chunk once all its views are in.

    `add` hands over one view; `finish_chunk` queues the chunk's write behind its views' encodings. At most
    `pending_views` views wait for their encoding (`add` blocks for the oldest: the renderer never runs far ahead of
    the encoders) and `pending` chunks for their write, which bounds the memory held by views not yet written."""

    def __init__(self, codec: str, workers: int = 2, pending: int = 16, pending_views: int | None = None):
        if codec not in CODECS:
            raise ValueError(f"unknown render codec {codec!r}; expected one of {sorted(CODECS)}")
        self.codec, self.pending = codec, pending
        self.pending_views = pending_views or 8 * max(1, workers)
        self.encodings: deque[Future] = deque()
        self.pool = ThreadPoolExecutor(max(1, workers), thread_name_prefix="render-encode")
        self.views: dict[Path, tuple[list[int], list[Future]]] = {}
        self.writes: list[Future] = []
        self.bytes_written = 0

    def add(self, path: Path, frame: int, image: np.ndarray) -> None:
        frames, encoded = self.views.setdefault(path, ([], []))
        frames.append(frame)
        encoded.append(self.pool.submit(encode_image, image, self.codec))
        self.encodings.append(encoded[-1])
        while len(self.encodings) > self.pending_views:
            self.encodings.popleft().result()

    def finish_chunk(self, path: Path) -> None:
        frames, encoded = self.views.pop(path)
        self.writes.append(self.pool.submit(lambda: write_chunk(path, frames, [f.result() for f in encoded], self.codec)))
        while len(self.writes) > self.pending:
            self.bytes_written += self.writes.pop(0).result()

    def close(self) -> int:
        """Wait for every queued write (re-raising the first failure); returns the bytes written."""
        try:
            for write in self.writes:
                self.bytes_written += write.result()
        finally:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.writes = []
        return self.bytes_written


class RenderReader:
    """The views of one rendered LOD folder (`renders/{split}/lod{l}`): chunks, else per-view PNGs.

    Keeps the encoded streams of the last chunk read per camera (views are read camera-major), decodes one view
    at a time."""

    def __init__(self, level_dir: Path):
        self.level_dir = Path(level_dir)
        self._index: dict[str, dict[int, Path]] = {}
        self._open: dict[str, tuple[Path, dict[int, int], np.ndarray, np.ndarray, str]] = {}

    def _chunks(self, camera: str) -> dict[int, Path]:
        if camera not in self._index:
            index = {}
            for path in sorted((self.level_dir / camera).glob("[0-9]*.npz")):
                for frame in self._load(path)[1]:
                    index[frame] = path
            self._index[camera] = index
        return self._index[camera]

    def _load(self, path: Path) -> tuple[Path, dict[int, int], np.ndarray, np.ndarray, str]:
        arrays = read_npz(path, CaptureError, CHUNK_EXPECTED, keys=CHUNK_KEYS)  # bounded: no member read past 1 GiB
        missing = [key for key in CHUNK_KEYS if key not in arrays]
        if missing:
            raise CaptureError(f"{path}: missing {missing}; expected {CHUNK_EXPECTED}")
        frames, offsets, data, codec = (arrays[key] for key in CHUNK_KEYS)
        codec = str(codec)
        if (codec not in CODECS or frames.ndim != 1 or offsets.shape != (len(frames) + 1,) or data.dtype != np.uint8
                or offsets[0] != 0 or offsets[-1] != len(data) or np.any(np.diff(offsets) <= 0)):
            raise CaptureError(f"{path}: inconsistent chunk (codec {codec!r}, {len(frames)} frames, offsets "
                               f"{offsets.shape}, {data.size} bytes); expected {CHUNK_EXPECTED}")
        return path, {int(f): i for i, f in enumerate(frames)}, offsets, data, codec

    def has(self, camera: str, frame: int) -> bool:
        return frame in self._chunks(camera) or (self.level_dir / camera / f"{frame:08d}.png").is_file()

    def source(self, camera: str, frame: int) -> str:
        """Where a view is read from, for messages: its chunk, else its per-view PNG."""
        path = self._chunks(camera).get(frame)
        return f"{path} (frame {frame})" if path is not None else str(self.level_dir / camera / f"{frame:08d}.png")

    def image_u8(self, camera: str, frame: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of one view."""
        path = self._chunks(camera).get(frame)
        if path is None:  # a per-view PNG; CaptureError naming it when absent
            return np.round(read_png(self.source(camera, frame)) * 255).astype(np.uint8)
        opened = self._open.get(camera)  # a local: decoding threads share the reader
        if opened is None or opened[0] != path:
            opened = self._open[camera] = self._load(path)
        _, rows, offsets, data, _ = opened
        i = rows[frame]
        bgr = decode_image(data[offsets[i]:offsets[i + 1]], self.source(camera, frame), cv2.IMREAD_COLOR)
        return np.ascontiguousarray(bgr[..., ::-1])

    def image(self, camera: str, frame: int) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1] of one view, as `read_png` gives a per-view PNG."""
        return self.image_u8(camera, frame).astype(np.float32) / 255
