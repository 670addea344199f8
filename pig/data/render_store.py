"""Rendered views of one split as 8-bit lossless chunks: one file per (LOD, camera, run of frames).

A chunk `lod{l}/{camera}/{first frame:08d}.npz` holds the ids of its frames, their lossless image streams back
to back, its camera and LOD (no pickle); the split's manifest.json lists the frames, in runs of `chunk_frames` per
chunk, and the reader checks each chunk against it. A fit's 56,000 THuman4 views make a few thousand files instead
of 112,000 PNG/EXR pairs, and chunks are written atomically: one present is complete, so a killed render resumes at
the missing chunks and evaluate never reads half a file. A split folder whose views are per-view PNGs
(`{camera}/{frame:08d}.png`, the render stage's `--every-view` option) reads the same way.
"""
from __future__ import annotations

import json
import re
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from pig.body.npz import read_npz
from pig.data.images import PNG_SIGNATURE, declared_size, decode_image, read_png
from pig.data.raw import CaptureError
from pig.names import safe_name
from pig._io import atomic_path, write_json

MANIFEST = "manifest.json"
# Format 2 chunks name their camera and LOD, which the reader checks (a chunk copied from another folder is
# refused); format 1 chunks, which do not, are still read.
FORMAT = "pig-render-chunks/2"
FORMAT_WITHOUT_IDS = "pig-render-chunks/1"
MAX_MANIFEST_BYTES = 64 << 20  # a split of 10^6 frames lists them in ~8 MB
# Lossless codecs by name: suffix and OpenCV's encoder flags (WebP quality above 100 is its lossless mode). PNG with
# one row filter (Up) and run-length deflate at level 1: 0.44-0.48x the encoding time of zlib level 3 with libpng's
# adaptive filters, and 0.89-0.99x the bytes, on 1330 x 1150 synthetic views, here and on an H200's host
# (benchmarks/render_codecs.py; NOTES, "Evaluation", run43); the render stage's novel-pose views are bound by it.
CODECS = {"webp": (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]),
          "png": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP,
                           cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE])}
CHUNK_KEYS = ("frames", "offsets", "data", "codec", "camera", "lod")
CHUNK_EXPECTED = ("a render chunk .npz with 'frames' (F,) int64, 'offsets' (F + 1,) int64, 'data' uint8 image "
                  "streams, 'codec', 'camera' and 'lod'")
RERENDER = "re-render the split (pig render)"


def _manifest_problem(manifest) -> str | None:
    """What is wrong with a manifest's fields that the reader relies on; None if nothing."""
    if not isinstance(manifest, dict) or manifest.get("format") not in (FORMAT, FORMAT_WITHOUT_IDS):
        return f"expected a render manifest of format {FORMAT!r}"
    frames, cameras, size = manifest.get("frames"), manifest.get("cameras"), manifest.get("chunk_frames")
    if not isinstance(frames, list) or not all(type(f) is int for f in frames) or len(set(frames)) != len(frames):
        return "'frames' must be a list of distinct integer frame ids"
    if not isinstance(cameras, list) or not all(isinstance(c, str) for c in cameras):
        return "'cameras' must be a list of camera ids"
    if type(size) is not int or size < 1:
        return "'chunk_frames' must be a positive integer"
    if manifest.get("codec") not in CODECS:
        return f"'codec' must be one of {sorted(CODECS)}"
    return None


def read_manifest(split_dir: Path) -> dict | None:
    """The render stage's manifest of a split folder (its fields checked); None for a folder of per-view PNGs
    without one."""
    path = Path(split_dir) / MANIFEST
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as handle:
            text = handle.read(MAX_MANIFEST_BYTES + 1)
        if len(text) > MAX_MANIFEST_BYTES:
            raise CaptureError(f"{path}: larger than {MAX_MANIFEST_BYTES:,} bytes; expected the render stage's "
                               "manifest")
        manifest = json.loads(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CaptureError(f"{path}: not valid JSON ({err}); expected the render stage's manifest") from None
    problem = _manifest_problem(manifest)
    if problem is not None:
        raise CaptureError(f"{path}: {problem}; {RERENDER}")
    for camera in manifest["cameras"]:
        safe_name(camera, "camera id", str(path), CaptureError)
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


def write_chunk(path: Path, frames: list[int], streams: list[np.ndarray], codec: str, camera: str, lod: int) -> int:
    """Write one chunk of `camera` at LOD `lod` atomically from encoded streams; returns its size in bytes."""
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in streams])]).astype(np.int64)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:  # np.savez on a handle keeps the temporary's name
            np.savez(handle, frames=np.asarray(frames, dtype=np.int64), offsets=offsets,
                     data=np.concatenate(streams) if streams else np.zeros(0, np.uint8), codec=np.array(codec),
                     camera=np.array(camera), lod=np.array(lod, dtype=np.int64))
    return path.stat().st_size


class ChunkEncoder:
    """Encodes views on worker threads (OpenCV releases the GIL) and writes each chunk once all its views are in.

    `add` hands over one view; `finish_chunk` queues the chunk's write (with its camera and LOD) behind its views'
    encodings. At most `pending_views` views wait for their encoding (`add` blocks for the oldest: the renderer never
    runs far ahead of the encoders) and `pending` chunks for their write, which bounds the memory held by views not
    yet written."""

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

    def finish_chunk(self, path: Path, camera: str, lod: int) -> None:
        frames, encoded = self.views.pop(path)
        self.writes.append(self.pool.submit(
            lambda: write_chunk(path, frames, [f.result() for f in encoded], self.codec, camera, lod)))
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

    Where a view's chunk is and which frames it holds come from the split's manifest, so a chunk is only opened to
    read its views; each member's shape and dtype (from its header) are checked against the manifest before it is
    read, and each image stream's format and size before it is decoded: a crafted chunk is refused naming it, never
    read in full. With `sizes` ({camera: (width, height)}, the capture's) every view must have its camera's size.
    Keeps the encoded streams of the last chunk read per camera (views are read camera-major), decodes one view
    at a time."""

    def __init__(self, level_dir: Path, sizes: dict[str, tuple[int, int]] | None = None):
        self.level_dir = Path(level_dir)
        self.sizes = sizes
        level = re.fullmatch(r"lod(\d+)", self.level_dir.name)
        self.lod = int(level.group(1)) if level else None
        self.manifest = read_manifest(self.level_dir.parent)
        self._runs: dict[int, list[int]] = {}  # frame -> the frames of its chunk, in the chunk's order
        if self.manifest is not None:
            frames, size = self.manifest["frames"], self.manifest["chunk_frames"]
            for start in range(0, len(frames), size):
                run = frames[start:start + size]
                self._runs.update(dict.fromkeys(run, run))
            self._cameras = set(self.manifest["cameras"])
        self._open: dict[str, tuple[Path, dict[int, int], np.ndarray, np.ndarray]] = {}

    def _chunk(self, camera: str, frame: int) -> Path | None:
        """The chunk that holds a view by the manifest; None when it lists no such view (or there is none)."""
        if self.manifest is None or camera not in self._cameras or frame not in self._runs:
            return None
        return chunk_path(self.level_dir, camera, self._runs[frame][0])

    def _png(self, camera: str, frame: int) -> Path:
        return self.level_dir / camera / f"{frame:08d}.png"

    def has(self, camera: str, frame: int) -> bool:
        chunk = self._chunk(camera, frame)
        return (chunk is not None and chunk.is_file()) or self._png(camera, frame).is_file()

    def source(self, camera: str, frame: int) -> str:
        """Where a view is read from, for messages: its chunk, else its per-view PNG."""
        chunk = self._chunk(camera, frame)
        if chunk is not None and (chunk.is_file() or not self._png(camera, frame).is_file()):
            return f"{chunk} (frame {frame})"
        return str(self._png(camera, frame))

    def _view_bytes(self, camera: str) -> int | None:
        """Most bytes one lossless stream of `camera`'s size takes: twice the raw pixels, plus headers."""
        if self.sizes is None or camera not in self.sizes:
            return None
        width, height = self.sizes[camera]
        return 2 * 3 * width * height + 65536

    def _load(self, path: Path, camera: str, run: list[int]) -> tuple[Path, dict[int, int], np.ndarray, np.ndarray]:
        count, view_bytes = len(run), self._view_bytes(camera)
        shapes = {"frames": (count,), "offsets": (count + 1,), "camera": (), "lod": (), "codec": ()}

        def declared(key: str, shape: tuple, dtype: np.dtype) -> str | None:
            if key in ("frames", "offsets", "lod"):
                ok = dtype.kind in "iu" and shape == shapes[key]
                return None if ok else f"{shapes[key]} integers (the manifest's run of {count} frames)"
            if key in ("codec", "camera"):
                return None if dtype.kind == "U" and shape == () and dtype.itemsize <= 4 * 1024 else "a string"
            ok = dtype == np.uint8 and len(shape) == 1 and (view_bytes is None or shape[0] <= count * view_bytes)
            bound = f", at most {count * view_bytes:,} bytes for {count} views" if view_bytes is not None else ""
            return None if ok else f"(N,) uint8 image streams{bound}"

        arrays = read_npz(path, CaptureError, CHUNK_EXPECTED, keys=CHUNK_KEYS, declared=declared)
        required = CHUNK_KEYS if self.manifest["format"] == FORMAT else CHUNK_KEYS[:4]
        missing = [key for key in required if key not in arrays]
        if missing:
            raise CaptureError(f"{path}: missing {missing}; expected {CHUNK_EXPECTED}; {RERENDER}")
        frames, data = arrays["frames"], arrays["data"]
        offsets = arrays["offsets"].astype(np.int64)  # uint64 offsets past 2**63 turn negative: refused below
        codec = str(arrays["codec"])
        if self.manifest["format"] == FORMAT:
            found = (str(arrays["camera"]), int(arrays["lod"]))
            if found != (camera, self.lod):
                raise CaptureError(f"{path}: a chunk of camera {found[0]!r} at LOD {found[1]}, expected camera "
                                   f"{camera!r} at LOD {self.lod} (copied from another folder?); {RERENDER}")
        if codec != self.manifest["codec"]:
            raise CaptureError(f"{path}: codec {codec!r}, the manifest's is {self.manifest['codec']!r}; {RERENDER}")
        if frames.tolist() != run:
            raise CaptureError(f"{path}: holds frames {frames.tolist()}, expected {run} in that order (the "
                               f"manifest's run of frames); {RERENDER}")
        if offsets[0] != 0 or offsets[-1] != len(data) or np.any(np.diff(offsets) <= 0):
            raise CaptureError(f"{path}: inconsistent chunk ({count} frames, offsets {offsets[0]}..{offsets[-1]} for "
                               f"{data.size} bytes); expected {CHUNK_EXPECTED}; {RERENDER}")
        return path, {frame: i for i, frame in enumerate(run)}, offsets, data

    def _check_stream(self, stream: bytes, camera: str, source: str) -> None:
        """Refuses a stream that is not the manifest codec's lossless 8-bit RGB, or not of the camera's size."""
        if self.manifest["codec"] == "png":
            ok = stream.startswith(PNG_SIGNATURE) and stream[12:16] == b"IHDR" and stream[24:26] == b"\x08\x02"
            what = "an 8-bit RGB PNG"
        else:  # lossless WebP (VP8L) without alpha, as OpenCV writes an RGB image
            ok = (stream[:4] == b"RIFF" and stream[8:16] == b"WEBPVP8L" and len(stream) >= 25 and stream[20] == 0x2F
                  and not int.from_bytes(stream[21:25], "little") >> 28)
            what = "a lossless RGB WebP (VP8L)"
        if not ok:
            raise CaptureError(f"{source}: the image stream is not {what}, the manifest's codec; {RERENDER}")
        expected = self.sizes.get(camera) if self.sizes is not None else None
        if expected is not None and declared_size(stream) != tuple(expected):
            width, height = declared_size(stream)
            raise CaptureError(f"{source}: the image is {width}x{height} (WxH), camera {camera} is "
                               f"{expected[0]}x{expected[1]}; {RERENDER}")

    def image_u8(self, camera: str, frame: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of one view."""
        path = self._chunk(camera, frame)
        if path is None or not path.is_file():
            return self._png_u8(camera, frame, path)
        opened = self._open.get(camera)  # a local: decoding threads share the reader
        if opened is None or opened[0] != path:
            opened = self._open[camera] = self._load(path, camera, self._runs[frame])
        _, rows, offsets, data = opened
        i = rows[frame]
        source = self.source(camera, frame)
        stream = data[offsets[i]:offsets[i + 1]].tobytes()
        self._check_stream(stream, camera, source)
        bgr = decode_image(stream, source, cv2.IMREAD_COLOR)
        return np.ascontiguousarray(bgr[..., ::-1])

    def _png_u8(self, camera: str, frame: int, chunk: Path | None) -> np.ndarray:
        """A per-view PNG; a missing one is an error naming the chunk the manifest expects, if any."""
        png, manifest = self._png(camera, frame), self.level_dir.parent / MANIFEST
        if chunk is not None and not png.is_file():
            raise CaptureError(f"{chunk}: missing; the manifest {manifest} lists frame {frame} of camera {camera!r} "
                               f"in it; {RERENDER}")
        if self.manifest is not None and not png.is_file():
            raise CaptureError(f"{manifest}: lists no view of camera {camera!r} at frame {frame} (cameras "
                               f"{self.manifest['cameras']}, {len(self._runs)} frames); were the renders made for "
                               "another split or capture?")
        if self.manifest is None and not png.is_file() and any((self.level_dir / camera).glob("[0-9]*.npz")):
            raise CaptureError(f"{self.level_dir.parent / MANIFEST}: missing, so the render chunks under "
                               f"{self.level_dir} cannot be read; {RERENDER}")
        image = np.round(read_png(png) * 255).astype(np.uint8)  # CaptureError naming it when absent
        expected = self.sizes.get(camera) if self.sizes is not None else None
        if expected is not None and image.shape[:2] != (expected[1], expected[0]):
            raise CaptureError(f"{png}: the image is {image.shape[1]}x{image.shape[0]} (WxH), camera {camera} is "
                               f"{expected[0]}x{expected[1]}")
        return image

    def image(self, camera: str, frame: int) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1] of one view, as `read_png` gives a per-view PNG."""
        return self.image_u8(camera, frame).astype(np.float32) / 255
