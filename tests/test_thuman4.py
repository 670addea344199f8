"""THuman4 reader: every layout variant of FORMATS.md reads the same capture; every malformed input fails naming the file."""
from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from thuman4_fixture import body_params, ring_cameras, write_thuman4

from pig.data.formats import open_capture
from pig.data.raw import CaptureError
from pig.data.thuman4 import Thuman4Capture


@pytest.mark.parametrize("flat, ext, betas_rows", [(False, "jpg", 1), (True, "png", 5), (True, "jpg", 1)])
def test_variants_read_the_written_values(tmp_path, flat, ext, betas_rows):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=5, ext=ext, flat=flat, betas_rows=betas_rows)
    capture = open_capture("thuman4", root)
    assert isinstance(capture, Thuman4Capture)
    expected = ring_cameras(3, 96, 80)
    assert list(capture.cameras) == list(expected)  # file order kept
    for name, cam in capture.cameras.items():
        np.testing.assert_allclose(cam.K, expected[name]["K"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(cam.R, expected[name]["R"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(cam.T, expected[name]["T"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(cam.dist, expected[name]["dist"])
        assert (cam.width, cam.height) == (96, 80)
    params = body_params(5)
    assert capture.frames == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(capture.params.betas, params["betas"][0])
    np.testing.assert_allclose(capture.params.full_pose[:, 0], params["global_orient"])
    np.testing.assert_allclose(capture.params.transl, params["transl"])
    path = root / "images" / "cam01" / f"00000003.{ext}"
    np.testing.assert_array_equal(capture.read_image("cam01", 3), cv2.imread(str(path))[..., ::-1])
    mask = capture.read_mask("cam01", 3)
    assert mask.dtype == np.uint8 and mask.shape == (80, 96) and mask.max() > 128 and mask.min() < 128


@pytest.mark.parametrize("line", [r"images\cam01\00000002.jpg", "images/cam01/00000002.jpg",
                                  r"D:\THuman4\subject00\images\cam01\00000002.jpg", "cam01/00000002.jpg"])
def test_missing_image_lists_with_either_separator(tmp_path, line):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=4, missing=[line, r"images\cam00\00000000.jpg"])
    capture = Thuman4Capture(root)
    absent = {("cam01", 2), ("cam00", 0)}
    for cam in capture.cameras:
        for frame in capture.frames:
            assert capture.has_frame(cam, frame) == ((cam, frame) not in absent)
    with pytest.raises(CaptureError, match=r"cam01: no usable file for frame 2"):
        capture.read_image("cam01", 2)


def test_missing_mask_list_hides_the_frame_even_with_an_image(tmp_path):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=3)
    (root / "masks" / "cam00" / "00000001.jpg").unlink()
    (root / "missing_msk_files.txt").write_text("masks\\cam00\\00000001.jpg\n\n")
    capture = Thuman4Capture(root)
    assert not capture.has_frame("cam00", 1) and capture.has_frame("cam00", 2) and capture.has_frame("cam01", 1)


def _edit_calibration(root, edit):
    path = root / "calibration.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _edit_params(root, **changes):
    path = root / "smpl_params.npz"
    arrays = dict(np.load(path))
    arrays.update(changes)
    np.savez(path, **arrays)


def _set(key, value, cam="cam01"):
    return lambda root: _edit_calibration(root, lambda d: d[cam].__setitem__(key, value))


def _transpose_k(root):
    _edit_calibration(root, lambda d: d["cam00"].__setitem__("K", np.asarray(d["cam00"]["K"]).T.tolist()))


def _nan_transl(root):
    transl = body_params(4)["transl"]
    transl[2, 1] = np.nan
    _edit_params(root, transl=transl)


BAD_SUBJECTS = {
    "no calibration": (lambda r: (r / "calibration.json").unlink(), r"incomplete: missing .*calibration\.json"),
    "no params": (lambda r: (r / "smpl_params.npz").unlink(), r"incomplete: missing .*smpl_params\.npz"),
    "calibration not json": (lambda r: (r / "calibration.json").write_text("{cam00: "), r"calibration\.json: not valid JSON"),
    "empty calibration": (lambda r: (r / "calibration.json").write_text("{}"), r"calibration\.json: expected a non-empty"),
    "K of 8 numbers": (_set("K", list(range(8))), r"camera 'cam01': 'K' has shape \(8,\), expected 9 numbers"),
    "K transposed": (_transpose_k, r"camera 'cam00': 'K' must be .*looks transposed"),
    "R not a rotation": (_set("R", [[1, 0, 0], [0, 2, 0], [0, 0, 1]]), r"camera 'cam01': 'R' is not a rotation"),
    "R reflection": (_set("R", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]), r"camera 'cam01': 'R' is a reflection"),
    "T of 2": (_set("T", [0, 1]), r"camera 'cam01': 'T' has shape \(2,\), expected 3"),
    "NaN in T": (_set("T", [0, float("nan"), 1]), r"camera 'cam01': 'T' contains NaN"),
    "no distCoeff": (lambda r: _edit_calibration(r, lambda d: d["cam01"].pop("distCoeff")), r"missing key 'distCoeff'"),
    "distCoeff of 3": (_set("distCoeff", [0.1, 0, 0]), r"'distCoeff' must hold 4 or 5 or 8"),
    "imgSize of 3": (_set("imgSize", [96, 80, 3]), r"'imgSize' has shape \(3,\), expected 2"),
    "NaN in transl": (_nan_transl, r"smpl_params\.npz: 'transl' contains NaN .* \[2, 1\]"),
    "body_pose width": (lambda r: _edit_params(r, body_pose=np.zeros((4, 60))),
                        r"smpl_params\.npz: 'body_pose' has shape \(4, 60\), expected \(4, 63\)"),
    "transl rows": (lambda r: _edit_params(r, transl=np.zeros((3, 3))), r"'transl' has shape \(3, 3\), expected \(4, 3\)"),
    "betas rows": (lambda r: _edit_params(r, betas=np.zeros((2, 10))), r"'betas' has shape \(2, 10\)"),
    "params not npz": (lambda r: (r / "smpl_params.npz").write_bytes(b"not a zip"),
                       r"smpl_params\.npz: not a valid npz archive \(the file starts with b'not '\); expected SMPL-X"),
    "params truncated": (lambda r: (r / "smpl_params.npz").write_bytes((r / "smpl_params.npz").read_bytes()[:3000]),
                         r"smpl_params\.npz: not a valid npz archive \(truncated or corrupt"),
    "camera folder absent": (lambda r: shutil.rmtree(r / "masks" / "cam01"),
                             r"masks/cam01: camera folder not found, but .*calibration\.json lists camera 'cam01'"),
    "image folder absent": (lambda r: shutil.rmtree(r / "images" / "cam00"),
                            r"images/cam00: camera folder not found, but .*calibration\.json lists camera 'cam00'"),
    "uncalibrated camera folder": (lambda r: shutil.copytree(r / "images" / "cam01", r / "images" / "cam02"),
                                   r"images/cam02: camera folder not listed in .*calibration\.json \(uncalibrated "
                                   r"folder\(s\) in images/: \['cam02'\]; calibrated cameras: \['cam00', 'cam01'\]\)"),
    "uncalibrated mask folder": (lambda r: (r / "masks" / "cam7").mkdir(), r"masks/cam7: camera folder not listed in"),
    "distCoeff a string": (_set("distCoeff", "-0.12 0.03 0.001 -0.0015 0.0"),
                           r"calibration\.json: camera 'cam01': 'distCoeff' must hold 4 or 5 or 8 or 12 or 14 finite "
                           r"numbers \(OpenCV distortion\), found '-0\.12 0\.03"),
    "distCoeff of strings": (_set("distCoeff", ["-0.12", "0.03", "0", "0", "0"]),
                             r"camera 'cam01': 'distCoeff' must hold"),
    "distCoeff ragged": (_set("distCoeff", [[0.1, 0.0], [0.0]]), r"camera 'cam01': 'distCoeff' must hold"),
    "distCoeff null": (_set("distCoeff", None), r"camera 'cam01': 'distCoeff' must hold .* found None"),
    "K a string": (_set("K", "[[1, 0, 0], [0, 1, 0], [0, 0, 1]]"),
                   r"camera 'cam01': 'K' must be 9 numbers, found '\[\[1"),
    "T of strings": (_set("T", ["0", "1", "2"]), r"camera 'cam01': 'T' must be 3 numbers, found \['0', '1', '2'\]"),
    "imgSize a mapping": (_set("imgSize", {"w": 96, "h": 80}), r"camera 'cam01': 'imgSize' must be 2 numbers"),
    "image without params": (lambda r: (r / "images" / "cam01" / "00000004.jpg").write_bytes(
        (r / "images" / "cam01" / "00000000.jpg").read_bytes()), r"images/cam01: 1 frame\(s\) from 4 on have no body parameters.*disagree"),
    "image absent, not listed": (lambda r: (r / "images" / "cam00" / "00000002.jpg").unlink(),
                                 r"images/cam00: 1 of the 4 frames .* not listed in missing_img_files\.txt.*\[2\]"),
    "two files for a frame": (lambda r: (r / "images" / "cam00" / "00000001.png").write_bytes(b""),
                              r"images/cam00: two files for frame 1"),
    "missing list unknown camera": (lambda r: (r / "missing_img_files.txt").write_text("images/cam07/00000001.jpg\n"),
                                    r"missing_img_files\.txt:1: expected a path ending in <camera>/<frame>\.jpg"),
    "missing list garbage": (lambda r: (r / "missing_img_files.txt").write_text("\n\nnothing here\n"),
                             r"missing_img_files\.txt:3: expected a path"),
}


@pytest.mark.parametrize("case", sorted(BAD_SUBJECTS))
def test_malformed_subject_fails_naming_the_file(tmp_path, case):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=4)
    mutate, message = BAD_SUBJECTS[case]
    mutate(root)
    with pytest.raises(CaptureError, match=message):
        Thuman4Capture(root)


def test_missing_root_says_where_to_put_the_data(tmp_path):
    with pytest.raises(CaptureError, match=r"subject folder .*nowhere not found: put the subject there with images/camXX"):
        open_capture("thuman4", tmp_path / "nowhere")
    with pytest.raises(CaptureError, match=r"unknown capture format 'thuman5'; known formats: \[.*'thuman4'"):
        open_capture("thuman5", tmp_path)


def test_params_of_random_bytes_name_the_file_without_suggesting_pickles(tmp_path):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=4)
    (root / "smpl_params.npz").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(CaptureError, match=r"smpl_params\.npz: not a valid npz archive") as error:
        Thuman4Capture(root)
    assert "pickle" not in str(error.value) and "\n" not in str(error.value)


def _cut(path, fraction=0.75):
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * fraction)])


@pytest.mark.parametrize("ext", ["jpg", "png"])
def test_truncated_image_or_mask_is_an_error_naming_the_file(tmp_path, ext):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=3, width=192, height=160, ext=ext)
    _cut(root / "images" / "cam00" / f"00000001.{ext}")
    _cut(root / "masks" / "cam01" / f"00000002.{ext}")
    capture = Thuman4Capture(root)
    expected = "truncated or corrupt JPEG" if ext == "jpg" else "truncated PNG"
    with pytest.raises(CaptureError, match=rf"images/cam00/00000001\.{ext}: {expected}"):
        capture.read_image("cam00", 1)
    with pytest.raises(CaptureError, match=rf"masks/cam01/00000002\.{ext}: {expected}"):
        capture.read_mask("cam01", 2)
    assert capture.read_image("cam01", 2).shape == (160, 192, 3)  # the image beside the cut mask is fine


def test_unreadable_or_wrongly_sized_images_fail_on_read(tmp_path):
    root = write_thuman4(tmp_path / "s", cameras=2, frames=3)
    (root / "images" / "cam00" / "00000001.jpg").write_bytes(b"\xff\xd8 truncated")
    (root / "images" / "cam01" / "00000001.jpg").write_bytes(b"no image")
    cv2.imwrite(str(root / "masks" / "cam01" / "00000002.jpg"), np.zeros((40, 96), np.uint8))
    capture = Thuman4Capture(root)
    with pytest.raises(CaptureError, match=r"images/cam00/00000001\.jpg: truncated or corrupt JPEG"):
        capture.read_image("cam00", 1)
    with pytest.raises(CaptureError, match=r"images/cam01/00000001\.jpg: image bytes could not be decoded"):
        capture.read_image("cam01", 1)
    with pytest.raises(CaptureError, match=r"masks/cam01/00000002\.jpg: image is 96x40 \(WxH\), but calibration\.json "
                                           r"gives imgSize \[96, 80\]"):
        capture.read_mask("cam01", 2)
    with pytest.raises(CaptureError, match=r"unknown camera 'cam09'"):
        capture.read_image("cam09", 0)
