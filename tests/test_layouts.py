"""The EasyMocap, ActorsHQ and AvatarReX readers, with frame folders or one video a camera.

The synthetic subject is written into each layout by tests/layout_writers.py and read back: cameras, images,
masks and body parameters must equal the THuman4 reader's. Writer and reader could share a mistake, so each layout
also has a fixture worked out by hand (a camera whose projection of a known point is computed on paper), and
EasyMocap's YAML is read here with cv2.FileStorage directly. Hostile trees must fail with the file named.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from layout_writers import write_actorshq, write_avatarrex, write_easymocap
from pig.body.model import BodyModel
from pig.data.actorshq import ActorsHQCapture
from pig.data.avatarrex import AvatarReXCapture
from pig.data.easymocap import EasyMocapCapture
from pig.data.formats import open_capture, reader_options, subject_path
from pig.data.frame_sources import VideoFrames
from pig.data.ground_truth import TrueMeshes
from pig.data.raw import CaptureError
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.data.thuman4 import Thuman4Capture


def _generate(root: Path, distortion: float) -> Path:
    cfg = SyntheticConfig(cameras=3, frames=3, width=40, height=40, workers=1, distortion=distortion)
    return generate_capture(root, cfg, progress=False)


@pytest.fixture(scope="module")
def pinhole(tmp_path_factory):
    """The synthetic subject with pinhole cameras (ActorsHQ stores no distortion) and its THuman4 reading."""
    raw = _generate(tmp_path_factory.mktemp("pinhole") / "subject", 0.0)
    return raw, Thuman4Capture(raw)


@pytest.fixture(scope="module")
def distorted(tmp_path_factory):
    raw = _generate(tmp_path_factory.mktemp("distorted") / "subject", 1.0)
    return raw, Thuman4Capture(raw)


@pytest.fixture(scope="module")
def model(pinhole):
    return BodyModel.from_file(pinhole[0] / "body_model.npz", dtype=torch.float64)


def _open(layout: str, source: tuple, model: BodyModel, root: Path, video: bool):
    raw, thuman = source
    if layout == "easymocap":
        write_easymocap(thuman, root, model, components=0, video=video)
        return EasyMocapCapture(root, body_model=model)
    if layout == "actorshq":
        write_actorshq(thuman, root, video=video)
        return ActorsHQCapture(root)
    write_avatarrex(thuman, root, video=video)
    return AvatarReXCapture(root)


def _project(points: np.ndarray, cam) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(cam.R)
    return cv2.projectPoints(points, rvec, cam.T, cam.K, cam.dist)[0][:, 0]


@pytest.mark.parametrize("video", [False, True], ids=["frames", "video"])
@pytest.mark.parametrize("layout, source", [("easymocap", "distorted"), ("actorshq", "pinhole"),
                                            ("avatarrex", "distorted")])
def test_round_trip_equals_the_thuman4_reading(layout, source, video, request, model, tmp_path):
    raw, thuman = request.getfixturevalue(source)
    capture = _open(layout, (raw, thuman), model, tmp_path / layout, video)
    assert len(capture.cameras) == len(thuman.cameras)
    assert capture.frames == thuman.frames
    truth = TrueMeshes.load(raw / "gt_meshes.npz")
    with torch.no_grad():
        p = capture.params
        posed = model(torch.from_numpy(p.full_pose), torch.from_numpy(p.betas)[None], torch.from_numpy(p.expression),
                      torch.from_numpy(p.transl)).vertices.numpy()
    for (name, cam), (ref_name, ref) in zip(capture.cameras.items(), thuman.cameras.items()):
        assert (cam.width, cam.height) == (ref.width, ref.height)
        for key in ("K", "R", "T"):
            np.testing.assert_allclose(getattr(cam, key), getattr(ref, key), atol=1e-9, err_msg=f"{layout} {key}")
        np.testing.assert_allclose(cam.dist[:5], ref.dist[:5], atol=1e-12)
        for i, frame in enumerate(capture.frames):
            assert capture.has_frame(name, frame)
            np.testing.assert_array_equal(capture.read_image(name, frame), thuman.read_image(ref_name, frame))
            mask, ref_mask = capture.read_mask(name, frame), thuman.read_mask(ref_name, frame)
            if layout == "easymocap":  # stored as labels 0/1, read as any value above 0
                np.testing.assert_array_equal(mask > 128, ref_mask > 128)
            else:
                np.testing.assert_array_equal(mask, ref_mask)
            # The body posed by the read parameters, seen by the read camera, lands where the true body does.
            shift = _project(posed[i], cam) - _project(truth.body_vertices[i].astype(np.float64), ref)
            assert np.abs(shift).max() < 1.0
    np.testing.assert_allclose(capture.params.full_pose, thuman.params.full_pose, atol=1e-9)
    np.testing.assert_allclose(capture.params.transl, thuman.params.transl, atol=1e-9)
    np.testing.assert_allclose(capture.params.betas, thuman.params.betas, atol=1e-9)
    np.testing.assert_allclose(capture.params.expression, thuman.params.expression, atol=1e-9)
    if video:  # each camera's frames decoded once, in order
        assert all(source.restarts == 0 for source in capture._images.values() if isinstance(source, VideoFrames))


def test_easymocap_yaml_read_by_opencv_itself(distorted, model, tmp_path):
    """What the writer put in intri.yml / extri.yml means, to OpenCV (as EasyMocap reads it), the THuman4
    cameras; and the reader agrees."""
    raw, thuman = distorted
    root = write_easymocap(thuman, tmp_path / "seq", model, components=0)
    capture = EasyMocapCapture(root, body_model=model)
    intri = cv2.FileStorage(str(root / "intri.yml"), cv2.FILE_STORAGE_READ)
    extri = cv2.FileStorage(str(root / "extri.yml"), cv2.FILE_STORAGE_READ)
    names = [intri.getNode("names").at(i).string() for i in range(intri.getNode("names").size())]
    assert names == list(thuman.cameras) == list(capture.cameras)
    for name, ref in thuman.cameras.items():
        K = intri.getNode(f"K_{name}").mat()
        R = cv2.Rodrigues(extri.getNode(f"R_{name}").mat())[0]
        T = extri.getNode(f"T_{name}").mat()[:, 0]
        point = np.array([0.1, 0.9, -0.2])
        expected = ref.K @ (ref.R @ point + ref.T)
        seen = K @ (R @ point + T)
        np.testing.assert_allclose(seen[:2] / seen[2], expected[:2] / expected[2], atol=1e-6)
        np.testing.assert_allclose(capture.cameras[name].R, R, atol=1e-12)
        assert int(intri.getNode(f"W_{name}").real()) == ref.width == capture.cameras[name].width


def test_easymocap_hand_pca_and_sizes_from_the_images(distorted, model, tmp_path):
    """EasyMocap's default 87-value form (6 hand PCA values a hand), no W_/H_ (sizes from the images) and no
    Rot_: every joint but the hands as THuman4's, the hands the 6-component projection."""
    raw, thuman = distorted
    root = write_easymocap(thuman, tmp_path / "seq", model, components=6, sizes=False, rotation_matrix=False)
    capture = EasyMocapCapture(root, body_model=model)
    sizes = [(c.width, c.height) for c in capture.cameras.values()]
    assert sizes == [(c.width, c.height) for c in thuman.cameras.values()]
    body = np.r_[0:25]
    np.testing.assert_allclose(capture.params.full_pose[:, body], thuman.params.full_pose[:, body], atol=1e-9)
    np.testing.assert_allclose(capture.params.transl, thuman.params.transl, atol=1e-9)
    fit = json.loads((root / "smplx" / "000001.json").read_text())[0]
    left = np.asarray(fit["poses"][0][66:72])
    components = np.load(raw / "body_model.npz")["hands_componentsl"]
    np.testing.assert_allclose(capture.params.full_pose[1, 25:40].reshape(-1), left @ components[:6], atol=1e-12)


HAND_POINT = np.array([0.0, 0.1, 0.2])  # a world point; each hand fixture's camera sees it at (55, 27.5)
HAND_PIXEL = np.array([55.0, 27.5])
# By hand: the world-to-camera rotation is +90 degrees about y, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], and T = (0, 0, 2):
# x_cam = (0.2, 0.1, 0) + (0, 0, 2) = (0.2, 0.1, 2); fx = fy = 50, cx = 50, cy = 25 on a 100 x 50 image:
# u = 50 * 0.2 / 2 + 50 = 55, v = 50 * 0.1 / 2 + 25 = 27.5.


def _one_frame(folder: Path, image_name: str, mask_folder: Path, mask_name: str, mask_value=255) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    mask_folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / image_name), np.full((50, 100, 3), 90, np.uint8))
    mask = np.zeros((50, 100), np.uint8)
    mask[10:40, 30:70] = mask_value
    cv2.imwrite(str(mask_folder / mask_name), mask)


def _thuman_params_file(path: Path, frames: int = 1) -> None:
    zeros = lambda width: np.zeros((frames, width))  # noqa: E731
    np.savez(path, betas=np.zeros((1, 10)), global_orient=zeros(3), transl=zeros(3), body_pose=zeros(63),
             jaw_pose=zeros(3), expression=zeros(10), left_hand_pose=zeros(45), right_hand_pose=zeros(45))


def _sees_the_point_where_worked_out(capture) -> None:
    (cam,) = capture.cameras.values()
    x = cam.R @ HAND_POINT + cam.T
    np.testing.assert_allclose(cam.K[:2] @ (x / x[2]), HAND_PIXEL, atol=1e-9)
    assert (cam.width, cam.height) == (100, 50)


def test_actorshq_fixture_by_hand(tmp_path):
    """calibration.csv holds camera to world: the camera's axes are the world's turned by -90 degrees about y
    (Rodrigues (0, -pi/2, 0)), the inverse of the world-to-camera rotation above, and its centre is
    c = -R^T T = (2, 0, 0) (it looks along R^T (0, 0, 1) = -x, at the origin). Intrinsics are fractions: fx 0.5
    of the width 100, fy 1.0 of the height 50, the principal point (0.5, 0.5) of each."""
    scale = tmp_path / "Actor01" / "Sequence1" / "4x"
    scale.mkdir(parents=True)
    (scale / "calibration.csv").write_text("name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py\n"
                                           f"Cam001,100,50,0,{-np.pi / 2!r},0,2,0,0,0.5,1.0,0.5,0.5\n")
    _one_frame(scale / "rgbs" / "Cam001", "Cam001_rgb000000.jpg", scale / "masks" / "Cam001", "Cam001_mask000000.png")
    _thuman_params_file(scale.parent / "smpl_params.npz")
    for root in (scale.parent, scale):  # the sequence folder or its scale folder
        capture = ActorsHQCapture(root)
        _sees_the_point_where_worked_out(capture)
        assert capture.has_frame("Cam001", 0) and capture.read_mask("Cam001", 0).max() == 255


def test_avatarrex_fixture_by_hand(tmp_path):
    """calibration_full.json holds world to camera, used as given; imgSize is [width, height]."""
    rotation = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    (tmp_path / "calibration_full.json").write_text(json.dumps({"22010708": {
        "K": [[50, 0, 50], [0, 50, 25], [0, 0, 1]], "R": rotation, "T": [0, 0, 2], "imgSize": [100, 50]}}))
    _one_frame(tmp_path / "22010708", "00000000.jpg", tmp_path / "22010708" / "mask" / "pha", "00000000.jpg")
    _thuman_params_file(tmp_path / "smpl_params.npz")
    capture = AvatarReXCapture(tmp_path)
    _sees_the_point_where_worked_out(capture)
    np.testing.assert_array_equal(capture.cameras["22010708"].dist, np.zeros(5))


def test_easymocap_fixture_by_hand(tmp_path, model):
    """intri.yml / extri.yml as EasyMocap writes them (camera_utils.write_camera: `names` quoted, matrices as
    !!opencv-matrix); R_ is the Rodrigues vector (0, pi/2, 0) of the rotation above, world to camera. The fit: the
    body at rest rotated by Rh = pi about y and moved by Th, so the standard translation is Th + R J0 - J0 =
    Th - 2 J0 in x and z (R = diag(-1, 1, -1))."""
    (tmp_path / "intri.yml").write_text(
        '%YAML:1.0\r\n---\r\nnames:\r\n  - "01"\r\nK_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 3\r\n  dt: d\r\n'
        '  data: [50.0, 0.0, 50.0, 0.0, 50.0, 25.0, 0.0, 0.0, 1.0]\r\ndist_01: !!opencv-matrix\r\n  rows: 1\r\n'
        '  cols: 5\r\n  dt: d\r\n  data: [0.0, 0.0, 0.0, 0.0, 0.0]\r\nH_01: 50\r\nW_01: 100\r\n')
    (tmp_path / "extri.yml").write_text(
        '%YAML:1.0\r\n---\r\nnames:\r\n  - "01"\r\nR_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 1\r\n  dt: d\r\n'
        f'  data: [0.0, {np.pi / 2!r}, 0.0]\r\nT_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 1\r\n  dt: d\r\n'
        '  data: [0.0, 0.0, 2.0]\r\n')
    _one_frame(tmp_path / "images" / "01", "000000.jpg", tmp_path / "mask-schp" / "01", "000000.png", mask_value=1)
    (tmp_path / "smplx").mkdir()
    (tmp_path / "smplx" / "000000.json").write_text(json.dumps([{
        "id": 0, "Rh": [[0.0, np.pi, 0.0]], "Th": [[0.5, 1.0, -0.25]], "poses": [[0.0] * 87], "shapes": [[0.0] * 10],
        "expression": [[0.0] * 10]}]))
    capture = EasyMocapCapture(tmp_path, body_model=model)
    _sees_the_point_where_worked_out(capture)
    assert capture.read_mask("01", 0).max() == 255  # labels above 0 are the person
    j0 = model.j_regressor.numpy()[0] @ model.v_template.numpy()
    np.testing.assert_allclose(capture.params.transl[0], [0.5 - 2 * j0[0], 1.0, -0.25 - 2 * j0[2]], atol=1e-9)
    np.testing.assert_allclose(np.abs(capture.params.full_pose[0, 0]), [0, np.pi, 0], atol=1e-9)


# Hostile trees: each a clear error naming the file, before anything is written.

@pytest.fixture
def trees(pinhole, model, tmp_path):
    raw, thuman = pinhole
    return {"easymocap": write_easymocap(thuman, tmp_path / "em", model, components=0),
            "actorshq": write_actorshq(thuman, tmp_path / "ahq" / "Actor01" / "Sequence1"),
            "avatarrex": write_avatarrex(thuman, tmp_path / "arx")}


def _reopen(layout, root, model):
    return open_capture(layout, root, **({"body_model": model} if layout == "easymocap" else {}))


def _edit_text(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


@pytest.mark.parametrize("layout, edit, file", [
    ("easymocap", lambda r: _edit_text(r / "intri.yml", '  - "cam00"', '  - "../cam00"'), "intri.yml"),
    ("actorshq", lambda r: _edit_text(r / "4x" / "calibration.csv", "\ncam00,", "\ncam/00,"), "calibration.csv"),
    ("avatarrex", lambda r: _edit_text(r / "calibration_full.json", '"22010700"', '"../22010700"'),
     "calibration_full.json"),
])
def test_camera_names_that_are_not_one_path_component(trees, model, layout, edit, file):
    root = trees[layout]
    edit(root)
    before = sorted(str(p) for p in root.parent.rglob("*"))
    with pytest.raises(CaptureError, match="path separator|starts with '.'") as err:
        _reopen(layout, root, model)
    assert file in str(err.value)
    assert sorted(str(p) for p in root.parent.rglob("*")) == before


@pytest.mark.parametrize("layout, victim", [("easymocap", "images/cam01/000001.png"),
                                            ("actorshq", "4x/masks/cam02/cam02_mask000002.png"),
                                            ("avatarrex", "22010701/00000000.png")])
def test_missing_frames(trees, model, layout, victim):
    (trees[layout] / victim).unlink()
    with pytest.raises(CaptureError, match="frame counts disagree") as err:
        _reopen(layout, trees[layout], model)
    assert str((trees[layout] / victim).parent) in str(err.value)


def test_a_listed_missing_frame_is_skipped(trees, model):
    root = trees["avatarrex"]
    (root / "22010701" / "00000002.png").unlink()
    (root / "missing_img_files.txt").write_text("D:\\avatarrex\\22010701\\00000002.jpg\n")
    capture = AvatarReXCapture(root)
    assert not capture.has_frame("22010701", 2) and capture.has_frame("22010701", 1)


@pytest.mark.parametrize("layout, extra", [("actorshq", "4x/rgbs/cam00/cam00_rgb000003.png"),
                                           ("avatarrex", "22010702/mask/pha/00000007.png")])
def test_frames_without_parameters(trees, model, layout, extra):
    shutil.copyfile(next((trees[layout] / extra).parent.iterdir()), trees[layout] / extra)
    with pytest.raises(CaptureError, match="have no body parameters"):
        _reopen(layout, trees[layout], model)


def test_easymocap_fits_without_images_and_images_without_fits(trees, model):
    root = trees["easymocap"]
    (root / "smplx" / "000000.json").unlink()  # images without a fit: a fit of part of the sequence
    assert EasyMocapCapture(root, body_model=model).frames == [1, 2]
    shutil.copyfile(root / "smplx" / "000001.json", root / "smplx" / "000009.json")
    with pytest.raises(CaptureError, match="have no image"):
        EasyMocapCapture(root, body_model=model)


def test_video_shorter_than_the_parameters(pinhole, tmp_path):
    raw, thuman = pinhole
    root = write_avatarrex(thuman, tmp_path / "arx", video=True)
    video = root / "22010701.mkv"
    capture = cv2.VideoCapture(str(video))
    frames = [capture.read()[1] for _ in range(2)]
    capture.release()
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 30, (40, 40))
    for frame in frames:
        writer.write(frame)
    writer.release()
    with pytest.raises(CaptureError, match="declares 2 frames, shorter than the 3 frames") as err:
        AvatarReXCapture(root)
    assert str(video) in str(err.value)


def test_video_beside_frames_and_video_of_another_size(pinhole, tmp_path):
    raw, thuman = pinhole
    root = write_avatarrex(thuman, tmp_path / "arx")
    writer = cv2.VideoWriter(str(root / "22010701.mkv"), cv2.VideoWriter_fourcc(*"FFV1"), 30, (80, 40))
    for _ in range(3):
        writer.write(np.zeros((40, 80, 3), np.uint8))
    writer.release()
    with pytest.raises(CaptureError, match="keep either the frames or the video"):
        AvatarReXCapture(root)
    for frame in (root / "22010701").glob("*.png"):
        frame.unlink()
    with pytest.raises(CaptureError, match="frames are 80x40 .* calibration gives 40x40"):
        AvatarReXCapture(root)


def test_huge_declared_sizes_are_not_read(trees, model):
    root = trees["easymocap"]
    intri = root / "intri.yml"
    _edit_text(intri, "K_cam00: !!opencv-matrix\n  rows: 3\n  cols: 3",
               "K_cam00: !!opencv-matrix\n  rows: 300000\n  cols: 300000")
    with pytest.raises(CaptureError, match="`K_cam00` declares 90000000000 values"):
        EasyMocapCapture(root, body_model=model)
    big = root / "smplx" / "000001.json"
    with open(big, "r+b") as handle:
        handle.truncate(1 << 30)  # sparse: a file that says 1 GiB
    with pytest.raises(CaptureError, match="000001.json: 1,073,741,824 bytes"):
        EasyMocapCapture(root, body_model=model)


def test_easymocap_poses_of_no_smplx_form_and_several_people(trees, model):
    root = trees["easymocap"]
    path = root / "smplx" / "000001.json"
    fit = json.loads(path.read_text())
    fit[0]["poses"] = [[0.0] * 78]
    path.write_text(json.dumps(fit))
    with pytest.raises(CaptureError, match="78 values, an SMPL\\+H fit"):
        EasyMocapCapture(root, body_model=model)
    fit[0]["poses"] = [[0.0] * 165]
    path.write_text(json.dumps(fit + [dict(fit[0], id=3)]))
    with pytest.raises(CaptureError, match="000001.json: holds 2 people"):
        EasyMocapCapture(root, body_model=model)
    assert EasyMocapCapture(root, body_model=model, person=0).frames == [0, 1, 2]


def test_reader_options_and_subject_paths_are_checked():
    assert reader_options("easymocap", {"masks": "mask-schp", "person": 1}, "d.yaml") == {"masks": "mask-schp",
                                                                                         "person": 1}
    with pytest.raises(CaptureError, match="d.yaml: `reader` option 'mask' is not one of the easymocap"):
        reader_options("easymocap", {"mask": "x"}, "d.yaml")
    with pytest.raises(CaptureError, match="flat_hand_mean must be bool"):
        reader_options("easymocap", {"flat_hand_mean": "yes"}, "d.yaml")
    with pytest.raises(CaptureError, match="takes none"):
        reader_options("avatarrex", {"scale": "4x"}, "d.yaml")
    data = {"subject_paths": {"a1s1": "Actor01/Sequence1"}}
    assert subject_path(data, "a1s1", "d.yaml") == "Actor01/Sequence1"
    assert subject_path(data, "other", "d.yaml") == "other"
    for bad in ("../Actor01", "/abs/path", "Actor01//x", "Actor01/.."):
        with pytest.raises(CaptureError, match="d.yaml"):
            subject_path({"subject_paths": {"s": bad}}, "s", "d.yaml")


def test_doctor_sizes_each_layout_from_its_calibration(trees, pinhole):
    """`pig doctor --dataset` sizes a capture of each layout from its calibration and parameters (first subject)."""
    from pig import doctor
    from pig.config import load_preset

    raw, thuman = pinhole
    sizes = {(cam.width, cam.height) for cam in thuman.cameras.values()}
    datasets = {"easymocap": {"root": str(trees["easymocap"].parent), "subjects": ["em"]},
                "actorshq": {"root": str(trees["actorshq"].parents[1]), "subjects": ["a1s1"],
                             "subject_paths": {"a1s1": "Actor01/Sequence1"}, "reader": {"scale": "4x"}},
                "avatarrex": {"root": str(trees["avatarrex"].parent), "subjects": ["arx"]}}
    for layout, dataset in datasets.items():
        geometry = doctor.nominal_geometry(load_preset("test"), {"name": f"my_{layout}", "format": layout, **dataset})
        assert geometry is not None, layout
        assert len(geometry.cameras) == len(thuman.cameras) and set(geometry.cameras.values()) == sizes
        assert geometry.frames == thuman.frames


def test_preprocess_decodes_each_video_once(pinhole, tmp_path):
    """The preprocess stage's threads ask for a video's frames nearly in order: each is decoded once, never from the
    start again, and the written capture equals the one from the frame folders."""
    from pig.data.splits import SplitConfig
    from pig.stages.preprocess import PreprocessConfig, preprocess_capture

    raw, thuman = pinhole
    outputs = {}
    for video in (False, True):
        capture = AvatarReXCapture(write_avatarrex(thuman, tmp_path / f"arx{video}", video=video))
        out = tmp_path / f"capture{video}"
        preprocess_capture(capture, out, PreprocessConfig(workers=4, train_encoding="png"), raw / "body_model.npz",
                           SplitConfig(novel_view_count=1), "arx", progress=False)
        if video:
            sources = [*capture._images.values(), *capture._masks.values()]
            assert all(isinstance(s, VideoFrames) and s.restarts == 0 for s in sources)
        outputs[video] = out
    for path in sorted(outputs[False].rglob("*.png")):
        twin = outputs[True] / path.relative_to(outputs[False])
        np.testing.assert_array_equal(cv2.imread(str(twin), cv2.IMREAD_UNCHANGED),
                                      cv2.imread(str(path), cv2.IMREAD_UNCHANGED))


def test_easymocap_newer_hand_keys_and_huge_image_headers(trees, model):
    """Fits with the newer separate `handl` / `handr` are refused, not read with the hands dropped; an image whose
    header declares far more pixels than its camera is refused before decoding."""
    root = trees["easymocap"]
    path = root / "smplx" / "000002.json"
    fit = json.loads(path.read_text())
    path.write_text(json.dumps([dict(fit[0], handl=[[0.0] * 6], handr=[[0.0] * 6])]))
    with pytest.raises(CaptureError, match="000002.json: holds 'handl' / 'handr'"):
        EasyMocapCapture(root, body_model=model)
    image = trees["actorshq"] / "4x" / "rgbs" / "cam01" / "cam01_rgb000001.png"
    data = bytearray(image.read_bytes())
    data[16:24] = (100_000).to_bytes(4, "big") * 2  # IHDR width and height
    image.write_bytes(bytes(data))
    capture = ActorsHQCapture(trees["actorshq"])
    with pytest.raises(CaptureError, match="cam01_rgb000001.png"):
        capture.read_image("cam01", 1)
