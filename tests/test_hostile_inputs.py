"""Hostile and unlucky inputs (issue 25): images decoded as stored, every read bounded by what the file declares
(YAML aliases, npz members, HDF5 datasets, image headers), inputs that are not regular files, HDF5 data from
outside the file, out-of-range preset values, masks blamed for what is wrong with the masks."""
from __future__ import annotations

import json
import os
import shutil
import struct
import threading
import time
import zipfile
import zlib
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from thuman4_fixture import look_at, write_thuman4

from pig.config import ConfigError, load_preset, load_section, load_yaml
from pig.data.images import decode_image
from pig.data.raw import CaptureError
from pig.data.thuman4 import Thuman4Capture
from pig._cli import run_cli
from pig.stages.preprocess import main as preprocess_main


def _preprocess(root: Path, out: Path, *extra: str) -> int:
    return run_cli(preprocess_main, ["--input", str(root), "--output", str(out), "--preset", "test", "--no-progress",
                                     *extra])


# -- item 3: EXIF orientation ------------------------------------------------------------------------------------

def _exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """The JPEG with an APP1 Exif segment (big-endian TIFF, one IFD entry: Orientation) after its SOI."""
    tiff = b"MM\x00\x2a" + struct.pack(">I", 8) + struct.pack(">H", 1) + struct.pack(">HHIHH", 0x0112, 3, 1,
                                                                                     orientation, 0) + b"\0" * 4
    body = b"Exif\0\0" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body + jpeg[2:]


def test_images_tagged_with_an_exif_orientation_are_decoded_as_stored(tmp_path):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (30, 50, 3), dtype=np.uint8)  # not square: a rotation changes the shape
    plain = cv2.imencode(".jpg", image)[1].tobytes()
    tagged = _exif_orientation(plain, 6)
    for flags in (cv2.IMREAD_COLOR, cv2.IMREAD_GRAYSCALE):
        # Reference: OpenCV's decode of the same stream without the tag.
        expected = cv2.imdecode(np.frombuffer(plain, np.uint8), flags)
        assert cv2.imdecode(np.frombuffer(tagged, np.uint8), flags).shape[:2] == (50, 30)  # OpenCV's default rotates
        np.testing.assert_array_equal(decode_image(tagged, "x", flags), expected)

    # Through the THuman4 reader: a tagged training image of a 96x80 camera, its mask untagged.
    root = write_thuman4(tmp_path / "s", cameras=2, frames=2)
    path = root / "images" / "cam00" / "00000001.jpg"
    stored = path.read_bytes()
    path.write_bytes(_exif_orientation(stored, 6))
    expected = cv2.cvtColor(cv2.imdecode(np.frombuffer(stored, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(Thuman4Capture(root).read_image("cam00", 1), expected)


# -- item 4: a camera inside the subject -------------------------------------------------------------------------

def test_a_camera_moved_inside_the_subject_fails_the_projection_check(tmp_path, capsys):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=3)
    calibration = json.loads((root / "calibration.json").read_text())
    # Inside the 0.2 m capsule, 0.1 m from its axis, looking out through the near wall: the body covers the image,
    # the median depth is centimetres, and an unbounded tolerance of f * 0.05 m / z covered the whole image.
    R, T = look_at(np.array([0.0, 0.3, 0.1]), (0.0, 0.3, 5.0))
    calibration["cam00"].update(R=R.tolist(), T=T.tolist())
    (root / "calibration.json").write_text(json.dumps(calibration))
    assert _preprocess(root, tmp_path / "out") == 1
    err = capsys.readouterr().err
    found = {float(tol): float(raw) for tol, raw in
             [m.split(" (raw ") for m in err.split("cameras (cam00 ")[1].split(")")[:1]]}
    (tolerant, plain), = found.items()
    assert plain < 0.1 and tolerant < 0.9 and "cameras and the body parameters disagree" in err


# -- item 8: YAML alias bomb, deep nesting -----------------------------------------------------------------------

def test_yaml_alias_bomb_and_deep_nesting_are_refused_naming_the_file(tmp_path):
    levels = [f"l0: &l0 [{', '.join(['lol'] * 9)}]"]
    levels += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, 9)]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(levels) + "\n")  # 9^9 = 387 M values when expanded
    with pytest.raises(ConfigError, match=rf"^{bomb}: YAML aliases expand the document to [\d,]+ values, more than"):
        load_preset(bomb)
    deep = tmp_path / "deep.yaml"
    deep.write_text("fit: " + "[" * 1000 + "]" * 1000 + "\n")
    with pytest.raises(ConfigError, match=rf"^{deep}: values nested too deeply"):
        load_yaml(deep)
    # Ordinary aliases still expand as PyYAML's own loader expands them.
    small = tmp_path / "small.yaml"
    small.write_text("base: &b {x: 1, y: [1, 2]}\na: *b\nb: {<<: *b, y: 3}\n")
    import yaml
    assert load_yaml(small) == yaml.safe_load(small.read_text())


# -- item 9: npz members -----------------------------------------------------------------------------------------

def _forged_npy(shape, descr="<f8", payload=b"\0" * 16) -> bytes:
    """A .npy whose header declares `shape` but holds only `payload`."""
    import io
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False, "shape": shape})
    return buffer.getvalue() + payload


def test_npz_members_never_used_are_not_read_and_declared_sizes_are_checked(tmp_path):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=3)
    params = root / "smpl_params.npz"
    reference = np.load(params)  # the file as numpy reads it, before the unused member is added
    with zipfile.ZipFile(params, "a", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("unused.npy", _forged_npy((1, 10 ** 12)))  # declares 8 TB
    capture = Thuman4Capture(root)
    np.testing.assert_array_equal(capture.params.transl, reference["transl"])

    # A member that is read declares more than the archive stores for it, or more than the bound.
    arrays = dict(reference)
    np.savez(params, **{k: v for k, v in arrays.items() if k != "transl"})
    with zipfile.ZipFile(params, "a") as archive:
        archive.writestr("transl.npy", _forged_npy((1, 10 ** 12)))
    with pytest.raises(CaptureError, match=rf"{params}: member 'transl' declares shape \(1, 1000000000000\) of "
                                           r"float64 \(8,000,000,000,000 bytes\), more than the"):
        Thuman4Capture(root)
    np.savez(params, **{k: v for k, v in arrays.items() if k != "transl"})
    with zipfile.ZipFile(params, "a") as archive:
        archive.writestr("transl.npy", _forged_npy((3, 3), payload=b"\0" * 16))  # 72 bytes declared, 16 stored
    with pytest.raises(CaptureError, match=r"member 'transl' declares shape \(3, 3\) of float64 \(72 bytes\) but the "
                                           r"archive stores 16 bytes"):
        Thuman4Capture(root)


# -- items 10 and 13: HDF5 ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def smc(tmp_path_factory):
    """A tiny DNA-Rendering sequence written from a THuman4 fixture subject."""
    from pig.data.smc_writer import write_smc

    tmp = tmp_path_factory.mktemp("smc")
    root = write_thuman4(tmp / "s", cameras=2, frames=2, ext="png")
    return write_smc(Thuman4Capture(root), tmp / "dna", "0007_03", root / "body_model.npz")


def _copy_smc(smc, tmp_path) -> tuple[Path, Path]:
    main, annots = smc
    out = tmp_path / "dna"
    shutil.copytree(main.parent, out)
    return out / main.name, out / "annotations" / annots.name


def test_hdf5_external_links_and_external_storage_are_refused(smc, tmp_path):
    from pig.data.dna import DnaCapture

    main, annots = _copy_smc(smc, tmp_path)
    with h5py.File(annots, "r") as handle:
        transl = handle["SMPLx/transl"][()]
    outside = tmp_path / "outside.h5"
    with h5py.File(outside, "w") as handle:
        handle["transl"] = transl + 5.0  # values a followed link would bring in
    with h5py.File(annots, "a") as handle:
        del handle["SMPLx/transl"]
        handle["SMPLx/transl"] = h5py.ExternalLink(str(outside), "/transl")
    with pytest.raises(CaptureError, match=r"_annots\.smc:/SMPLx/transl: an external link to .*outside\.h5:/transl; "
                                           "links out of the file are not followed"):
        DnaCapture(main.parent, "0007_03")

    main, annots = _copy_smc(smc, tmp_path / "storage")
    png = cv2.imencode(".png", np.full((80, 96, 3), 7, np.uint8))[1].tobytes()
    (tmp_path / "elsewhere.png").write_bytes(png)  # a decodable image: followed storage would read it silently
    with h5py.File(main, "a") as handle:
        del handle["Camera_5mp/1/color/1"]
        handle.create_dataset("Camera_5mp/1/color/1", shape=(len(png),), dtype=np.uint8,
                              external=[(str(tmp_path / "elsewhere.png"), 0, len(png))])
    with DnaCapture(main.parent, "0007_03") as dna:
        dna.read_image("1", 0)
        with pytest.raises(CaptureError, match=r"0007_03\.smc:/Camera_5mp/1/color/1: the dataset's values are stored "
                                               "in other files"):
            dna.read_image("1", 1)


def test_hdf5_datasets_never_used_are_not_read_and_declared_shapes_are_checked(smc, tmp_path):
    from pig.data.dna import DnaCapture

    main, annots = _copy_smc(smc, tmp_path)
    with h5py.File(annots, "r") as handle:
        transl = handle["SMPLx/transl"][()]
    huge = dict(shape=(10 ** 12,), dtype=np.float64, chunks=(1024,))  # declared 8 TB, nothing stored
    with h5py.File(annots, "a") as handle:
        handle.create_dataset("SMPLx/unused", **huge)
    with DnaCapture(main.parent, "0007_03") as dna:  # the unused dataset is never read
        np.testing.assert_array_equal(dna._file_params.transl, transl)
    with h5py.File(annots, "a") as handle:
        del handle["SMPLx/transl"]
        handle.create_dataset("SMPLx/transl", shape=(10 ** 12, 3), dtype=np.float64, chunks=(1024, 3))
    with pytest.raises(CaptureError, match=r"_annots\.smc:/SMPLx/transl: declares shape \(1000000000000, 3\) "
                                           r"\(3,000,000,000,000 values\), more than the 800 expected"):
        DnaCapture(main.parent, "0007_03")

    main, _ = _copy_smc(smc, tmp_path / "image")
    with h5py.File(main, "a") as handle:
        del handle["Camera_5mp/0/color/1"]
        handle.create_dataset("Camera_5mp/0/color/1", shape=(10 ** 12,), dtype=np.uint8, chunks=(4096,))
    with DnaCapture(main.parent, "0007_03") as dna:
        with pytest.raises(CaptureError, match=r"0007_03\.smc:/Camera_5mp/0/color/1: 1,000,000,000,000 encoded bytes, "
                                               r"more than an image of at most 7,680 pixels takes"):
            dna.read_image("0", 1)


# -- item 11: declared image sizes -------------------------------------------------------------------------------

def _png_declaring(width: int, height: int) -> bytes:
    """A complete grey PNG whose IHDR declares width x height but whose data holds one row."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * (width + 1)))
            + chunk(b"IEND", b""))


def _jpeg_declaring(width: int, height: int) -> bytes:
    """A small real JPEG whose start-of-frame header is rewritten to declare width x height."""
    data = bytearray(cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def _webp_declaring(width: int, height: int) -> bytes:
    """A small real WebP with alpha whose VP8X chunk is rewritten to declare a width x height canvas."""
    data = bytearray(cv2.imencode(".webp", np.zeros((8, 8, 4), np.uint8), [cv2.IMWRITE_WEBP_QUALITY, 80])[1].tobytes())
    assert data[12:16] == b"VP8X"
    data[24:30] = (width - 1).to_bytes(3, "little") + (height - 1).to_bytes(3, "little")
    return bytes(data)


def test_declared_image_size_is_read_from_the_header_and_bounded_before_decoding(tmp_path):
    for forged in (_png_declaring(30000, 30000), _jpeg_declaring(30000, 30000), _webp_declaring(30000, 30000)):
        with pytest.raises(CaptureError, match=r"^big: the image header declares 30000x30000 \(WxH\) pixels, more "
                                               r"than the 100,000,000 expected here; not decoded"):
            decode_image(forged, "big")
    # A capture's reader bounds by its camera: 96 x 80 = 7,680 pixels.
    root = write_thuman4(tmp_path / "s", cameras=2, frames=2, ext="png")
    path = root / "masks" / "cam01" / "00000001.png"
    path.write_bytes(_png_declaring(200, 200))
    with pytest.raises(CaptureError, match=rf"{path}: the image header declares 200x200 \(WxH\) pixels, more than "
                                           r"the 7,680 expected here"):
        Thuman4Capture(root).read_mask("cam01", 1)

    from pig.data.images import declared_size

    rng = np.random.default_rng(1)
    for ext, channels, params in ((".png", 3, []), (".jpg", 3, []), (".webp", 3, [cv2.IMWRITE_WEBP_QUALITY, 101]),
                                  (".webp", 3, [cv2.IMWRITE_WEBP_QUALITY, 80]), (".webp", 4, [cv2.IMWRITE_WEBP_QUALITY, 80])):
        # the header parser against OpenCV's decoded shape (WebP: lossless VP8L, lossy VP8, lossy with alpha VP8X)
        image = rng.integers(0, 256, (37, 53, channels), dtype=np.uint8)
        data = cv2.imencode(ext, image, params)[1].tobytes()
        assert declared_size(data) == (53, 37) == cv2.imdecode(np.frombuffer(data, np.uint8), 1).shape[1::-1]
    assert declared_size(_png_declaring(30000, 20000)) == declared_size(_jpeg_declaring(30000, 20000)) == (30000, 20000)
    assert declared_size(_webp_declaring(30000, 20000)) == (30000, 20000)


# -- item 12: inputs that are not regular files ------------------------------------------------------------------

def _unblock_later(fifo: Path) -> None:
    """Open the FIFO for writing after a while, so that code which wrongly opens it for reading gets an end of file
    instead of hanging; with no reader the open fails (ENXIO) and nothing happens."""
    def release():
        time.sleep(3)
        try:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:
            pass

    threading.Thread(target=release, daemon=True).start()


def test_fifos_and_devices_as_inputs_are_refused_naming_the_file(tmp_path):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=2)
    image = root / "images" / "cam00" / "00000001.jpg"
    image.unlink()
    os.mkfifo(image)
    _unblock_later(image)
    capture = Thuman4Capture(root)
    with pytest.raises(CaptureError, match=rf"^{image}: is a FIFO \(named pipe\), not a regular file"):
        capture.read_image("cam00", 1)
    mask = root / "masks" / "cam01" / "00000000.jpg"
    mask.unlink()
    mask.symlink_to("/dev/zero")
    with pytest.raises(CaptureError, match=rf"^{mask}: is a character device, reached through a link to /dev/zero, "
                                           "not a regular file"):
        capture.read_mask("cam01", 0)
    for name in ("smpl_params.npz", "calibration.json"):
        shutil.copytree(root, tmp_path / name, ignore=shutil.ignore_patterns("00000001.jpg", "00000000.jpg"))
        target = tmp_path / name / name
        target.unlink()
        target.symlink_to("/dev/zero")
        with pytest.raises(CaptureError, match=rf"{target}: is a character device"):
            Thuman4Capture(tmp_path / name)
    preset = tmp_path / "preset.yaml"
    os.mkfifo(preset)
    _unblock_later(preset)
    with pytest.raises(ConfigError, match=rf"^{preset}: is a FIFO"):
        load_preset(preset)


# -- weak group: preset values -----------------------------------------------------------------------------------

def _section_classes():
    from pig.avatar.config import AvatarConfig
    from pig.avatar.training import FitConfig
    from pig.stages.evaluate import EvaluateConfig
    from pig.stages.preprocess import PreprocessConfig

    return {"preprocess": PreprocessConfig, "fit": FitConfig, "avatar": AvatarConfig, "evaluate": EvaluateConfig}


BAD_VALUES = {  # key -> values refused; each stands in for a crash deep inside a stage in the sweep
    ("preprocess", "scale"): [".nan", ".inf", "0", "-1"],
    ("preprocess", "max_side"): ["0", "-5", "1"],
    ("preprocess", "min_iou"): [".nan", "0", "-0.5", "1.5"],
    ("preprocess", "check_frames"): ["0", "-2"],
    ("fit", "views"): ["0", "-1"],
    ("fit", "eval_every"): ["0"],
    ("fit", "iterations"): ["-5", "0"],
    ("avatar", "hidden_width"): ["0", "1000000"],
    ("avatar", "num_anchors"): ["0", "1e12"],
    ("evaluate", "batch_size"): ["0"],
    ("evaluate", "timing_frames"): ["-3", "0"],
}


@pytest.mark.parametrize("section, key, value", [(s, k, v) for (s, k), vs in BAD_VALUES.items() for v in vs])
def test_out_of_range_preset_values_are_refused_naming_file_and_key(tmp_path, section, key, value):
    path = tmp_path / "preset.yaml"
    path.write_text(f"{section}:\n  {key}: {value}\n")
    with pytest.raises(ConfigError, match=rf"^{path}: section '{section}'\.{key}: expected (an integer|a finite "
                                          r"number) (above|at least) "):
        load_section(load_preset(path), section, _section_classes()[section])


def test_the_shipped_presets_load_and_in_range_values_pass(tmp_path):
    classes = _section_classes()
    for name in ("test", "cpu-demo", "paper"):
        preset = load_preset(name)
        for section, cls in classes.items():
            load_section(preset, section, cls)
    path = tmp_path / "preset.yaml"
    path.write_text("preprocess: {scale: 0.5, max_side: 16, min_iou: 1.0, check_frames: 1}\n")
    cfg = load_section(load_preset(path), "preprocess", classes["preprocess"])
    assert (cfg.scale, cfg.max_side, cfg.min_iou, cfg.check_frames) == (0.5, 16, 1.0, 1)


def test_preprocess_with_a_nan_scale_names_the_preset_and_key(tmp_path, capsys):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=3)
    preset = tmp_path / "preset.yaml"
    preset.write_text("preprocess:\n  scale: .nan\n")
    assert run_cli(preprocess_main, ["--input", str(root), "--output", str(tmp_path / "out"), "--preset", str(preset),
                                     "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert f"{preset}: section 'preprocess'.scale: expected a finite number above 0, found nan" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, option", [(["--fps", "0"], "--fps"), (["--fps", "nan"], "--fps"),
                                          (["--size", "0", "-5"], "--size"), (["--size", "100000", "100"], "--size"),
                                          (["--seconds", "1e12"], "--seconds"), (["--seconds", "-1"], "--seconds")])
def test_animate_refuses_out_of_range_fps_size_and_seconds(tmp_path, capsys, args, option):
    from pig.stages.animate import main as animate_main

    with pytest.raises(SystemExit) as exit_info:
        animate_main(["--checkpoint", str(tmp_path / "avatar.pt"), "--output", str(tmp_path / "anim"), *args])
    assert exit_info.value.code == 2
    assert f"argument {option}: expected a finite value" in capsys.readouterr().err
    assert not (tmp_path / "anim").exists()


# -- weak group: wrong failure blamed ----------------------------------------------------------------------------

def test_masks_saved_as_0_1_are_named_not_the_calibration(tmp_path, capsys):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=3, ext="png")
    for path in sorted((root / "masks").rglob("*.png")):
        cv2.imwrite(str(path), (cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127).astype(np.uint8))
    assert _preprocess(root, tmp_path / "out") == 1
    err = capsys.readouterr().err
    assert "masks/cam00/00000000.png: the mask's largest value is 1, so no pixel counts as the person" in err
    assert "multiply it by 255" in err and "calibration" not in err


def test_all_black_masks_are_named_not_the_calibration(tmp_path, capsys):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=3, ext="png")
    for path in (root / "masks" / "cam02").glob("*.png"):
        cv2.imwrite(str(path), np.zeros((80, 96), np.uint8))
    assert _preprocess(root, tmp_path / "out") == 1
    err = capsys.readouterr().err
    assert (f"{root}: the masks are empty (all black, no pixel above 128) in every frame checked for 1 of 3 cameras "
            "(camera cam02, frames [0, 1, 2])") in err
    assert "calibration" not in err


# -- weak group: numpy's messages --------------------------------------------------------------------------------

def test_a_garbage_body_model_in_a_checkpoint_spec_never_shows_numpys_pickle_advice():
    from pig.avatar.build import build_avatar

    for garbage in (b"\0" * 100, b"PK\x03\x04" + b"\0" * 96):
        with pytest.raises(ValueError) as info:
            build_avatar({"avatar": {}, "field": {}, "precond": {}, "body_model_npz": garbage})
        assert str(info.value).startswith("body model of the avatar spec: not a valid npz archive")
        assert "pickle" not in str(info.value)


def test_a_body_model_that_is_a_fifo_is_named_as_one(tmp_path):
    from pig.body.model import BodyModel, BodyModelError

    fifo = tmp_path / "SMPLX_NEUTRAL.npz"
    os.mkfifo(fifo)
    _unblock_later(fifo)
    with pytest.raises(BodyModelError, match=rf"^{fifo}: is a FIFO \(named pipe\), not a regular file; expected an "
                                             "SMPL-X model"):
        BodyModel.from_file(fifo)


def test_an_exr_declaring_a_huge_data_window_is_refused_before_reading(tmp_path):
    from pig.data.exr import read_exr, write_exr

    path = tmp_path / "depth.exr"
    values = np.arange(35, dtype=np.float32).reshape(5, 7)
    write_exr(path, {"Z": values})
    np.testing.assert_array_equal(read_exr(path)["Z"], values)
    data = bytearray(path.read_bytes())
    window = data.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4  # after the attribute's size
    data[window:window + 16] = struct.pack("<4i", 0, 0, 29999, 29999)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=rf"^{path}: the EXR header declares a 30000x30000 \(WxH\) data window, not 1 "
                                         r"to 100,000,000 pixels; not read"):
        read_exr(path)
