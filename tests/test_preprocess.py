"""Preprocess stage: geometry survives undistortion + resize, the projection check tells good from swapped
cameras, protocol splits, bad input fails cleanly and nothing is left half-written."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from thuman4_fixture import look_at, write_thuman4

from pig.config import load_section
from pig.data.capture import Capture
from pig.data.images import read_image
from pig.data.projection_check import View, overlap_counts, silhouette
from pig.data.raw import CaptureError
from pig.data.splits import SplitConfig, make_split
from pig.data.thuman4 import Thuman4Capture
from pig._cli import run_cli
from pig.stages.preprocess import PreprocessConfig, main, preprocess_capture

REPO = Path(__file__).resolve().parent.parent
HOLD_OUT_LAST = SplitConfig(novel_view_cameras=["cam01"], novel_pose_frames=[1, 1])


def _run(root: Path, out: Path, *extra: str) -> int:
    return run_cli(main, ["--input", str(root), "--output", str(out), "--preset", "test", "--no-progress", *extra])


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


# -- geometry: a known 3D point lands on the same image content before and after ---------------------------------

def _blob_subject(root: Path, points_cam: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """cam00 strongly distorted, its frame 0 = Gaussian blobs drawn at cv2.projectPoints (with distortion) of points;
    cam01 and frame 1 are there to be held out (HOLD_OUT_LAST)."""
    width, height = 320, 240
    write_thuman4(root, cameras=2, frames=2, width=width, height=height, ext="png")
    K = np.array([[262.0, 0.0, 161.3], [0.0, 259.0, 118.6], [0.0, 0.0, 1.0]])
    dist = np.array([-0.28, 0.09, 0.0012, -0.0008, -0.01])
    R, T = look_at(np.array([0.4, 0.5, 3.0]))
    points = (points_cam - T) @ R  # camera -> world: R^T (x - T)
    uv = cv2.projectPoints(points, cv2.Rodrigues(R)[0], T, K, dist)[0][:, 0]
    ys, xs = np.mgrid[:height, :width]
    image = sum(np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * sigma**2)) for u, v in uv)
    cv2.imwrite(str(root / "images" / "cam00" / "00000000.png"), np.round(255 * np.dstack([image] * 3)).astype(np.uint8))
    cv2.imwrite(str(root / "masks" / "cam00" / "00000000.png"), np.full((height, width), 255, np.uint8))
    calibration = json.loads((root / "calibration.json").read_text())
    calibration["cam00"] = {"K": K.tolist(), "R": R.tolist(), "T": T.tolist(), "imgSize": [width, height],
                            "distCoeff": dist.tolist()}
    (root / "calibration.json").write_text(json.dumps(calibration))
    return points, uv, K


def _centroid(gray: np.ndarray, u: float, v: float, radius: int) -> np.ndarray:
    u0, v0 = int(round(u)), int(round(v))
    window = gray[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1]
    ys, xs = np.mgrid[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1]
    return np.array([(window * xs).sum(), (window * ys).sum()]) / window.sum()


@pytest.mark.parametrize("scale", [1.0, 0.5, 0.37])
def test_known_point_projects_to_the_blob_after_undistort_and_resize(tmp_path, scale):
    # Normalised image coordinates from the centre to the corners, where the distortion is several pixels.
    directions = np.array([[0.0, 0.0], [-0.48, -0.34], [0.5, -0.32], [-0.46, 0.36], [0.47, 0.35], [0.25, -0.1]])
    depth = np.array([3.0, 2.6, 3.4, 2.8, 3.2, 3.6])
    points_cam = np.column_stack([directions * depth[:, None], depth])
    sigma = 2.5
    points, raw_uv, K = _blob_subject(tmp_path / "raw", points_cam, sigma)
    cfg = PreprocessConfig(scale=scale, min_iou=0.0, workers=1)
    preprocess_capture(Thuman4Capture(tmp_path / "raw"), tmp_path / "out", cfg, tmp_path / "raw" / "body_model.npz",
                       HOLD_OUT_LAST, "s", progress=False)
    capture = Capture.load(tmp_path / "out")
    cam = capture.cameras["cam00"]
    assert (cam.width, cam.height) == (round(320 * scale), round(240 * scale))
    gray = capture.image("cam00", 0).mean(axis=2).astype(np.float64)
    projected = (points @ cam.R.T + cam.T) @ cam.K.T
    pinhole = projected[:, :2] / projected[:, 2:]
    radius = int(np.ceil(4 * sigma * scale)) + 1
    found = np.array([_centroid(gray, u, v, radius) for u, v in pinhole])
    np.testing.assert_array_less(np.linalg.norm(found - pinhole, axis=1), 0.5)
    # The test can fail: without undistortion the corner blobs would sit pixels away from the pinhole projection.
    ideal = (points @ cam.R.T + cam.T) @ K.T
    assert np.linalg.norm(raw_uv - ideal[:, :2] / ideal[:, 2:], axis=1).max() * scale > 3.0


# -- projection check -----------------------------------------------------------------------------------------

def test_silhouette_covers_exactly_the_pixels_inside_projected_triangles(rng):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    vertices = mesh.vertices * [1.0, 1.6, 0.7] + [0.05, -0.1, 0.0]
    R, T = look_at(np.array([0.3, 0.2, 2.5]))
    view = View(np.array([[70.0, 0, 31.7], [0, 72.0, 30.2], [0, 0, 1]]), R, T, 64, 60)
    filled = silhouette(vertices, mesh.faces, view)
    # Reference: float64 point-in-triangle test of every pixel centre against every projected triangle.
    cam = vertices @ R.T + T
    uv = (cam @ view.K.T)[:, :2] / cam[:, 2:]
    a, b, c = (uv[mesh.faces[:, i]][:, None] for i in range(3))
    ys, xs = np.mgrid[:60, :64]
    p = np.stack([xs.ravel(), ys.ravel()], axis=1)[None].astype(np.float64)

    def cross(o, d, q):
        return (d[..., 0] - o[..., 0]) * (q[..., 1] - o[..., 1]) - (d[..., 1] - o[..., 1]) * (q[..., 0] - o[..., 0])

    s1, s2, s3 = cross(a, b, p), cross(b, c, p), cross(c, a, p)
    inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
    reference = inside.any(axis=0).reshape(60, 64)
    assert reference.sum() > 500
    assert np.all(filled[reference])  # every covered pixel centre is filled
    grown = cv2.dilate(reference.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.all(grown[filled])  # and nothing farther than a pixel from the covered centres


def test_tolerant_iou_of_concentric_discs_matches_the_closed_form():
    ys, xs = np.mgrid[:201, :361]
    r = np.hypot(xs - 100, ys - 100)
    small, large = r <= 40, r <= 60
    raw = overlap_counts(small, large, 0.0, 0.0)
    assert raw[0] / raw[1] == pytest.approx(40**2 / 60**2, rel=0.02)
    assert raw[2] / raw[1] == pytest.approx(raw[0] / raw[1])  # no tolerance: the plain IoU
    # Mask larger than the body (a skirt): the garment radius forgives the annulus 40 < r <= 40 + 10.
    skirt = overlap_counts(small, large, 0.0, 10.0)
    assert skirt[2] / skirt[1] == pytest.approx(1 - (60**2 - 50**2) / 60**2, rel=0.02)
    assert overlap_counts(small, large, 0.0, 20.5)[2] == overlap_counts(small, large, 0.0, 20.5)[1]
    # Body larger than the mask: only the body radius forgives, the garment radius does not.
    body_out = overlap_counts(large, small, 10.0, 30.0)
    assert body_out[2] / body_out[1] == pytest.approx(1 - (60**2 - 50**2) / 60**2, rel=0.02)
    apart = np.hypot(xs - 230, ys - 100) <= 40  # 30 px gap: smaller tolerances forgive nothing
    assert overlap_counts(apart, large, 15.0, 15.0)[2] == 0 and overlap_counts(apart, large, 15.0, 15.0)[1] > 0


def test_good_capture_passes_and_camera_to_world_calibration_is_named(tmp_path, capsys):
    good = write_thuman4(tmp_path / "good", cameras=4, frames=4, width=192, height=160)
    assert _run(good, tmp_path / "out_good") == 0
    check = json.loads((tmp_path / "out_good" / "report.json").read_text())["projection_check"]
    assert check["passed"] and all(c["iou"] >= 0.9 and c["raw_iou"] > 0.8 for c in check["cameras"].values())

    swapped = write_thuman4(tmp_path / "swapped", cameras=4, frames=4, width=192, height=160, camera_to_world=True)
    capsys.readouterr()
    assert _run(swapped, tmp_path / "out_swapped") == 1
    err = capsys.readouterr().err
    assert "calibration looks camera-to-world; invert it" in err and "cam00" in err
    assert f"the unfinished work is kept in {tmp_path / '.out_swapped.partial'}" in err
    assert not (tmp_path / "out_swapped").exists() and _leftovers(tmp_path) == [".out_swapped.partial"]


def test_body_parameters_that_miss_the_masks_fail_with_the_general_message(tmp_path, capsys):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=3, width=192, height=160)
    arrays = dict(np.load(root / "smpl_params.npz"))
    arrays["transl"] = arrays["transl"] + [0.6, 0.0, 0.0]  # body beside the person the masks show
    np.savez(root / "smpl_params.npz", **arrays)
    assert _run(root, tmp_path / "out") == 1
    err = capsys.readouterr().err
    assert "cameras and the body parameters disagree" in err and "camera-to-world" not in err
    assert not (tmp_path / "out").exists()


# -- atomic output and bad input ------------------------------------------------------------------------------

def test_failed_rerun_keeps_the_previous_output_intact(tmp_path, capsys):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=3)
    out = tmp_path / "out"
    assert _run(root, out) == 0
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    (root / "images" / "cam01" / "00000002.jpg").write_bytes(b"broken")
    assert _run(root, out) == 1
    assert "images/cam01/00000002.jpg: image bytes could not be decoded" in capsys.readouterr().err
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before and _leftovers(tmp_path) == [".out.partial"]
    (root / "images" / "cam01" / "00000002.jpg").unlink()
    (root / "missing_img_files.txt").write_text("images\\cam01\\00000002.jpg\n")
    assert _run(root, out) == 0  # a later good run replaces it
    assert not (out / "images" / "cam01" / "00000002.png").exists() and (out / "images" / "cam00" / "00000002.png").exists()
    assert _leftovers(tmp_path) == []


def _dataset_yaml(tmp_path, text: str) -> str:
    path = tmp_path / "dataset.yaml"
    path.write_text(text)
    return str(path)


def _list_missing(root: Path, camera: str, frames) -> list[str]:
    (root / "missing_img_files.txt").write_text("".join(f"images/{camera}/{f:08d}.jpg\n" for f in frames))
    return []


BAD_RUNS = {
    "split names an unknown camera": (
        lambda t, r: ["--dataset", _dataset_yaml(t, "name: x\nsplit:\n  novel_view_cameras: [cam09]\n")],
        r"dataset\.yaml: section 'split': 'novel_view_cameras' names camera\(s\) \['cam09'\] that are not in the calibration"),
    "no body model": (lambda t, r: (r / "body_model.npz").unlink() or [],
                      r"no body model for .*SMPLX_NEUTRAL\.npz .*--body-model"),
    "body model path absent": (lambda t, r: ["--body-model", str(t / "SMPLX_NEUTRAL.npz")],
                               r"body model .*SMPLX_NEUTRAL\.npz does not exist"),
    "NaN in parameters": (
        lambda t, r: np.savez(r / "smpl_params.npz", **{**dict(np.load(r / "smpl_params.npz")),
                                                         "global_orient": np.full((3, 3), np.nan)}) or [],
        r"smpl_params\.npz: 'global_orient' contains NaN"),
    "frame counts disagree": (lambda t, r: (r / "masks" / "cam00" / "00000001.jpg").unlink() or [],
                              r"masks/cam00: 1 of the 3 frames in smpl_params\.npz have no file"),
    "missing root": (lambda t, r: ["--input", str(t / "absent")], r"absent not found: put the subject there"),
    "unknown preset key": (lambda t, r: ["--preset", _dataset_yaml(t, "preprocess:\n  scael: 2\n")],
                            r"section 'preprocess': unknown key\(s\) \['scael'\]"),
    "unknown encoding": (lambda t, r: ["--preset", _dataset_yaml(t, "preprocess:\n  train_encoding: webp\n")],
                         r"section 'preprocess'\.train_encoding: expected one of \['jpeg', 'png'\], found 'webp'"),
    "JPEG quality out of range": (lambda t, r: ["--preset", _dataset_yaml(t, "preprocess:\n  jpeg_quality: 101\n")],
                                  r"preprocess\.jpeg_quality must be in 1\.\.100, found 101"),
    "PNG level out of range": (lambda t, r: ["--preset", _dataset_yaml(t, "preprocess:\n  png_compression: 10\n")],
                               r"preprocess\.png_compression must be a zlib level in 0\.\.9, found 10"),
    "no novel-view camera": (
        lambda t, r: ["--dataset", _dataset_yaml(t, "name: x\nsplit:\n  novel_view_count: 0\n")],
        r"dataset\.yaml: section 'split': the novel_view split is empty \(0 cameras, 2 frames; novel_view_cameras: "
        r"None, novel_view_count: 0\); train, novel_view and novel_pose each need at least one camera and frame; the "
        r"capture has cameras \['cam00', 'cam01', 'cam02'\] and frames \[0, 1, 2\]"),
    "no novel-pose frame": (
        lambda t, r: ["--dataset", _dataset_yaml(t, "name: x\nsplit:\n  novel_pose_fraction: 0.0\n")],
        r"dataset\.yaml: section 'split': the novel_pose split is empty \(3 cameras, 0 frames; novel_pose_frames: "
        r"None, novel_pose_fraction: 0\.0, novel_pose_cameras: None\)"),
    "novel-view images all missing": (
        lambda t, r: _list_missing(r, "cam02", range(3))
        + ["--dataset", _dataset_yaml(t, "name: x\nsplit:\n  novel_view_cameras: [cam02]\n")],
        r"dataset\.yaml: section 'split': none of the novel_view split's images exist in \S+/s \(cameras "
        r"\['cam02'\], frames \[0, 1\]: all absent or listed as missing\)"),
    "body model of random bytes": (
        lambda t, r: (r / "body_model.npz").write_bytes(np.random.default_rng(0).bytes(999)) and [],
        r"^preprocess: error: \S*body_model\.npz: not a valid npz archive \(the file starts with b'.*'\); expected an "
        r"SMPL-X model with \['v_template', .*\], a zip of \.npy arrays as numpy\.savez writes\n$"),
    "parameters of random bytes": (
        lambda t, r: (r / "smpl_params.npz").write_bytes(np.random.default_rng(0).bytes(999)) and [],
        r"^preprocess: error: \S*smpl_params\.npz: not a valid npz archive \(the file starts with b'.*'\); expected "
        r"SMPL-X parameters \(betas, global_orient, transl, body_pose, \.\.\.\), a zip of \.npy arrays as "
        r"numpy\.savez writes\n$"),
    "uncalibrated camera folder": (
        lambda t, r: shutil.copytree(r / "images" / "cam02", r / "images" / "cam03") and [],
        r"images/cam03: camera folder not listed in .*calibration\.json"),
}


@pytest.mark.parametrize("case", sorted(BAD_RUNS))
def test_bad_input_exits_with_a_message_and_writes_nothing(tmp_path, capsys, case):
    root = write_thuman4(tmp_path / "s", cameras=3, frames=3)
    make_args, message = BAD_RUNS[case]
    extra = make_args(tmp_path, root)
    args = ["--input", str(root), "--output", str(tmp_path / "out"), "--preset", "test", "--no-progress", *extra]
    assert run_cli(main, args) == 1
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert not (tmp_path / "out").exists() and _leftovers(tmp_path) == []


# -- protocol splits ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("cfg, message", [
    (SplitConfig(novel_pose_cameras=["cam1", "cam7"]), r"'novel_pose_cameras' names camera\(s\) \['cam7'\]"),
    (SplitConfig(drop_train_cameras={"s": ["x"]}), r"'drop_train_cameras\.s' names camera\(s\) \['x'\]"),
    (SplitConfig(train_frames=[0, 5], novel_pose_frames=[5, 9]), r"train and novel-pose frames overlap \(first: \[5\]\)"),
    (SplitConfig(novel_pose_frames=[20, 30]), r"'novel_pose_frames' \[20, 30\] contains none of the capture's frames \(0\.\.9\)"),
    (SplitConfig(train_frames=[5, 1]), r"'train_frames' must be \[first, last\]"),
    (SplitConfig(novel_view_count=4), r"'novel_view_count' 4 must leave at least one of the 4 cameras"),
    (SplitConfig(novel_view_count=1, drop_train_cameras={"s": ["cam0", "cam1", "cam3"]}),
     r"the train split is empty \(0 cameras, 7 frames; .*drop_train_cameras: \{'s': \['cam0', 'cam1', 'cam3'\]\}"),
    (SplitConfig(novel_view_count=0), r"novel_view split is empty \(0 cameras, 7 frames; novel_view_cameras: None, "
                                      r"novel_view_count: 0\).*cameras \['cam0', 'cam1', 'cam2', 'cam3'\] and frames "
                                      r"\[0, 1, ..., 9\] \(10\)"),
    (SplitConfig(novel_view_cameras=[]), r"novel_view split is empty \(0 cameras"),
    (SplitConfig(novel_pose_fraction=0.0), r"novel_pose split is empty \(4 cameras, 0 frames; novel_pose_frames: None, "
                                           r"novel_pose_fraction: 0\.0"),
    (SplitConfig(novel_pose_cameras=[]),
     r"novel_pose split is empty \(0 cameras, 3 frames; .*novel_pose_cameras: \[\]"),
])
def test_split_errors(cfg, message):
    with pytest.raises(CaptureError, match=message):
        make_split([f"cam{i}" for i in range(4)], list(range(10)), cfg, "s", "where.yaml")


# -- encodings and resuming ----------------------------------------------------------------------------------

RESUME_SPLIT = SplitConfig(novel_view_cameras=["cam02"], novel_pose_frames=[4, 4])
# train: cam00, cam01 x frames 0..3; held out: cam02 x 0..3 (novel view) and every camera at frame 4 (novel pose)
TRAIN = [(c, f) for c in ("cam00", "cam01") for f in range(4)]
HELD_OUT = [("cam02", f) for f in range(4)] + [(c, 4) for c in ("cam00", "cam01", "cam02")]
TIMINGS = ("seconds", "seconds_images", "seconds_check", "images_resumed")


class Killed(BaseException):
    """Stands for SIGKILL: not an Exception, so nothing on its way out handles it."""


@pytest.fixture(scope="module")
def resume_raw(tmp_path_factory) -> Path:
    return write_thuman4(tmp_path_factory.mktemp("resume") / "s", cameras=3, frames=5, width=160, height=128)


def _preprocess(raw_root: Path, out: Path, **cfg) -> dict:
    return preprocess_capture(Thuman4Capture(raw_root), out, PreprocessConfig(**cfg), raw_root / "body_model.npz",
                              RESUME_SPLIT, "s", progress=False)


def _die_after(monkeypatch, views: int, dead_pid: int) -> None:
    """The writer dies while writing the image of view `views` + 1 (one worker: views complete in order), leaving
    half of its bytes in a temporary as a killed process of id `dead_pid` would."""
    from pig.stages import preprocess

    calls = iter(range(1, 10**6))
    real = preprocess._write_encoded

    def dying(path, image, suffix, params):
        if next(calls) == 2 * views + 1:
            data = cv2.imencode(suffix, image, params)[1]
            path.with_name(f".{path.stem}.{dead_pid}.tmp{suffix}").write_bytes(data[:data.size // 2].tobytes())
            raise Killed
        real(path, image, suffix, params)

    monkeypatch.setattr(preprocess, "_write_encoded", dying)


def _count_writes(monkeypatch) -> list[Path]:
    from pig.stages import preprocess

    written, real = [], preprocess._write_encoded
    monkeypatch.setattr(preprocess, "_write_encoded", lambda path, *args: written.append(path) or real(path, *args))
    return written


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _jpeg_header(data: bytes) -> tuple[int, list[int]]:
    """(first luminance quantiser, sampling factor byte of each component) from a baseline JPEG's DQT and SOF0."""
    dqt, sof = data.index(b"\xff\xdb"), data.index(b"\xff\xc0")
    components = data[sof + 9]
    return data[dqt + 5], [data[sof + 11 + 3 * i] for i in range(components)]


def test_training_views_are_jpeg_444_held_out_views_and_masks_lossless_png(resume_raw, tmp_path):
    _preprocess(resume_raw, tmp_path / "out", jpeg_quality=80)
    out = tmp_path / "out"
    for cam, frame in TRAIN + HELD_OUT:
        names = sorted(p.name for p in (out / "images" / cam).glob(f"{frame:08d}.*"))
        assert names == [f"{frame:08d}.{'jpg' if (cam, frame) in TRAIN else 'png'}"], (cam, frame)
        mask = (out / "masks" / cam / f"{frame:08d}.png").read_bytes()
        assert mask[24:26] == b"\x01\x00"  # IHDR: bit depth 1, greyscale
    # IJG quality scaling of the standard luminance table's first entry (16): q >= 50 -> (16 (200 - 2q) + 50) / 100.
    quantiser, sampling = _jpeg_header((out / "images" / "cam00" / "00000001.jpg").read_bytes())
    assert quantiser == (16 * (200 - 2 * 80) + 50) // 100 and sampling == [0x11, 0x11, 0x11]
    _preprocess(resume_raw, tmp_path / "swapped", train_encoding="png", heldout_encoding="jpeg", jpeg_quality=95)
    assert _jpeg_header((tmp_path / "swapped" / "images" / "cam02" / "00000000.jpg").read_bytes())[0] == 2
    assert (tmp_path / "swapped" / "images" / "cam00" / "00000000.png").is_file()


@pytest.fixture
def dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


@pytest.fixture(scope="module")
def uninterrupted(resume_raw, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("uninterrupted") / "out"
    return out, _preprocess(resume_raw, out, workers=1)


def _partial_views(partial: Path) -> set[tuple[str, int]]:
    """The views whose image and mask lie complete in the work folder; asserts nothing else is under a final name."""
    views = set()
    for mask in (p for p in partial.glob("masks/*/*.png") if not p.name.startswith(".")):
        images = list(mask.parent.parent.parent.glob(f"images/{mask.parent.name}/{mask.stem}.*"))
        assert len(images) == 1, mask
        read_image(images[0])  # strict: a cut-short file fails
        read_image(mask, cv2.IMREAD_GRAYSCALE)
        views.add((mask.parent.name, int(mask.stem)))
    images = {(p.parent.name, int(p.stem)) for p in partial.glob("images/*/*.*") if not p.name.startswith(".")}
    assert images == views  # the image before the mask, nothing after the last complete view
    return views


def test_killed_run_resumes_without_partial_files_to_the_bytes_of_an_uninterrupted_run(
        resume_raw, uninterrupted, tmp_path, monkeypatch, dead_pid):
    out = tmp_path / "out"
    _die_after(monkeypatch, 5, dead_pid)
    with pytest.raises(Killed):
        _preprocess(resume_raw, out, workers=1)
    partial = tmp_path / ".out.partial"
    assert not out.exists() and _leftovers(tmp_path) == [".out.partial"]
    done = _partial_views(partial)
    assert len(done) >= 5  # the worker may finish a view it had taken before the main thread saw the error
    half_written = [p.name for p in partial.rglob(".*") if p.parent.parent.name == "images"]
    assert len(half_written) == 1 and half_written[0].endswith(".tmp.jpg")
    (tmp_path / f".out.{dead_pid}.tmp").mkdir()  # an orphan of another killed run: removed, the work folder kept

    monkeypatch.undo()
    written = _count_writes(monkeypatch)
    report = _preprocess(resume_raw, out, workers=2, min_iou=0.5)  # neither changes an image: the work is resumed
    assert report["images_resumed"] == len(done) and report["images"] == len(TRAIN + HELD_OUT)
    assert len(written) == 2 * (report["images"] - len(done))
    assert not {(p.parent.name, int(p.stem)) for p in written} & done
    assert _leftovers(tmp_path) == [] and [p for p in out.rglob(".*") if p.name != ".pig-stage"] == []

    reference, expected = uninterrupted
    got, want = _files(out), _files(reference)
    assert sorted(got) == sorted(want) and any(name.endswith(".jpg") for name in got)
    assert {k for k in got if got[k] != want[k]} == {"report.json"}
    resumed = json.loads(got.pop("report.json"))
    assert resumed["projection_check"]["cameras"] == expected["projection_check"]["cameras"]
    assert {k: v for k, v in resumed.items() if k not in (*TIMINGS, "config", "projection_check")} == \
        {k: v for k, v in expected.items() if k not in (*TIMINGS, "config", "projection_check")}


KILLED_CHILD = """
import os, signal, sys
from pathlib import Path
import cv2
from pig.data.splits import SplitConfig
from pig.data.thuman4 import Thuman4Capture
from pig.stages import preprocess
from pig._io import atomic_path

raw, out, views = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
calls, real = iter(range(1, 10**6)), preprocess._write_encoded

def dying(path, image, suffix, params):
    if next(calls) == 2 * views + 1:  # SIGKILL in the middle of writing an image
        data = cv2.imencode(suffix, image, params)[1]
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            handle.write(data[:data.size // 2])
            handle.flush()
            os.kill(os.getpid(), signal.SIGKILL)
    real(path, image, suffix, params)

preprocess._write_encoded = dying
preprocess.preprocess_capture(Thuman4Capture(raw), out, preprocess.PreprocessConfig(workers=1), raw / "body_model.npz",
                              SplitConfig(novel_view_cameras=["cam02"], novel_pose_frames=[4, 4]), "s", progress=False)
"""


@pytest.mark.slow
def test_sigkilled_run_resumes_to_the_bytes_of_an_uninterrupted_run(resume_raw, uninterrupted, tmp_path):
    out = tmp_path / "out"
    child = subprocess.run([sys.executable, "-c", KILLED_CHILD, str(resume_raw), str(out), "6"],
                           env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True)
    assert child.returncode == -9, child.stderr
    assert not out.exists() and sorted(_leftovers(tmp_path)) == [".out.lock", ".out.partial"]
    assert len(_partial_views(tmp_path / ".out.partial")) == 6
    assert len([p for p in (tmp_path / ".out.partial").rglob(".*.tmp.*")]) == 1  # the image cut short, hidden
    report = _preprocess(resume_raw, out, workers=2)
    assert report["images_resumed"] == 6 and _leftovers(tmp_path) == []
    got, want = _files(out), _files(uninterrupted[0])
    assert {k for k in got.keys() | want.keys() if got.get(k) != want.get(k)} == {"report.json"}


def _replace_raw_image(root: Path) -> dict:
    image = root / "images" / "cam01" / "00000000.jpg"
    image.write_bytes((root / "images" / "cam01" / "00000001.jpg").read_bytes())  # another frame's bytes
    return {}


@pytest.mark.parametrize("change", [lambda root: {"jpeg_quality": 80}, _replace_raw_image],
                         ids=["jpeg quality", "raw image replaced"])
def test_changed_settings_start_the_unfinished_work_afresh(resume_raw, tmp_path, monkeypatch, dead_pid, change):
    raw, out = tmp_path / "s", tmp_path / "out"
    shutil.copytree(resume_raw, raw)
    _die_after(monkeypatch, 4, dead_pid)
    with pytest.raises(Killed):
        _preprocess(raw, out, workers=1)
    assert len(_partial_views(tmp_path / ".out.partial")) >= 4
    monkeypatch.undo()
    written = _count_writes(monkeypatch)
    report = _preprocess(raw, out, **change(raw))
    assert report["images_resumed"] == 0 and len(written) == 2 * report["images"]
    quality = report["config"]["jpeg_quality"]
    assert all(_jpeg_header(p.read_bytes())[0] == (16 * (200 - 2 * quality) + 50) // 100
               for p in out.glob("images/*/*.jpg"))
    assert _leftovers(tmp_path) == []


def test_a_second_run_on_the_same_output_is_refused_while_the_first_lives(resume_raw, tmp_path, capsys):
    out = tmp_path / "out"
    script = ("import sys, time\nfrom pathlib import Path\nfrom pig._outputs import output_lock\n"
              "with output_lock(Path(sys.argv[1]), 'preprocess'):\n    print('held', flush=True)\n    time.sleep(60)\n")
    holder = subprocess.Popen([sys.executable, "-c", script, str(out)], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        assert holder.stdout.readline() == "held\n"
        assert _run(resume_raw, out) == 1
        assert (f"preprocess: error: {out}: another preprocess run (pid {holder.pid}) is writing it; wait for it to "
                f"finish or stop it, then run again (lock file {tmp_path / '.out.lock'})") in capsys.readouterr().err
        assert not out.exists() and _leftovers(tmp_path) == [".out.lock"]
    finally:
        holder.kill()
        holder.wait()
    assert _run(resume_raw, out) == 0  # the killed holder's lock file is no obstacle
    assert _leftovers(tmp_path) == [] and (out / "report.json").is_file()


def test_a_foreign_folder_where_the_work_would_be_kept_is_left_alone(resume_raw, tmp_path, capsys):
    mine = tmp_path / ".out.partial" / "notes.txt"
    mine.parent.mkdir()
    mine.write_text("not the stage's")
    assert _run(resume_raw, tmp_path / "out") == 1
    assert (f"preprocess: error: {mine.parent}: a folder the preprocess stage did not write lies where it keeps its "
            "unfinished work; move it away") in capsys.readouterr().err
    assert [p.name for p in mine.parent.iterdir()] == ["notes.txt"] and _leftovers(tmp_path) == [".out.partial"]


# -- the synthetic capture (engineer A's generator, `test` preset) -------------------------------------------

@pytest.fixture(scope="module")
def synthetic_raw(tmp_path_factory):
    from pig.config import load_preset
    from pig.data.synthetic import SyntheticConfig, generate_capture

    cfg = load_section(load_preset("test"), "synthetic", SyntheticConfig)
    return generate_capture(tmp_path_factory.mktemp("synthetic") / "subject00", cfg, progress=False)


@pytest.mark.slow
def test_synthetic_capture_passes_with_iou_above_0_9_on_every_camera(synthetic_raw, tmp_path):
    assert _run(synthetic_raw, tmp_path / "capture", "--dataset", "synthetic") == 0
    report = json.loads((tmp_path / "capture" / "report.json").read_text())
    cameras = report["projection_check"]["cameras"]
    assert len(cameras) == len(json.loads((synthetic_raw / "calibration.json").read_text()))
    assert all(c["iou"] >= 0.9 for c in cameras.values()), cameras
    # The skirt: the plain IoU is clearly lower, so the tolerance is doing the work it is documented to do.
    assert all(c["raw_iou"] < c["iou"] for c in cameras.values())
    capture = Capture.load(tmp_path / "capture")
    assert capture.split["novel_pose"]["frames"] == capture.frames[-2:]  # ceil(25% of 6 frames)


@pytest.mark.slow
def test_synthetic_capture_with_camera_to_world_calibration_fails_naming_it(synthetic_raw, tmp_path, capsys):
    raw = tmp_path / "subject00"
    shutil.copytree(synthetic_raw, raw)
    calibration = json.loads((raw / "calibration.json").read_text())
    for cam in calibration.values():
        R, T = np.asarray(cam["R"], dtype=np.float64).reshape(3, 3), np.asarray(cam["T"], dtype=np.float64)
        cam["R"], cam["T"] = R.T.tolist(), (-R.T @ T).tolist()
    (raw / "calibration.json").write_text(json.dumps(calibration))
    assert _run(raw, tmp_path / "capture", "--dataset", "synthetic") == 1
    assert "calibration looks camera-to-world; invert it" in capsys.readouterr().err
    assert not (tmp_path / "capture").exists() and _leftovers(tmp_path) == [".capture.partial"]
    # Fixed, the rerun starts afresh (a raw file changed) and passes.
    shutil.copy(synthetic_raw / "calibration.json", raw / "calibration.json")
    assert _run(raw, tmp_path / "capture", "--dataset", "synthetic") == 0
    report = json.loads((tmp_path / "capture" / "report.json").read_text())
    assert report["images_resumed"] == 0 and report["images"] > 0 and _leftovers(tmp_path) == []
