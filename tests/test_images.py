"""Strict image decoding: complete JPEGs and PNGs decode as OpenCV decodes them, a file cut anywhere is an error
naming its source (OpenCV alone returns a partly grey image for a cut JPEG), in files and in DNA-Rendering's HDF5."""
from __future__ import annotations

import cv2
import h5py
import numpy as np
import pytest

from thuman4_fixture import write_thuman4

from pig.data.dna import DnaCapture
from pig.data.images import decode_image, read_image
from pig.data.raw import CaptureError
from pig.data.smc_writer import write_smc
from pig.data.thuman4 import Thuman4Capture


def _photo(height=120, width=140, seed=0) -> np.ndarray:
    """Smooth gradients plus noise: compresses like a photograph, so a cut lands inside the image data."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[:height, :width]
    base = np.dstack([xs * 255 // width, ys * 255 // height, (xs + ys) * 255 // (width + height)])
    return np.clip(base + rng.integers(-25, 25, base.shape), 0, 255).astype(np.uint8)


def _encode(image, ext, *params) -> bytes:
    ok, data = cv2.imencode(ext, image, list(params))
    assert ok
    return data.tobytes()


ENCODINGS = {
    "baseline jpeg": lambda im: _encode(im, ".jpg", cv2.IMWRITE_JPEG_QUALITY, 90),
    "progressive jpeg": lambda im: _encode(im, ".jpg", cv2.IMWRITE_JPEG_PROGRESSIVE, 1),
    "png": lambda im: _encode(im, ".png"),
    "grey png": lambda im: _encode(im[..., 0], ".png"),
    # The render stage's lossless chunks (VP8L), and the other two first chunks of the container: lossy (VP8) and
    # lossy with alpha (VP8X).
    "lossless webp": lambda im: _encode(im, ".webp", cv2.IMWRITE_WEBP_QUALITY, 101),
    "lossy webp": lambda im: _encode(im, ".webp", cv2.IMWRITE_WEBP_QUALITY, 80),
    "alpha webp": lambda im: _encode(np.dstack([im, im[..., :1]]), ".webp", cv2.IMWRITE_WEBP_QUALITY, 80),
}
TRUNCATED = {"jpeg": "truncated or corrupt JPEG", "png": "truncated PNG", "webp": "truncated WebP"}


@pytest.mark.parametrize("kind", sorted(ENCODINGS))
def test_complete_images_decode_exactly_as_opencv_with_padding_or_trailing_bytes(kind):
    data = ENCODINGS[kind](_photo())
    expected = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    for variant in (data, data + b"\0" * 37, data + b"trailing bytes after the end"):
        np.testing.assert_array_equal(decode_image(variant, "x", cv2.IMREAD_UNCHANGED), expected)
    np.testing.assert_array_equal(decode_image(np.frombuffer(data, np.uint8), "x", cv2.IMREAD_UNCHANGED), expected)


@pytest.mark.parametrize("kind", sorted(ENCODINGS))
@pytest.mark.parametrize("fraction", [0.05, 0.5, 0.75, 0.99])
def test_a_cut_image_is_an_error_naming_the_source(kind, fraction):
    data = ENCODINGS[kind](_photo())
    cut = data[:int(len(data) * fraction)]
    expected = TRUNCATED[kind.split()[-1]]
    with pytest.raises(CaptureError, match=rf"^images/cam03/00000007\.x: {expected} \({len(cut)} bytes"):
        decode_image(cut, "images/cam03/00000007.x")
    with pytest.raises(CaptureError, match=expected):
        decode_image(data[:-2], "x")  # only the end marker / the IEND CRC missing


def test_opencv_imread_alone_accepts_the_cut_jpeg(tmp_path):
    """Why the check exists: cv2.imread decodes a 75 % JPEG file to a full-size image whose lower rows are grey."""
    image = _photo(240, 200)
    data = _encode(image, ".jpg", cv2.IMWRITE_JPEG_QUALITY, 95)
    path = tmp_path / "00000000.jpg"
    path.write_bytes(data[:len(data) * 3 // 4])
    decoded = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert decoded is not None and decoded.shape == image.shape
    assert np.abs(decoded[-20:].astype(int) - image[-20:]).mean() > 20  # the lost rows, filled in
    with pytest.raises(CaptureError, match=r"00000000\.jpg: truncated or corrupt JPEG"):
        read_image(path)


def test_thumbnail_end_marker_does_not_make_a_cut_jpeg_complete():
    """An EXIF segment holding a thumbnail JPEG has its own FF D9 before the main image data."""
    thumbnail = _encode(_photo(16, 16, seed=1), ".jpg")
    payload = b"Exif\0\0" + thumbnail
    app1 = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
    main = _encode(_photo(), ".jpg")
    data = main[:2] + app1 + main[2:]
    expected = cv2.imdecode(np.frombuffer(main, np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(decode_image(data, "x"), expected)
    for cut in (2 + len(app1), 2 + len(app1) + (len(main) - 2) * 3 // 4):  # ends on the thumbnail's FF D9; 75 %
        with pytest.raises(CaptureError, match="truncated or corrupt JPEG"):
            decode_image(data[:cut], "x")


def test_empty_missing_and_non_image_files(tmp_path):
    with pytest.raises(CaptureError, match=r"^x: empty image \(0 bytes\)"):
        decode_image(b"", "x")
    with pytest.raises(CaptureError, match=r"absent\.png: image file not found"):
        read_image(tmp_path / "absent.png")
    (tmp_path / "text.jpg").write_text("hello")
    with pytest.raises(CaptureError, match=r"text\.jpg: image bytes could not be decoded"):
        read_image(tmp_path / "text.jpg")
    (tmp_path / "folder.png").mkdir()
    with pytest.raises(CaptureError, match=r"folder\.png: is a folder, not a regular file"):
        read_image(tmp_path / "folder.png")


def test_truncated_image_in_a_dna_smc_names_the_file_and_hdf5_path(tmp_path):
    raw = Thuman4Capture(write_thuman4(tmp_path / "raw", cameras=3, frames=3))
    main, annots = write_smc(raw, tmp_path / "dna", "0012_01", tmp_path / "raw" / "body_model.npz", num_5mp=3,
                             image_ext=".jpg")
    for path, key in ((main, "Camera_5mp/1/color/2"), (annots, "Mask/2/mask/1")):
        with h5py.File(path, "r+") as handle:
            data = handle[key][()]
            del handle[key]
            handle[key] = data[:len(data) * 3 // 4]
    with DnaCapture(main) as dna:
        assert dna.read_image("1", 1).shape == (80, 96, 3)  # neighbours still read
        with pytest.raises(CaptureError, match=r"0012_01\.smc:/Camera_5mp/1/color/2: truncated or corrupt JPEG"):
            dna.read_image("1", 2)
        with pytest.raises(CaptureError, match=r"0012_01_annots\.smc:/Mask/2/mask/1: truncated or corrupt JPEG"):
            dna.read_mask("2", 1)


def test_a_cut_render_read_for_evaluation_is_an_error_naming_it(tmp_path):
    """The evaluate stage's render reader decodes strictly too: a cut PNG is no grey-rowed image."""
    from pig._io import write_png
    from pig.data.images import read_png

    image = np.random.default_rng(0).random((24, 32, 3))
    path = tmp_path / "render.png"
    write_png(path, image)
    assert np.abs(read_png(path) - image).max() <= 0.5 / 255 + 1e-6  # RGB order and scale kept
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 3 // 4])
    with pytest.raises(CaptureError, match=f"{path}: truncated PNG"):
        read_png(path)
