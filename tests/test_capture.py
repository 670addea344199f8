"""Preprocessed-capture loader: reads back what preprocess wrote (checked against OpenCV's own undistortion),
caches decoded frames, and names the file on every malformed input."""
from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import torch

from thuman4_fixture import write_thuman4

from pig.body.model import BodyModel
from pig.body.params import from_thuman
from pig.data.capture import Capture
from pig.data.raw import CaptureError
from pig.data.rectify import Rectifier, scaled_intrinsics
from pig.data.thuman4 import Thuman4Capture
from pig.stages.preprocess import main


@pytest.fixture(scope="module")
def preprocessed(tmp_path_factory):
    """Raw tiny subject (cam01 frame 3 listed missing) and its preprocessed capture at scale 0.5 on white."""
    tmp = tmp_path_factory.mktemp("capture")
    raw = write_thuman4(tmp / "raw", cameras=3, frames=4, width=192, height=160, ext="png",
                        missing=["images\\cam01\\00000003.png"])
    preset = tmp / "preset.yaml"
    preset.write_text("preprocess:\n  scale: 0.5\n  background: [1.0, 1.0, 1.0]\n")
    dataset = tmp / "dataset.yaml"
    dataset.write_text("name: tiny\nsplit:\n  novel_view_cameras: [cam02]\n  novel_pose_frames: [3, 3]\n")
    assert main(["--input", str(raw), "--output", str(tmp / "out"), "--preset", str(preset),
                 "--dataset", str(dataset), "--no-progress"]) == 0
    return raw, tmp / "out"


def test_cameras_params_and_split_round_trip(preprocessed):
    raw_root, out = preprocessed
    raw = Thuman4Capture(raw_root)
    capture = Capture.load(out)
    assert list(capture.cameras) == ["cam00", "cam01", "cam02"]
    for name, cam in capture.cameras.items():
        source = raw.cameras[name]
        assert (cam.width, cam.height) == (96, 80)
        expected = source.K.copy()
        expected[:2, :2] *= 0.5
        expected[:2, 2] = (source.K[:2, 2] + 0.5) * 0.5 - 0.5
        np.testing.assert_allclose(cam.K, expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(cam.K, scaled_intrinsics(source.K, 0.5, 0.5))
        np.testing.assert_array_equal(cam.R, source.R)
        point = np.array([0.1, -0.3, 0.2])
        np.testing.assert_allclose((cam.viewmat() @ np.append(point, 1))[:3], source.R @ point + source.T)
        np.testing.assert_allclose(cam.center, -source.R.T @ source.T)
    assert capture.frames == [0, 1, 2, 3]
    reference = from_thuman(dict(np.load(raw_root / "smpl_params.npz")), "ref")
    np.testing.assert_array_equal(capture.params.full_pose, reference.full_pose)
    np.testing.assert_array_equal(capture.params.transl, reference.transl)
    np.testing.assert_array_equal(capture.params.betas, reference.betas)
    assert capture.frame_index(2) == 2
    assert capture.split == {"train": {"cameras": ["cam00", "cam01"], "frames": [0, 1, 2]},
                             "novel_view": {"cameras": ["cam02"], "frames": [0, 1, 2]},
                             "novel_pose": {"cameras": ["cam00", "cam01", "cam02"], "frames": [3]}}
    assert not capture.has("cam01", 3) and capture.has("cam00", 3)
    assert capture.views("novel_pose") == [("cam00", 3), ("cam02", 3)]
    model = capture.body_model()
    assert isinstance(model, BodyModel)
    np.testing.assert_array_equal(model.faces.numpy(), np.load(raw_root / "body_model.npz")["f"])
    np.testing.assert_allclose(capture.background, [1, 1, 1])


def test_images_and_masks_match_opencv_undistort_then_area_resize(preprocessed):
    """Reference: cv2.undistort (its own maps) + binarise + composite + INTER_AREA, computed here independently.
    On held-out views, which are lossless (the JPEG training views: test_training_views_are_jpeg_...)."""
    raw_root, out = preprocessed
    raw = Thuman4Capture(raw_root)
    capture = Capture.load(out)
    for cam, frame in (("cam02", 0), ("cam00", 3)):
        source = raw.cameras[cam]
        image = cv2.undistort(raw.read_image(cam, frame), source.K, source.dist)
        matte = cv2.undistort(raw.read_mask(cam, frame), source.K, source.dist)
        white = np.where((matte > 128)[..., None], image, 255).astype(np.uint8)
        small = cv2.resize(white, (96, 80), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
        mask = capture.mask(cam, frame)
        reference_mask = cv2.resize((matte > 128).astype(np.float32), (96, 80), interpolation=cv2.INTER_AREA) >= 0.5
        # Bilinear vs nearest resampling of the matte may flip boundary pixels only.
        assert np.count_nonzero(mask != reference_mask) <= 0.1 * np.count_nonzero(reference_mask)
        assert mask.sum() > 50
        got = capture.image(cam, frame)
        assert got.dtype == np.float32 and got.shape == (80, 96, 3)
        both = mask & reference_mask
        inner = cv2.erode(both.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        np.testing.assert_allclose(got[inner], small[inner], atol=3 / 255)
        np.testing.assert_array_equal(got[~mask], 1.0)  # composited on the configured white
        black = capture.image(cam, frame, background=(0, 0, 0))
        np.testing.assert_array_equal(black[~mask], 0.0)
        np.testing.assert_array_equal(black[mask], got[mask])


def _lossless(raw_root, cam, frame):
    """The preprocess output before encoding: uint8 RGB on white and the mask (scale 0.5, as the fixture)."""
    raw = Thuman4Capture(raw_root)
    return Rectifier(raw.cameras[cam], 96, 80)(raw.read_image(cam, frame), raw.read_mask(cam, frame),
                                               np.full(3, 255, np.uint8))


def test_training_views_are_jpeg_read_back_on_the_exact_background(preprocessed):
    raw_root, out = preprocessed
    capture = Capture.load(out)
    for cam, frame in capture.views("train"):
        assert (out / "images" / cam / f"{frame:08d}.jpg").is_file()
        expected, expected_mask = _lossless(raw_root, cam, frame)
        mask = capture.mask(cam, frame)
        np.testing.assert_array_equal(mask, expected_mask)
        got = capture.image(cam, frame)
        np.testing.assert_array_equal(got[~mask], 1.0)  # JPEG ringing outside the silhouette is undone
        error = got[mask] * 255 - expected[mask]
        assert 0 < np.abs(error).max() and 10 * np.log10(255**2 / np.mean(error**2)) > 30  # lossy, but close
    for cam, frame in capture.views("novel_view") + capture.views("novel_pose"):
        expected, _ = _lossless(raw_root, cam, frame)
        np.testing.assert_array_equal(np.round(capture.image(cam, frame) * 255), expected)  # held out: exact


def test_an_all_png_capture_of_earlier_versions_reads_the_same(preprocessed, tmp_path):
    """Earlier preprocess versions wrote every image as PNG and masks as 8-bit PNG."""
    raw_root, out = preprocessed
    old = tmp_path / "old"
    shutil.copytree(out, old)
    for jpeg in old.glob("images/*/*.jpg"):
        image, _ = _lossless(raw_root, jpeg.parent.name, int(jpeg.stem))
        cv2.imwrite(str(jpeg.with_suffix(".png")), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        jpeg.unlink()
    for mask in old.glob("masks/*/*.png"):
        cv2.imwrite(str(mask), cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE))  # 8 bits per pixel
        assert mask.read_bytes()[24] == 8
    capture, new = Capture.load(old), Capture.load(out)
    assert capture.views("train") == new.views("train") and len(capture.views("train")) == 6
    for cam, frame in capture.views("train") + capture.views("novel_pose"):
        expected, expected_mask = _lossless(raw_root, cam, frame)
        np.testing.assert_array_equal(np.round(capture.image(cam, frame) * 255), expected)
        np.testing.assert_array_equal(capture.mask(cam, frame), expected_mask)


def test_fingerprint_covers_the_jpeg_training_views(preprocessed, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(preprocessed[1], copy)
    reference = Capture.load(copy).fingerprint()
    image = copy / "images" / "cam00" / "00000001.jpg"
    image.write_bytes(image.read_bytes() + b"\0")
    found = Capture.load(copy).fingerprint()
    assert sorted(k for k in reference if found[k] != reference[k]) == ["images"]


def test_decoded_frames_are_cached_within_the_budget(preprocessed, tmp_path):
    _, out = preprocessed
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    capture = Capture.load(copy)
    first = capture.image("cam00", 1)
    capture.preload(workers=2)
    shutil.rmtree(copy / "images")  # from now on only the cache can answer
    np.testing.assert_array_equal(capture.image("cam00", 1), first)
    assert capture.mask("cam02", 3).any()
    small = Capture.load(out, cache_mb=30_000 / 2**20)  # room for about one 96x80 RGB frame and a mask
    for cam, frame in small.views("train"):
        small.image(cam, frame)
        small.mask(cam, frame)
    assert small._cache_bytes <= 30_000
    fresh = Capture.load(out)
    np.testing.assert_array_equal(small.image("cam00", 0), fresh.image("cam00", 0))  # evicted, read again


def _broken(out, tmp_path, edit):
    copy = tmp_path / "broken"
    shutil.copytree(out, copy)
    edit(copy)
    return copy


def _edit_json(name, change):
    def edit(root):
        data = json.loads((root / name).read_text())
        change(data)
        (root / name).write_text(json.dumps(data))
    return edit


BAD = {
    "no cameras.json": (lambda r: (r / "cameras.json").unlink(), r"cameras\.json: file not found"),
    "cameras.json garbage": (lambda r: (r / "cameras.json").write_text("{"), r"cameras\.json: not valid JSON"),
    "K of 2x3": (_edit_json("cameras.json", lambda d: d["cam01"].__setitem__("K", [[1, 0, 0], [0, 1, 0]])),
                 r"cameras\.json: camera 'cam01' 'K' must be finite with shape \(3, 3\)"),
    "no width": (_edit_json("cameras.json", lambda d: d["cam00"].pop("width")), r"camera 'cam00' must have keys"),
    "no smplx.npz": (lambda r: (r / "smplx.npz").unlink(), r"smplx\.npz: body parameter file not found"),
    "split unknown camera": (_edit_json("split.json", lambda d: d["train"]["cameras"].append("cam07")),
                             r"split\.json: split 'train' names camera\(s\) \['cam07'\] not in cameras\.json"),
    "split unknown frame": (_edit_json("split.json", lambda d: d["novel_pose"]["frames"].append(9)),
                            r"split\.json: split 'novel_pose' names frame\(s\) \[9\] that smplx\.npz has no parameters"),
    "split with no novel-view camera": (_edit_json("split.json", lambda d: d["novel_view"].update(cameras=[])),
                                        r"split\.json: split 'novel_view' is empty \(0 cameras, \d+ frames\); rerun preprocess"),
    "split with no novel-pose frame": (_edit_json("split.json", lambda d: d["novel_pose"].update(frames=[])),
                                       r"split\.json: split 'novel_pose' is empty \(\d+ cameras, 0 frames\)"),
    "split without novel_view": (_edit_json("split.json", lambda d: d.pop("novel_view")),
                                 r"split\.json: expected 'novel_view'"),
    "no report.json": (lambda r: (r / "report.json").unlink(), r"report\.json: file not found"),
    "a frame as .jpg and .png": (
        lambda r: shutil.copyfile(r / "images" / "cam00" / "00000001.jpg", r / "images" / "cam00" / "00000001.png"),
        r"images/cam00: frame 1 has two files, 00000001\.(jpg and 00000001\.png|png and 00000001\.jpg); a capture "
        r"holds one per frame"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_capture_fails_naming_the_file(preprocessed, tmp_path, case):
    edit, message = BAD[case]
    with pytest.raises(CaptureError, match=message):
        Capture.load(_broken(preprocessed[1], tmp_path, edit))


def test_bad_frame_access_names_the_file(preprocessed, tmp_path):
    with pytest.raises(CaptureError, match=r"capture .*nothing not found \(run the preprocess stage"):
        Capture.load(tmp_path / "nothing")
    copy = _broken(preprocessed[1], tmp_path, lambda r: (r / "images" / "cam00" / "00000002.jpg").write_bytes(b"x"))
    capture = Capture.load(copy)
    with pytest.raises(CaptureError, match=r"images/cam00/00000002\.jpg: image bytes could not be decoded"):
        capture.image("cam00", 2)
    with pytest.raises(CaptureError, match=r"images/cam01/00000003\.png or \.jpg: not in the capture"):
        capture.image("cam01", 3)
    with pytest.raises(CaptureError, match=r"unknown camera 'cam9'"):
        capture.mask("cam9", 0)
    with pytest.raises(CaptureError, match=r"no split 'test'"):
        capture.views("test")
    with pytest.raises(CaptureError, match=r"no parameters for frame 7"):
        capture.frame_index(7)
    cv2.imwrite(str(copy / "masks" / "cam00" / "00000001.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(CaptureError, match=r"masks/cam00/00000001\.png: image is 10x10, cameras\.json says 96x80"):
        capture.mask("cam00", 1)


def test_truncated_image_or_mask_names_the_file_also_when_preloading(preprocessed, tmp_path):
    """A file cut short after preprocess (a partial copy) is found when the fit, render or evaluate stage reads it."""
    def cut(root):
        for path in (root / "images" / "cam02" / "00000001.png", root / "masks" / "cam00" / "00000003.png"):
            data = path.read_bytes()
            path.write_bytes(data[:len(data) * 3 // 4])
    capture = Capture.load(_broken(preprocessed[1], tmp_path, cut))
    with pytest.raises(CaptureError, match=r"images/cam02/00000001\.png: truncated PNG \(\d+ bytes, no IEND chunk\)"):
        capture.image("cam02", 1)
    with pytest.raises(CaptureError, match=r"masks/cam00/00000003\.png: truncated PNG"):
        capture.mask("cam00", 3)
    with pytest.raises(CaptureError, match=r"(images/cam02/00000001|masks/cam00/00000003)\.png: truncated PNG"):
        capture.preload()
    assert capture.image("cam02", 0).shape == (80, 96, 3)


def test_body_model_poses_onto_the_masks(preprocessed):
    """The saved parameters and body model reproduce the check: the posed body projects inside the masks."""
    capture = Capture.load(preprocessed[1])
    model = capture.body_model(torch.float64)
    assert model.dtype == torch.float64
    p = capture.params
    with torch.no_grad():
        vertices = model(torch.from_numpy(p.full_pose), torch.from_numpy(p.betas), torch.from_numpy(p.expression),
                         torch.from_numpy(p.transl)).vertices.numpy()
    for cam, frame in capture.views("train") + capture.views("novel_pose"):
        c = capture.cameras[cam]
        uvz = (vertices[capture.frame_index(frame)] @ c.R.T + c.T) @ c.K.T
        uv = np.round(uvz[:, :2] / uvz[:, 2:]).astype(int)
        mask = cv2.dilate(capture.mask(cam, frame).astype(np.uint8), np.ones((3, 3), np.uint8))
        assert mask[uv[:, 1], uv[:, 0]].mean() > 0.98
