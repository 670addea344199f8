"""DNA-Rendering .smc reader and writer: round trips against the source capture, conventions checked
against independent references (raw HDF5 values, explicit matrix algebra), malformed files, and the
access pattern of the dataset's own reader.

The official reader's accesses, re-expressed below as plain h5py reads (`_official_*`; facts only, no
code taken). Sources, read through the search tool:
  [R] DNA-Rendering/DNA-Rendering scripts/3DGS/SMCReader.py @ bd66a27e920f8582cff0587a55cc5e0bd381bb10
  [D] DNA-Rendering/DNA-Rendering scripts/3DGS/dataset_readers.py @ 1e41b621f13072400401ca787b7182492f7c3374
  [P] DNA-Rendering/DNA-Rendering.github.io inner-download.html @ 03fd9accae4dccf091294b4608b5d4465ca5d61e
  [C] a public copy of [R] (repository not resolvable by the search tool) whose constructor also reads
      `ethnicity`; [R] has that line commented out.
- SMCReader(path) [R], on the main and on the annotation file alike: if the root has any attribute, reads
  attrs actor_id, performance_id, age, gender, height, weight (+ ethnicity [C]); [P] documents them as
  int, int, int, str ("male"/"female"), int, int, str ("yellow"/"white"/"black"/"brown"), plus
  text_label (str, a JSON file name; no reader reads it). For each of Camera_5mp, Camera_12mp, Kinect
  present: group attrs num_device, num_frame, resolution ([P]: int, int, (height, width)).
- get_Calibration(cam) [R]: Camera_Parameter/f"{int(cam):02d}"/{D, K, RT, Color_Calibration}[()], all four
  unconditionally; get_Calibration_all(): the same four under every key of Camera_Parameter. [P]: K
  double (3, 3), D double (5,), RT double (4, 4) camera-to-world, Color_Calibration double (3, 3), BGR.
- get_img(group, cam, "color", frame) [R]: asserts group in (Camera_12mp, Camera_5mp, Kinect), str(cam) in
  the group, "color" in group[cam], str(frame) in its keys; cv2.imdecode(bytes, IMREAD_COLOR) (BGR).
  frame None: the frame keys as sorted ints, one image each, np.stack.
- get_mask(cam, frame) [R]: asserts str(frame) in Mask/str(cam)/mask; imdecode IMREAD_COLOR; np.max over axis 2.
- get_SMPLx(frame) [R]: t_frame = SMPLx/betas[()].shape[0]; an int frame asserts frame < t_frame; a list
  or None (range(t_frame)) index too; returns SMPLx/{betas, expression, fullpose, transl}[()][frames, ...]
  and SMPLx/scale[()]. So betas need one row per frame ([P] still says "beta" (1, 10)).
- get_Keypoints2d/3d (Keypoints_2D/f"{cam:02d}", Keypoints_3D/keypoints3d) and get_Kinect_Calibration*
  (Calibration/Kinect) print a notice and return None when the group is absent.
- readCamerasDNARendering [D]: actor_info["gender"] of the main file builds SMPLX(gender=...);
  get_SMPLx(Frame_id=1), each of betas, expression, fullpose, transl given a batch axis, fullpose sliced
  [:, 0], [:, 1:22], [:, 22], [:, 23], [:, 24], [:, 25:40], [:, 40:55]; per view of Camera_5mp:
  get_Calibration(view) K, D, RT; get_img("Camera_5mp", view, "color", 1) and get_mask(view, 1), both
  cv2.undistort(x, K, D); w2c = inv(np.array(RT, float32)); K[:2] *= 0.5 in place.
"""
from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch

from pig.body.model import NUM_JOINTS, SMPLX_PARENTS, BodyModel
from pig.body.params import SmplxParams
from pig.data.dna import DnaCapture, locate_smc, required_files
from pig.data.raw import CaptureError, RawCamera
from pig.data.smc_writer import write_smc

SEQ = "0007_03"


def _tiny_body_arrays(rng) -> dict[str, np.ndarray]:
    """A 165-vertex body in the SMPL-X layout: three vertices per joint, rigidly skinned; nonzero hands_mean."""
    joints = np.zeros((NUM_JOINTS, 3))
    for j in range(1, NUM_JOINTS):
        joints[j] = joints[SMPLX_PARENTS[j]] + rng.normal(0, 0.06, 3)
    verts = np.repeat(joints, 3, axis=0) + rng.normal(0, 0.02, (3 * NUM_JOINTS, 3))
    regressor = np.kron(np.eye(NUM_JOINTS), np.full((1, 3), 1 / 3))
    return {
        "v_template": verts,
        "f": np.arange(3 * NUM_JOINTS).reshape(-1, 3),
        "shapedirs": rng.normal(0, 0.01, (len(verts), 3, 20)),
        "posedirs": np.zeros((len(verts), 3, (NUM_JOINTS - 1) * 9)),
        "J_regressor": regressor,
        "weights": regressor.T.copy(),
        "kintree_table": np.stack([SMPLX_PARENTS, np.arange(NUM_JOINTS)]),
        "hands_meanl": rng.normal(0, 0.3, 45),
        "hands_meanr": rng.normal(0, 0.3, 45),
    }


def _look_at(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, T) of an OpenCV camera at `centre` looking at the origin, image y pointing down."""
    z = -centre / np.linalg.norm(centre)
    down = np.array([0.0, -1.0, 0.0])
    y = down - down @ z * z
    y /= np.linalg.norm(y)
    R = np.stack([np.cross(y, z), y, z])
    return R, -R @ centre


def _project(camera: RawCamera, points: np.ndarray) -> np.ndarray:
    rvec = cv2.Rodrigues(camera.R)[0]
    pixels = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, camera.T, camera.K, camera.dist)[0]
    return pixels.reshape(-1, 2)


def _posed_vertices(model: BodyModel, params: SmplxParams) -> np.ndarray:
    out = model(torch.from_numpy(params.full_pose), torch.from_numpy(params.betas),
                torch.from_numpy(params.expression), torch.from_numpy(params.transl))
    return out.vertices.numpy()


class TinyCapture:
    """An in-memory RawCapture: noise images, masks = the projected body vertices, one missing frame."""

    def __init__(self, model: BodyModel, rng, width=40, height=30):
        self.source = Path("<tiny>")
        self.frames = [10, 11, 13]
        n = len(self.frames)
        self.params = SmplxParams(full_pose=rng.normal(0, 0.3, (n, NUM_JOINTS, 3)), betas=rng.normal(0, 1, 10),
                                  expression=rng.normal(0, 1, (n, 10)), transl=rng.normal(0, 0.05, (n, 3)))
        self.cameras = {}
        for i, angle in enumerate(np.linspace(0, 2 * np.pi, 5, endpoint=False)):
            R, T = _look_at(np.array([3 * np.sin(angle), 0.3 * i - 0.5, 3 * np.cos(angle)]))
            K = np.array([[25.0 + i, 0.2, width / 2 + 0.3 * i], [0, 26.0 - i, height / 2 - 0.2 * i], [0, 0, 1]])
            self.cameras[f"cam{i:02d}"] = RawCamera(name=f"cam{i:02d}", K=K, R=R, T=T, width=width, height=height,
                                                    dist=np.array([0.02, -0.01, 0.001, -0.002, 0.003]) * (i + 1))
        self.missing = {("cam02", 13)}
        verts = _posed_vertices(model, self.params)
        self.images, self.masks = {}, {}
        for name, cam in self.cameras.items():
            for index, frame in enumerate(self.frames):
                self.images[name, frame] = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
                mask = np.zeros((height, width), np.uint8)
                for u, v in np.round(_project(cam, verts[index])).astype(int):
                    if 0 <= u < width and 0 <= v < height:
                        mask[v, u] = 255
                self.masks[name, frame] = mask

    def has_frame(self, camera, frame):
        return (camera, frame) not in self.missing

    def read_image(self, camera, frame):
        return self.images[camera, frame].copy()

    def read_mask(self, camera, frame):
        return self.masks[camera, frame].copy()


@pytest.fixture(scope="module")
def body_model():
    return BodyModel(_tiny_body_arrays(np.random.default_rng(1))).to(torch.float64)


@pytest.fixture(scope="module")
def tiny(body_model):
    return TinyCapture(body_model, np.random.default_rng(2))


@pytest.fixture(scope="module")
def written(tiny, body_model, tmp_path_factory):
    """The tiny capture as .smc: cams 0..2 in Camera_5mp, 3..4 in Camera_12mp."""
    out = tmp_path_factory.mktemp("dna")
    main, annots = write_smc(tiny, out, SEQ, body_model, num_5mp=3)
    return out, main, annots


def _copy(written, tmp_path) -> tuple[Path, Path]:
    out = tmp_path / "copy"
    shutil.copytree(written[0], out)
    return out / f"{SEQ}.smc", out / "annotations" / f"{SEQ}_annots.smc"


def test_round_trip_cameras_images_masks_and_poses(tiny, written, body_model):
    out, main, annots = written
    assert (main, annots) == (out / f"{SEQ}.smc", out / "annotations" / f"{SEQ}_annots.smc")
    with DnaCapture(out, SEQ, body_model=body_model) as dna:
        assert list(dna.cameras) == ["0", "1", "2", "3", "4"]
        assert dna.frames == [0, 1, 2]
        for index, (name, source) in enumerate(tiny.cameras.items()):
            cam = dna.cameras[str(index)]
            for key in ("K", "R", "T", "dist"):
                np.testing.assert_allclose(getattr(cam, key), getattr(source, key), atol=1e-6, rtol=0)
            assert (cam.width, cam.height) == (source.width, source.height)
            for new, frame in enumerate(tiny.frames):
                assert dna.has_frame(str(index), new) == tiny.has_frame(name, frame)
                if tiny.has_frame(name, frame):
                    np.testing.assert_array_equal(dna.read_image(str(index), new), tiny.read_image(name, frame))
                    np.testing.assert_array_equal(dna.read_mask(str(index), new), tiny.read_mask(name, frame))
        params = dna.params
        np.testing.assert_allclose(params.full_pose, tiny.params.full_pose, atol=1e-12)
        np.testing.assert_allclose(params.betas, tiny.params.betas, atol=1e-12)
        np.testing.assert_allclose(params.expression, tiny.params.expression, atol=1e-12)
        np.testing.assert_allclose(params.transl, tiny.params.transl, atol=1e-12)


def test_file_layout_follows_the_dataset_conventions(tiny, written, body_model):
    """Raw HDF5 values against the documented layout: c2w RT, BGR bytes, flat_hand_mean=False, keys."""
    _, main_path, annots_path = written
    with h5py.File(main_path, "r") as main, h5py.File(annots_path, "r") as annots:
        assert (main.attrs["actor_id"], main.attrs["performance_id"]) == (7, 3)  # ints, as the download page
        assert sorted(main["Camera_5mp"].keys()) == ["0", "1", "2"]
        assert sorted(main["Camera_12mp"].keys()) == ["3", "4"]
        assert main["Camera_12mp"].attrs["num_device"] == 2 and main["Camera_12mp"].attrs["num_frame"] == 3
        assert sorted(annots["Camera_Parameter"].keys()) == ["00", "01", "02", "03", "04"]
        assert "2" not in main["Camera_5mp/2/color"] and "2" not in annots["Mask/2/mask"]  # the missing frame
        source = tiny.cameras["cam04"]
        centre = -source.R.T @ source.T
        rt = annots["Camera_Parameter/04/RT"][()]
        np.testing.assert_allclose(rt[:3, 3], centre, atol=1e-12)  # camera-to-world: translation = centre
        np.testing.assert_allclose(rt[:3, :3], source.R.T, atol=1e-12)
        data = main["Camera_12mp/4/color/1"][()]
        assert data.dtype == np.uint8 and data.ndim == 1
        np.testing.assert_array_equal(cv2.imdecode(data, cv2.IMREAD_COLOR), tiny.read_image("cam04", 11)[..., ::-1])
        hands = annots["SMPLx/fullpose"][()][:, 25:]
        expected = tiny.params.full_pose[:, 25:] - body_model.hands_mean.numpy()[25:]
        np.testing.assert_allclose(hands, expected, atol=1e-12)
        np.testing.assert_allclose(annots["SMPLx/fullpose"][()][:, :25], tiny.params.full_pose[:, :25], atol=1e-12)


def test_projection_of_the_read_body_lands_on_the_masks(written, body_model):
    """The posed body from the reader's params, projected with the reader's cameras, hits every mask pixel."""
    out = written[0]
    with DnaCapture(out, SEQ, body_model=body_model) as dna:
        verts = _posed_vertices(body_model, dna.params)
        hits = 0
        for name, cam in dna.cameras.items():
            for frame in dna.frames:
                if not dna.has_frame(name, frame):
                    continue
                mask = dna.read_mask(name, frame)
                pixels = np.round(_project(cam, verts[frame])).astype(int)
                inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < cam.width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < cam.height)
                assert inside.mean() > 0.9
                assert np.all(mask[pixels[inside, 1], pixels[inside, 0]] == 255)
                hits += inside.sum()
        assert hits > 0


def test_params_need_the_body_model(written):
    with DnaCapture(written[0], SEQ) as dna:
        assert len(dna.cameras) == 5  # cameras and images need no body model
        with pytest.raises(CaptureError, match="flat_hand_mean=False"):
            dna.params


# -- the official reader's accesses (module docstring) ------------------------------------------------

OFFICIAL_ACTOR_ATTRS = ("actor_id", "performance_id", "age", "gender", "height", "weight", "ethnicity")
OFFICIAL_CALIBRATION = ("D", "K", "RT", "Color_Calibration")
OFFICIAL_SMPLX = ("betas", "expression", "fullpose", "transl")


def _official_open(handle: h5py.File) -> tuple[dict | None, dict]:
    """SMCReader's constructor: actor attributes if the root has any; info attributes of each camera group."""
    actor = {key: handle.attrs[key] for key in OFFICIAL_ACTOR_ATTRS} if len(handle.attrs.keys()) > 0 else None
    groups = {group: {key: handle[group].attrs[key] for key in ("num_device", "num_frame", "resolution")}
              for group in ("Camera_5mp", "Camera_12mp", "Kinect") if group in handle}
    return actor, groups


def _official_calibration(handle: h5py.File, camera_id) -> dict:
    return {key: handle["Camera_Parameter"][f"{int(camera_id):02d}"][key][()] for key in OFFICIAL_CALIBRATION}


def _official_calibration_all(handle: h5py.File) -> dict:
    return {ci: {key: handle["Camera_Parameter"][ci][key][()] for key in OFFICIAL_CALIBRATION}
            for ci in handle["Camera_Parameter"].keys()}


def _official_img(handle: h5py.File, group: str, camera_id, frame=None) -> np.ndarray:
    assert group in ("Camera_12mp", "Camera_5mp", "Kinect")
    camera_id = str(camera_id)
    assert camera_id in handle[group].keys()
    assert "color" in handle[group][camera_id].keys()
    if frame is None:
        frames = sorted(int(key) for key in handle[group][camera_id]["color"].keys())
        return np.stack([_official_img(handle, group, camera_id, f) for f in frames], axis=0)
    assert str(frame) in handle[group][camera_id]["color"].keys()
    return cv2.imdecode(handle[group][camera_id]["color"][str(frame)][()], cv2.IMREAD_COLOR)


def _official_mask(handle: h5py.File, camera_id, frame) -> np.ndarray:
    masks = handle["Mask"][str(camera_id)]["mask"]
    assert str(frame) in masks.keys()
    return np.max(cv2.imdecode(masks[str(frame)][()], cv2.IMREAD_COLOR), 2)


def _official_smplx(handle: h5py.File, frame=None) -> dict:
    t_frame = handle["SMPLx"]["betas"][()].shape[0]
    if frame is None:
        frames = range(t_frame)
    elif isinstance(frame, list):
        frames = [int(f) for f in frame]
    else:
        frames = int(frame)
        assert frames < t_frame, f"Invalid frame_index {frames}"
    result = {key: handle["SMPLx"][key][()][frames, ...] for key in OFFICIAL_SMPLX}
    result["scale"] = handle["SMPLx"]["scale"][()]
    return result


def test_official_get_smplx_reads_every_frame(tiny, written, body_model):
    """get_SMPLx counts frames by the rows of `betas`: all 3 frames by index, as a list and as None."""
    n = len(tiny.frames)
    file_pose = tiny.params.full_pose.copy()
    for part in (slice(25, 40), slice(40, 55)):
        file_pose[:, part] -= body_model.hands_mean.numpy()[part]
    with h5py.File(written[2], "r") as annots:
        for frame in range(n):
            got = _official_smplx(annots, frame)
            assert {k: got[k].shape for k in OFFICIAL_SMPLX} == {"betas": (10,), "expression": (10,),
                                                                  "fullpose": (NUM_JOINTS, 3), "transl": (3,)}
            np.testing.assert_allclose(got["betas"], tiny.params.betas, atol=1e-12)
            np.testing.assert_allclose(got["expression"], tiny.params.expression[frame], atol=1e-12)
            np.testing.assert_allclose(got["fullpose"], file_pose[frame], atol=1e-12)
            np.testing.assert_allclose(got["transl"], tiny.params.transl[frame], atol=1e-12)
            assert np.asarray(got["scale"]).size == 1 and float(np.asarray(got["scale"]).ravel()[0]) == 1.0
        with pytest.raises(AssertionError, match=f"Invalid frame_index {n}"):
            _official_smplx(annots, n)
        every = _official_smplx(annots)
        assert [every[k].shape for k in OFFICIAL_SMPLX] == [(n, 10), (n, 10), (n, NUM_JOINTS, 3), (n, 3)]
        np.testing.assert_allclose(_official_smplx(annots, [0, 2])["fullpose"], file_pose[[0, 2]], atol=1e-12)


def test_official_get_calibration_reads_every_camera(tiny, written):
    """get_Calibration / get_Calibration_all read D, K, RT and Color_Calibration of every camera."""
    with h5py.File(written[2], "r") as annots:
        every = _official_calibration_all(annots)
        assert sorted(every) == ["00", "01", "02", "03", "04"]
        for index, source in enumerate(tiny.cameras.values()):
            calib = _official_calibration(annots, index)
            assert {k: (v.dtype, v.shape) for k, v in calib.items()} == {
                "D": (np.float64, (5,)), "K": (np.float64, (3, 3)), "RT": (np.float64, (4, 4)),
                "Color_Calibration": (np.float64, (3, 3))}
            for key in OFFICIAL_CALIBRATION:
                np.testing.assert_array_equal(calib[key], every[f"{index:02d}"][key])
            np.testing.assert_array_equal(calib["Color_Calibration"], np.eye(3))
            np.testing.assert_array_equal(calib["D"], source.dist)
            np.testing.assert_array_equal(calib["K"], source.K)


def test_official_actor_info_and_group_info(tiny, written, body_model):
    """The constructor's attributes: all seven actor attributes on the main file with the download page's
    types, none on the annotation file (so it skips them), and the camera groups' info attributes."""
    with h5py.File(written[1], "r") as main, h5py.File(written[2], "r") as annots:
        actor, groups = _official_open(main)
        assert _official_open(annots) == (None, {})
        assert {group: (int(info["num_device"]), int(info["num_frame"]), info["resolution"].tolist())
                for group, info in groups.items()} == {"Camera_5mp": (3, 3, [30, 40]), "Camera_12mp": (2, 3, [30, 40])}
        # Kinect, keypoints and Kinect calibration are absent: those getters of the reader return None.
        assert not {"Kinect", "Keypoints_2D", "Keypoints_3D", "Calibration"} & (set(main) | set(annots))
    assert [type(actor[k]) for k in OFFICIAL_ACTOR_ATTRS] == [np.int64] * 3 + [str] + [np.int64] * 2 + [str]
    # Defaults: ids from the sequence name; a BodyModel object names no gender; the height of the shaped rest
    # body (y extent of v_template + shapedirs betas, from the raw arrays), the weight of a BMI of 22.
    arrays = _tiny_body_arrays(np.random.default_rng(1))
    shaped = arrays["v_template"] + arrays["shapedirs"][..., :10] @ tiny.params.betas
    height = int(round(100 * np.ptp(shaped[:, 1])))
    assert height > 10
    assert actor == {"actor_id": 7, "performance_id": 3, "age": 30, "gender": "neutral", "height": height,
                     "weight": int(round(22 * (height / 100) ** 2)), "ethnicity": "unknown"}


def test_official_3dgs_loader_reads_frame_1_of_every_view(tiny, written):
    """readCamerasDNARendering's use of frame 1 (the frame that failed): SMPL-X with a batch axis and its
    fullpose slices, then per Camera_5mp view the undistorted image and mask and inv(RT) as float32."""
    with h5py.File(written[1], "r") as main, h5py.File(written[2], "r") as annots:
        actor, _ = _official_open(main)
        assert actor["gender"] in ("male", "female", "neutral")  # what SMPLX(gender=...) accepts
        smplx = {k: v[None] for k, v in _official_smplx(annots, 1).items() if k != "scale"}
        fullpose = smplx["fullpose"]
        slices = [fullpose[:, 0], fullpose[:, 1:22], fullpose[:, 22], fullpose[:, 23], fullpose[:, 24],
                  fullpose[:, 25:40], fullpose[:, 40:55]]
        assert [x.shape for x in slices] == [(1, 3), (1, 21, 3), (1, 3), (1, 3), (1, 3), (1, 15, 3), (1, 15, 3)]
        assert (smplx["betas"].shape, smplx["expression"].shape, smplx["transl"].shape) == ((1, 10), (1, 10), (1, 3))
        for view in sorted(int(k) for k in main["Camera_5mp"].keys()):
            source = list(tiny.cameras.values())[view]
            calib = _official_calibration(annots, view)
            image = cv2.undistort(_official_img(main, "Camera_5mp", view, 1), calib["K"], calib["D"])
            mask = cv2.undistort(_official_mask(annots, view, 1), calib["K"], calib["D"])
            assert image.shape == (30, 40, 3) and mask.shape == (30, 40)
            w2c = np.linalg.inv(np.array(calib["RT"], dtype=np.float32))
            np.testing.assert_allclose(w2c[:3, :3], source.R, atol=1e-5)
            np.testing.assert_allclose(w2c[:3, 3], source.T, atol=1e-5)
            K = calib["K"]
            K[:2] = K[:2] * 0.5
            np.testing.assert_allclose(K[:2], source.K[:2] * 0.5, atol=1e-12)


def test_official_get_img_and_get_mask_give_the_source_pixels(tiny, written):
    """get_img (BGR, one frame or the stack of all present ones) and get_mask (max over channels) on every
    camera of both groups, against the capture the file was written from."""
    with h5py.File(written[1], "r") as main, h5py.File(written[2], "r") as annots:
        for index, name in enumerate(tiny.cameras):
            group = "Camera_5mp" if index < 3 else "Camera_12mp"
            present = [i for i, frame in enumerate(tiny.frames) if tiny.has_frame(name, frame)]
            for i in present:
                np.testing.assert_array_equal(_official_img(main, group, index, i),
                                              tiny.read_image(name, tiny.frames[i])[..., ::-1])
                np.testing.assert_array_equal(_official_mask(annots, index, i), tiny.read_mask(name, tiny.frames[i]))
            stack = _official_img(main, group, index)
            assert stack.shape == (len(present), 30, 40, 3)
            np.testing.assert_array_equal(stack[-1], tiny.read_image(name, tiny.frames[present[-1]])[..., ::-1])
        with pytest.raises(AssertionError):  # the one missing frame is missing for the reader too
            _official_img(main, "Camera_5mp", 2, 2)


def test_locates_official_and_flat_layouts(written, tmp_path):
    out, main, annots = written
    official = tmp_path / "official"
    (official / "main").mkdir(parents=True)
    (official / "annotations").mkdir()
    shutil.copy(main, official / "main" / main.name)
    shutil.copy(annots, official / "annotations" / annots.name)
    assert locate_smc(official, SEQ) == (official / "main" / main.name, official / "annotations" / annots.name)
    assert locate_smc(official)[0] == official / "main" / main.name  # the only sequence
    beside = tmp_path / "beside"
    beside.mkdir()
    shutil.copy(main, beside / main.name)
    shutil.copy(annots, beside / annots.name)
    assert locate_smc(beside / main.name) == (beside / main.name, beside / annots.name)
    # The workflow passes <root>/<sequence>, which is no folder.
    assert required_files(out / SEQ) == [main, annots]
    with pytest.raises(CaptureError, match=r"put .*0165_01\.smc and .*annotations.*0165_01_annots\.smc"):
        required_files(tmp_path / "nowhere" / "0165_01")
    (beside / annots.name).unlink()
    with pytest.raises(CaptureError, match="annotation file not found"):
        locate_smc(beside / main.name)


def _edit(path: Path, action) -> None:
    with h5py.File(path, "a") as handle:
        action(handle)


@pytest.mark.parametrize("which, action, expected", [
    ("annots", lambda h: h.__delitem__("Camera_Parameter/01"), r"_annots\.smc:/Camera_Parameter/01: missing group"),
    ("annots", lambda h: h.__delitem__("SMPLx"), r"_annots\.smc:/SMPLx: missing group"),
    ("annots", lambda h: h.__delitem__("Camera_Parameter/03/RT"), r"_annots\.smc:/Camera_Parameter/03/RT: missing dataset"),
    ("main", lambda h: h["Camera_12mp"].attrs.__delitem__("num_frame"),
     r"0007_03\.smc:/Camera_12mp: missing attribute 'num_frame'"),
    ("main", lambda h: h["Camera_5mp"].attrs.__delitem__("resolution"),
     r"0007_03\.smc:/Camera_5mp: missing attribute 'resolution'"),
    ("main", lambda h: h["Camera_5mp"].attrs.__setitem__("num_frame", 4),
     r"0007_03\.smc:/Camera_5mp: attribute num_frame = 4 but .*_annots\.smc:/SMPLx/fullpose has 3 frames"),
    ("main", lambda h: h["Camera_5mp"].attrs.__setitem__("resolution", np.array([30, 41])),
     r"0007_03\.smc:/Camera_5mp/0/color/0: image is 40x30 \(WxH\) but .*resolution is \[30, 41\]"),
    ("annots", lambda h: (h.__delitem__("SMPLx/transl"), h.create_dataset("SMPLx/transl", data=np.zeros((2, 3)))),
     r"_annots\.smc:/SMPLx: 'transl' has shape \(2, 3\), expected \(3, 3\)"),
    ("annots", lambda h: (h.__delitem__("Camera_Parameter/02/RT"),
                          h.create_dataset("Camera_Parameter/02/RT", data=np.diag([1.0, 1, -1, 1]))),
     r"_annots\.smc:/Camera_Parameter/02/RT: expected a rigid 4x4"),
])
def test_malformed_files_name_file_and_hdf5_path(written, tmp_path, which, action, expected):
    main, annots = _copy(written, tmp_path)
    _edit(main if which == "main" else annots, action)
    with pytest.raises(CaptureError, match=expected):
        DnaCapture(main.parent, SEQ)


def _replace(handle: h5py.File, path: str, data) -> None:
    if path in handle:
        del handle[path]
    handle.create_dataset(path, data=data)


def test_writer_stores_one_betas_row_per_frame_and_the_reader_takes_any_row_count(written, tmp_path, tiny, body_model):
    """The export has (N, 10) betas, as real files; the reader also takes (1, 10) and (10,), not (2, 10)
    for 3 frames."""
    with h5py.File(written[2], "r") as annots:
        np.testing.assert_array_equal(annots["SMPLx/betas"][()], np.repeat(tiny.params.betas[None], 3, axis=0))
    main, annots = _copy(written, tmp_path)
    for stored in (tiny.params.betas[None], tiny.params.betas):
        _edit(annots, lambda h: _replace(h, "SMPLx/betas", stored))
        with DnaCapture(main.parent, SEQ, body_model=body_model) as dna:
            np.testing.assert_allclose(dna.params.betas, tiny.params.betas, atol=1e-12)
            assert dna.params.num_frames == 3
    _edit(annots, lambda h: _replace(h, "SMPLx/betas", np.repeat(tiny.params.betas[None], 2, axis=0)))
    with pytest.raises(CaptureError, match=r"_annots\.smc:/SMPLx: 'betas' has shape \(2, 10\)"):
        DnaCapture(main.parent, SEQ)


def test_undecodable_image_and_mask_bytes(written, tmp_path):
    main, annots = _copy(written, tmp_path)
    junk = np.frombuffer(b"not an image at all", dtype=np.uint8)
    _edit(main, lambda h: (h.__delitem__("Camera_5mp/1/color/2"), h.create_dataset("Camera_5mp/1/color/2", data=junk)))
    _edit(annots, lambda h: (h.__delitem__("Mask/3/mask/0"), h.create_dataset("Mask/3/mask/0", data=junk)))
    with DnaCapture(main.parent, SEQ) as dna:
        dna.read_image("1", 1)  # neighbours still read
        with pytest.raises(CaptureError, match=r"0007_03\.smc:/Camera_5mp/1/color/2: image bytes could not be decoded"):
            dna.read_image("1", 2)
        with pytest.raises(CaptureError, match=r"_annots\.smc:/Mask/3/mask/0: image bytes could not be decoded"):
            dna.read_mask("3", 0)
        with pytest.raises(CaptureError, match=r"0007_03\.smc:/Camera_5mp/2/color/2: missing dataset"):
            dna.read_image("2", 2)


def test_not_an_hdf5_file(written, tmp_path):
    main, _ = _copy(written, tmp_path)
    main.write_bytes(b"garbage")
    with pytest.raises(CaptureError, match=r"0007_03\.smc: not a readable HDF5"):
        DnaCapture(main.parent, SEQ)


def test_resolution_in_either_order_and_padded_or_unpadded_keys(written, tmp_path, tiny):
    """(W, H) instead of (H, W); masks under zero-padded and calibration under unpadded camera keys."""
    main, annots = _copy(written, tmp_path)
    _edit(main, lambda h: h["Camera_5mp"].attrs.__setitem__("resolution", np.array([40, 30])))
    _edit(annots, lambda h: (h.move("Mask/1", "Mask/01"), h.move("Camera_Parameter/02", "Camera_Parameter/2")))
    with DnaCapture(main.parent, SEQ) as dna:
        assert (dna.cameras["0"].width, dna.cameras["0"].height) == (40, 30)
        np.testing.assert_array_equal(dna.read_mask("1", 0), tiny.read_mask("cam01", 10))
        np.testing.assert_allclose(dna.cameras["2"].K, tiny.cameras["cam02"].K, atol=1e-12)


@pytest.mark.parametrize("channels", [3, 4])
def test_mask_is_the_maximum_over_channels(written, tmp_path, channels):
    """Colour masks reduce to the maximum of B, G, R (as the dataset's loader); an alpha channel is ignored."""
    main, annots = _copy(written, tmp_path)
    mask = np.zeros((30, 40, channels), np.uint8)
    mask[3, 4, :3] = (0, 0, 200)
    mask[5, 6, :3] = (90, 10, 0)
    mask[..., 3:] = 255
    data = cv2.imencode(".png", mask)[1].reshape(-1)
    _edit(annots, lambda h: (h.__delitem__("Mask/0/mask/1"), h.create_dataset("Mask/0/mask/1", data=data)))
    with DnaCapture(main.parent, SEQ) as dna:
        got = dna.read_mask("0", 1)
    expected = np.zeros((30, 40), np.uint8)
    expected[3, 4], expected[5, 6] = 200, 90
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("stored", [
    np.array([[0.9, 0.05, 0.0], [0.02, 1.1, 0.01], [0.1, 0.0, 0.8]]),  # 3x3 acting on BGR vectors
    np.array([0.8, 1.0, 1.2]),  # per-channel gains in BGR order
])
def test_color_calibration_acts_on_bgr_pixels(written, tmp_path, tiny, stored):
    main, annots = _copy(written, tmp_path)
    for cam in range(5):
        data = stored if cam == 3 else np.ones_like(stored) if stored.ndim == 1 else np.eye(3)
        _edit(annots, lambda h: _replace(h, f"Camera_Parameter/{cam:02d}/Color_Calibration", data))
    matrix = stored if stored.ndim == 2 else np.diag(stored)
    bgr = tiny.read_image("cam03", 11)[..., ::-1].astype(np.float64)
    expected = np.clip(bgr @ matrix.T, 0, 255)[..., ::-1]  # reference in BGR space
    with DnaCapture(main.parent, SEQ, color_correction=True) as dna:
        np.testing.assert_allclose(dna.read_image("3", 1), expected, atol=0.5 + 1e-4)  # rounded to uint8 (float32)
        np.testing.assert_array_equal(dna.read_image("2", 1), tiny.read_image("cam02", 11))  # identity
    with DnaCapture(main.parent, SEQ) as dna:  # not applied unless asked
        np.testing.assert_array_equal(dna.read_image("3", 1), tiny.read_image("cam03", 11))
    _edit(annots, lambda h: h.__delitem__("Camera_Parameter/00/Color_Calibration"))
    with pytest.raises(CaptureError, match=r"Camera_Parameter/00: color_correction requested but no Color_Calibration"):
        DnaCapture(main.parent, SEQ, color_correction=True)


def test_color_calibration_of_unknown_shape(written, tmp_path):
    main, annots = _copy(written, tmp_path)
    for cam in range(5):
        _edit(annots, lambda h: _replace(h, f"Camera_Parameter/{cam:02d}/Color_Calibration", np.ones((2, 4))))
    with pytest.warns(UserWarning, match=r"Color_Calibration: expected a finite 3x3 matrix or 3 per-channel gains"):
        dna = DnaCapture(main.parent, SEQ)
    assert dna.cameras["0"].color_correction is None
    dna.close()
    with pytest.raises(CaptureError, match=r"Camera_Parameter/00/Color_Calibration: expected a finite 3x3"):
        DnaCapture(main.parent, SEQ, color_correction=True)


def test_writer_colour_calibration_round_trip(tiny, body_model, tmp_path):
    """A camera's RGB correction matrix survives write (stored for BGR) and read."""
    matrix = np.array([[1.0, 0.1, 0.0], [0.0, 0.9, 0.05], [0.02, 0.0, 1.1]])
    tiny.cameras["cam01"].color_correction = matrix
    try:
        write_smc(tiny, tmp_path, SEQ, body_model)
    finally:
        tiny.cameras["cam01"].color_correction = None
    with h5py.File(tmp_path / "annotations" / f"{SEQ}_annots.smc", "r") as annots:
        np.testing.assert_allclose(annots["Camera_Parameter/01/Color_Calibration"][()], matrix[::-1, ::-1])
        stored = annots["Camera_Parameter/00/Color_Calibration"][()]  # no correction: identity, not absent
        assert stored.dtype == np.float64 and stored.shape == (3, 3)
        np.testing.assert_array_equal(stored, np.eye(3))
    for requested in (False, True):
        with DnaCapture(tmp_path, SEQ, color_correction=requested) as dna:
            np.testing.assert_allclose(dna.cameras["1"].color_correction, matrix)
            assert dna.cameras["0"].color_correction is None  # identity reads as "no correction"
            np.testing.assert_array_equal(dna.read_image("0", 1), tiny.read_image("cam00", 11))
    with h5py.File(tmp_path / f"{SEQ}.smc", "r") as main:  # default: up to 48 cams in Camera_5mp
        assert sorted(main) == ["Camera_5mp"] and len(main["Camera_5mp"]) == 5


def test_jpeg_export_stores_the_encoder_output(tiny, body_model, tmp_path):
    write_smc(tiny, tmp_path, SEQ, body_model, image_ext=".jpg", jpeg_quality=80)
    with DnaCapture(tmp_path, SEQ) as dna:
        image = dna.read_image("1", 2)
    bgr = tiny.read_image("cam01", 13)[..., ::-1]
    reference = cv2.imdecode(cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 80])[1], cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(image, reference[..., ::-1])
    assert not np.array_equal(image, bgr[..., ::-1])  # lossy, unlike the default PNG


def test_gender_mismatch_with_the_model_file_is_warned(tiny, body_model, tmp_path):
    write_smc(tiny, tmp_path, SEQ, body_model, actor={"gender": "female"})
    path = tmp_path / "SMPLX_MALE.npz"
    np.savez(path, **_tiny_body_arrays(np.random.default_rng(1)))
    with pytest.warns(UserWarning, match="gender is 'female' but the body model is .*SMPLX_MALE"):
        DnaCapture(tmp_path, SEQ, body_model=path).close()
    (tmp_path / "SMPLX_MALE.npz").rename(tmp_path / "SMPLX_FEMALE.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        DnaCapture(tmp_path, SEQ, body_model=tmp_path / "SMPLX_FEMALE.npz").close()


def test_default_gender_is_the_one_the_model_file_names(tiny, tmp_path):
    """The official loader builds SMPLX(gender=<attribute>): an export fitted with SMPLX_FEMALE says "female"."""
    path = tmp_path / "models" / "SMPLX_FEMALE.npz"
    path.parent.mkdir()
    np.savez(path, **_tiny_body_arrays(np.random.default_rng(1)))
    write_smc(tiny, tmp_path / "out", SEQ, path)
    with h5py.File(tmp_path / "out" / f"{SEQ}.smc", "r") as main:
        assert main.attrs["gender"] == "female"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and our reader sees no mismatch
        DnaCapture(tmp_path / "out", SEQ, body_model=path).close()


def _thuman4_as_dna(tmp_path) -> tuple[Path, Path, "Thuman4Capture"]:
    """B's tiny THuman4 subject (capsule body, distorted ring cameras) exported to .smc; cam 3 in Camera_12mp.

    The exported body model gets a nonzero hands_mean (the capsule's hands carry no weight, so the
    geometry and the projection check are unchanged, but the convention is exercised)."""
    from thuman4_fixture import capsule_body_arrays, write_thuman4

    from pig.data.thuman4 import Thuman4Capture

    raw = write_thuman4(tmp_path / "raw", cameras=4, frames=5, width=192, height=160)
    arrays = capsule_body_arrays()
    rng = np.random.default_rng(3)
    arrays.update(hands_meanl=rng.normal(0, 0.3, 45), hands_meanr=rng.normal(0, 0.3, 45))
    model_path = tmp_path / "models" / "SMPLX_NEUTRAL.npz"
    model_path.parent.mkdir()
    np.savez(model_path, **arrays)
    source = Thuman4Capture(raw)
    write_smc(source, tmp_path / "dna", "0001_01", model_path, num_5mp=3)
    return tmp_path / "dna" / "0001_01", model_path, source


def test_writer_cli_exports_a_thuman4_subject(tmp_path, capsys):
    from thuman4_fixture import write_thuman4

    from pig.data.smc_writer import main
    from pig.data.thuman4 import Thuman4Capture

    raw = write_thuman4(tmp_path / "raw", cameras=3, frames=2, width=48, height=40, ext="png")
    main(["--format", "thuman4", "--input", str(raw), "--output", str(tmp_path / "out"), "--sequence", "0100_02",
          "--actor", "ethnicity=white", "--actor", "age=41", "--actor", "gender=male"])
    assert capsys.readouterr().out.split() == [str(tmp_path / "out" / "0100_02.smc"),
                                               str(tmp_path / "out" / "annotations" / "0100_02_annots.smc")]
    with h5py.File(tmp_path / "out" / "0100_02.smc", "r") as handle:
        assert _official_open(handle)[0] | {"height": 0, "weight": 0} == {
            "actor_id": 100, "performance_id": 2, "age": 41, "gender": "male", "height": 0, "weight": 0,
            "ethnicity": "white"}
    with pytest.raises(SystemExit):
        main(["--format", "thuman4", "--input", str(raw), "--output", str(tmp_path / "x"), "--actor", "age"])
    assert "--actor 'age': expected KEY=VALUE" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    source = Thuman4Capture(raw)
    with DnaCapture(tmp_path / "out", body_model=raw / "body_model.npz") as dna:
        np.testing.assert_array_equal(dna.read_image("2", 1), source.read_image("cam02", 1))
        np.testing.assert_allclose(dna.params.transl, source.params.transl, atol=1e-12)
    with pytest.raises(SystemExit):
        main(["--format", "thuman4", "--input", str(tmp_path / "absent"), "--output", str(tmp_path / "x")])
    assert "body model" in capsys.readouterr().err


@pytest.fixture(scope="module")
def dna_subject(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dna_subject")
    root, model_path, source = _thuman4_as_dna(tmp)
    dataset = tmp / "dna.yaml"
    dataset.write_text(f"name: dna\nformat: dna\nbody_model: {model_path}\n"
                       "split:\n  novel_view_cameras: ['3']\n  novel_pose_fraction: 0.2\n")
    return root, dataset, source


def _preprocess(dna_subject, out: Path, preset: str):
    from pig.data.capture import Capture
    from pig.stages.preprocess import main

    root, dataset, _ = dna_subject
    assert main(["--input", str(root), "--output", str(out), "--preset", preset, "--dataset", str(dataset),
                 "--no-progress"]) == 0
    return Capture.load(out)


def test_preprocess_format_dna_end_to_end(dna_subject, tmp_path):
    """`--format dna` through the preprocess stage: projection check passes, protocol split, cameras and poses kept."""
    capture = _preprocess(dna_subject, tmp_path / "capture", "test")
    source = dna_subject[2]
    assert capture.split == {"train": {"cameras": ["0", "1", "2"], "frames": [0, 1, 2, 3]},
                             "novel_view": {"cameras": ["3"], "frames": [0, 1, 2, 3]},
                             "novel_pose": {"cameras": ["0", "1", "2", "3"], "frames": [4]}}
    for index, cam in enumerate(source.cameras.values()):
        np.testing.assert_allclose(capture.cameras[str(index)].R, cam.R, atol=1e-9)
        np.testing.assert_allclose(capture.cameras[str(index)].T, cam.T, atol=1e-9)
    np.testing.assert_allclose(capture.params.full_pose, source.params.full_pose, atol=1e-12)
    report = json.loads((tmp_path / "capture" / "report.json").read_text())
    assert report["projection_check"]["passed"] and report["format"] == "DnaCapture"


def test_half_resolution_preset_option(dna_subject, tmp_path):
    """The presets' dna override (scale 0.5, nearest masks) against the full-resolution output: 2x2 block
    means for images, every second pixel for masks, K scaled about pixel centres (cx' = (cx + 0.5) / 2 - 0.5)."""
    full_preset = tmp_path / "full.yaml"
    full_preset.write_text("preprocess:\n  scale: 1.0\n")
    full = _preprocess(dna_subject, tmp_path / "full", str(full_preset))
    half = _preprocess(dna_subject, tmp_path / "half", "test")
    for name, cam in full.cameras.items():
        small = half.cameras[name]
        assert (small.width, small.height) == (cam.width // 2, cam.height // 2)
        expected = cam.K.copy()
        expected[0, 0], expected[1, 1] = cam.K[0, 0] / 2, cam.K[1, 1] / 2
        expected[:2, 2] = (cam.K[:2, 2] + 0.5) / 2 - 0.5
        np.testing.assert_allclose(small.K, expected, atol=1e-12)
        for frame in (0, 4):
            mask = half.mask(name, frame)
            np.testing.assert_array_equal(mask, full.mask(name, frame)[::2, ::2])
            if frame not in half.split["novel_pose"]["frames"]:
                continue  # training views are JPEG: lossy, not held to a block mean at half a level
            blocks = full.image(name, frame).reshape(cam.height // 2, 2, cam.width // 2, 2, 3).mean(axis=(1, 3))
            reference = np.where(mask[..., None], blocks, 0.0)  # the test preset's background is black
            np.testing.assert_allclose(half.image(name, frame), reference, atol=0.5 / 255 + 1e-6)


@pytest.fixture(scope="module")
def synthetic_dna(tmp_path_factory):
    """Engineer A's synthetic capture (THuman4 layout) exported to .smc, with a nonzero hands_mean in the
    exported model (the stand-in's is zero, which would hide a convention error)."""
    from pig.data.synthetic import SyntheticConfig, generate_capture
    from pig.data.thuman4 import Thuman4Capture

    tmp = tmp_path_factory.mktemp("synthetic_dna")
    cfg = SyntheticConfig(cameras=4, frames=5, width=128, height=112, workers=1)
    subject = generate_capture(tmp / "synthetic" / "subject00", cfg, progress=False)
    with np.load(subject / "body_model.npz") as data:
        arrays = {k: data[k] for k in data.files}
    rng = np.random.default_rng(4)
    arrays.update(hands_meanl=rng.normal(0, 0.3, 45), hands_meanr=rng.normal(0, 0.3, 45))
    model_path = tmp / "SMPLX_NEUTRAL.npz"
    np.savez(model_path, **arrays)
    source = Thuman4Capture(subject)
    write_smc(source, tmp / "dna", "0002_01", model_path, num_5mp=3)
    return tmp / "dna" / "0002_01", model_path, source


@pytest.mark.slow
def test_synthetic_capture_round_trip(synthetic_dna):
    root, model_path, source = synthetic_dna
    with DnaCapture(root, body_model=model_path) as dna:
        assert dna.frames == source.frames == list(range(5))
        for index, (name, cam) in enumerate(source.cameras.items()):
            got = dna.cameras[str(index)]
            for key in ("K", "R", "T", "dist"):
                np.testing.assert_allclose(getattr(got, key), getattr(cam, key), atol=1e-6, rtol=0)
            assert (got.width, got.height) == (cam.width, cam.height)
            for frame in source.frames:
                np.testing.assert_array_equal(dna.read_image(str(index), frame), source.read_image(name, frame))
                np.testing.assert_array_equal(dna.read_mask(str(index), frame), source.read_mask(name, frame))
        for key in ("full_pose", "betas", "expression", "transl"):
            np.testing.assert_allclose(getattr(dna.params, key), getattr(source.params, key), atol=1e-12)


@pytest.mark.slow
def test_synthetic_capture_preprocess_matches_the_thuman4_path(synthetic_dna, tmp_path):
    """`python -m pig.stages.preprocess --format dna` on the export passes the projection check with exactly
    the scores, cameras and frames that `--format thuman4` gives on the original synthetic subject."""
    from pig.data.capture import Capture
    from pig.stages.preprocess import main

    root, model_path, source = synthetic_dna
    preset = tmp_path / "preset.yaml"
    # The check's default tolerances (5 cm body, 20 cm garment; pig/data/projection_check.py) cover the skirt.
    preset.write_text("preprocess:\n  scale: 1.0\n")
    outputs = {}
    for fmt, raw in (("dna", root), ("thuman4", source.source)):
        dataset = tmp_path / f"{fmt}.yaml"
        cameras = "['3']" if fmt == "dna" else "['cam03']"
        dataset.write_text(f"name: {fmt}\nformat: {fmt}\nbody_model: {model_path}\n"
                           f"split:\n  novel_view_cameras: {cameras}\n  novel_pose_fraction: 0.2\n")
        outputs[fmt] = tmp_path / fmt
        assert main(["--format", fmt, "--input", str(raw), "--output", str(outputs[fmt]), "--preset", str(preset),
                     "--dataset", str(dataset), "--no-progress"]) == 0
    reports = {fmt: json.loads((out / "report.json").read_text())["projection_check"] for fmt, out in outputs.items()}
    assert reports["dna"]["passed"]
    dna, thuman = Capture.load(outputs["dna"]), Capture.load(outputs["thuman4"])
    for index, name in enumerate(source.cameras):
        assert reports["dna"]["cameras"][str(index)]["iou"] == pytest.approx(reports["thuman4"]["cameras"][name]["iou"],
                                                                            abs=1e-12)
        for key in ("K", "R", "T"):
            np.testing.assert_allclose(getattr(dna.cameras[str(index)], key), getattr(thuman.cameras[name], key),
                                       atol=1e-6, rtol=0)
        for frame in (0, 4):
            np.testing.assert_array_equal(dna.image(str(index), frame), thuman.image(name, frame))
            np.testing.assert_array_equal(dna.mask(str(index), frame), thuman.mask(name, frame))
    assert dna.split["novel_pose"]["frames"] == thuman.split["novel_pose"]["frames"] == [4]
