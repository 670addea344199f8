"""Strict decoding of encoded JPEG/PNG images: a truncated file is an error naming its source.

cv2.imread decodes a JPEG file cut short to a full-size image with grey rows and only a libjpeg warning
on stderr, so the encoded stream is checked for its end before decoding: a JPEG must hold the
end-of-image marker FF D9 after its first scan, a PNG its IEND chunk (under 0.02 ms against about 12 ms for
decoding a 1330x1150 JPEG). The size the header declares (PNG IHDR, JPEG SOF) is checked against a bound
before decoding, so a small file cannot make the decoder allocate gigabytes. Images are decoded as stored,
ignoring an EXIF orientation tag: the calibration describes the sensor's pixels, and masks are rarely
tagged alike. Every reader of raw and preprocessed images decodes through here; data preparation, no paper
equation.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pig.data.raw import CaptureError
from pig.inputs import require_regular_file

JPEG_START = b"\xff\xd8"
JPEG_END = b"\xff\xd9"
JPEG_SCAN = 0xDA  # start-of-scan marker: entropy-coded data follows, up to the end marker
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # length 0, type, fixed CRC
# Markers without a length field (TEM, RST0..7, SOI, EOI).
_STANDALONE = {0x01, *range(0xD0, 0xDA)}
# Start-of-frame markers (baseline, progressive, lossless, arithmetic...): C0..CF but DHT, JPG and DAC.
_JPEG_FRAME = set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Default bound on a decoded image: 100 MP (300 MB as 8-bit RGB); capture cameras are 1-50 MP.
MAX_PIXELS = 100_000_000


def declared_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR or a JPEG's start-of-frame header, without decoding; None if absent."""
    if data.startswith(PNG_SIGNATURE):
        if data[12:16] != b"IHDR" or len(data) < 24:
            return None
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data.startswith(JPEG_START):
        pos, size = 2, len(data)
        while pos + 4 <= size:
            if data[pos] != 0xFF:
                return None
            marker = data[pos + 1]
            if marker == 0xFF:
                pos += 1
                continue
            if marker in _STANDALONE:
                pos += 2
                continue
            if marker in _JPEG_FRAME:
                if pos + 9 > size:
                    return None
                return int.from_bytes(data[pos + 7:pos + 9], "big"), int.from_bytes(data[pos + 5:pos + 7], "big")
            if marker == JPEG_SCAN:
                return None
            pos += 2 + int.from_bytes(data[pos + 2:pos + 4], "big")
    return None


def check_declared_size(data: bytes, source: str, max_pixels: int) -> None:
    """CaptureError naming `source` if the image is not a JPEG or PNG with a readable header declaring at most
    `max_pixels` pixels."""
    size = declared_size(data)
    if size is None:
        raise CaptureError(f"{source}: image bytes could not be decoded (corrupt, or not a JPEG or PNG file: no "
                           "PNG IHDR or JPEG frame header declares its size)")
    width, height = size
    if width * height > max_pixels:
        raise CaptureError(f"{source}: the image header declares {width}x{height} (WxH) pixels, more than the "
                           f"{max_pixels:,} expected here; not decoded (a corrupt or forged file?)")


def _jpeg_complete(data: bytes) -> bool:
    """Whether the end-of-image marker follows the first scan. Segments before the scan are skipped by their
    lengths, so an EXIF thumbnail's own FF D9 does not count; zero padding and other bytes after the marker
    are tolerated."""
    pos, size = 2, len(data)
    while pos + 4 <= size:
        if data[pos] != 0xFF:  # stray bytes between segments (libjpeg skips them): the file must end with FF D9
            return data.rstrip(b"\0").endswith(JPEG_END)
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in _STANDALONE:
            pos += 2
            continue
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker == JPEG_SCAN:
            scan = pos + 2 + length
            end = size if data[-1] else len(data.rstrip(b"\0"))
            if end - 2 >= scan and data[end - 2:end] == JPEG_END:
                return True  # the usual case, checked without scanning the image data
            return data.find(JPEG_END, scan) != -1
        pos += 2 + length
    return False


def check_complete(data: bytes, source: str) -> None:
    """CaptureError naming `source` if the JPEG or PNG stream `data` is cut short; other formats pass."""
    if data.startswith(JPEG_START):
        if not _jpeg_complete(data):
            raise CaptureError(f"{source}: truncated or corrupt JPEG ({len(data)} bytes, no end-of-image marker "
                               "FF D9 after the image data); copy or extract the file again")
    elif data.startswith(PNG_SIGNATURE):
        if data.rfind(PNG_END) == -1:
            raise CaptureError(f"{source}: truncated PNG ({len(data)} bytes, no IEND chunk); copy or extract the "
                               "file again")


def decode_image(data: bytes | np.ndarray, source: str, flags: int = cv2.IMREAD_COLOR,
                 max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Decode encoded image bytes with OpenCV (BGR for IMREAD_COLOR), as stored (EXIF orientation ignored), after
    checking they are complete and declare at most `max_pixels` pixels."""
    encoded = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
    if not encoded:
        raise CaptureError(f"{source}: empty image (0 bytes); expected a JPEG or PNG")
    check_complete(encoded, source)
    check_declared_size(encoded, source, max_pixels)
    if flags != cv2.IMREAD_UNCHANGED:  # IMREAD_UNCHANGED ignores the orientation already and takes no other flag
        flags |= cv2.IMREAD_IGNORE_ORIENTATION
    try:
        image = cv2.imdecode(np.frombuffer(encoded, dtype=np.uint8), flags)
    except cv2.error:
        image = None
    if image is None:
        raise CaptureError(f"{source}: image bytes could not be decoded (corrupt, or not a JPEG or PNG file)")
    return image


def read_image(path: str | Path, flags: int = cv2.IMREAD_COLOR, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Read and strictly decode the image file at `path`; CaptureError naming it if absent, not a regular file,
    cut short, corrupt or declaring more than `max_pixels` pixels."""
    try:
        require_regular_file(path, CaptureError, "a JPEG or PNG image file")
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise CaptureError(f"{path}: image file not found") from None
    except OSError as err:
        raise CaptureError(f"{path}: cannot read the image file: {err.strerror or err}") from None
    return decode_image(data, str(path), flags, max_pixels)


def read_png(path: str | Path) -> np.ndarray:
    """8-bit RGB PNG -> (H, W, 3) float32 in [0, 1], strictly (a cut-off render is an error naming the file)."""
    return cv2.cvtColor(read_image(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(np.float32) / 255
