"""The synthetic capture: exact THuman4 layout, consistency of images, masks, calibration and parameters,
determinism, and a garment that is off the body and moves beyond skinning."""
import dataclasses
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from pig.body.model import SMPLX_JOINT_NAMES, BodyModel
from pig.body.params import from_thuman
from pig.config import ConfigError, load_preset, load_section
from pig.data.formats import open_capture
from pig.data.synthetic import SyntheticConfig, SyntheticError, build_scene, generate_capture
from pig.data.synthetic import capture as synthetic_capture
from pig.data.synthetic import workers as synthetic_workers
from pig.data.synthetic.garment import AROUND
from pig.data.synthetic.render import RAY_CACHE_BYTES
from pig.data.synthetic.rig import pixel_rays
from pig.data.synthetic.texture import ValueNoise, body_albedo, garment_albedo
from pig.stages import generate
from pig._cli import run_cli
from pig._outputs import MARKER

J = {name: i for i, name in enumerate(SMPLX_JOINT_NAMES)}
TOP_LEVEL = {"images", "masks", "calibration.json", "smpl_params.npz", "body_model.npz", "gt_meshes.npz", MARKER}


@pytest.fixture(scope="module")
def cfg():
    return load_section(load_preset("test"), "synthetic", SyntheticConfig)


@pytest.fixture(scope="module")
def capture(tmp_path_factory, cfg):
    return generate_capture(tmp_path_factory.mktemp("synthetic") / "subject00", cfg, progress=False)


@pytest.fixture(scope="module")
def scene(cfg):
    return build_scene(cfg)


def load_npz(path):
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def read_gray(path):
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def test_exact_thuman4_layout(capture, cfg):
    assert {p.name for p in capture.iterdir()} == TOP_LEVEL
    cams = [f"cam{i:02d}" for i in range(cfg.cameras)]
    names = [f"{f:08d}.jpg" for f in range(cfg.frames)]
    for kind in ("images", "masks"):
        assert sorted(p.name for p in (capture / kind).iterdir()) == cams
        for cam in cams:
            assert sorted(p.name for p in (capture / kind / cam).iterdir()) == names
    assert cv2.imread(str(capture / "images/cam00/00000000.jpg")).shape == (cfg.height, cfg.width, 3)
    assert read_gray(capture / "masks/cam00/00000000.jpg").shape == (cfg.height, cfg.width)

    calibration = json.loads((capture / "calibration.json").read_text())
    assert list(calibration) == cams
    for entry in calibration.values():
        assert set(entry) == {"K", "R", "T", "imgSize", "distCoeff"}
        K, R = np.array(entry["K"]), np.array(entry["R"])
        assert K.shape == (3, 3) and np.array_equal(K[2], [0, 0, 1])
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert len(entry["T"]) == 3 and entry["imgSize"] == [cfg.width, cfg.height] and len(entry["distCoeff"]) == 5

    n = cfg.frames
    shapes = {"betas": (1, 10), "global_orient": (n, 3), "transl": (n, 3), "body_pose": (n, 63), "jaw_pose": (n, 3),
              "expression": (n, 10), "left_hand_pose": (n, 45), "right_hand_pose": (n, 45)}
    assert {k: v.shape for k, v in load_npz(capture / "smpl_params.npz").items()} == shapes

    meshes = load_npz(capture / "gt_meshes.npz")
    model = BodyModel.from_file(capture / "body_model.npz")
    v, vg = len(model.v_template), len(meshes["garment_rest_vertices"])
    assert meshes["body_vertices"].shape == (n, v, 3) and meshes["garment_vertices"].shape == (n, vg, 3)
    np.testing.assert_array_equal(meshes["body_faces"], model.faces.numpy())
    assert meshes["garment_faces"].max() == vg - 1


def test_thuman4_reader_opens_it(capture, cfg):
    raw = open_capture("thuman4", capture)
    assert list(raw.cameras) == [f"cam{i:02d}" for i in range(cfg.cameras)]
    assert raw.frames == list(range(cfg.frames))
    assert raw.read_image("cam03", 2).shape == (cfg.height, cfg.width, 3)
    assert np.abs(raw.cameras["cam01"].dist).sum() > 1e-4  # the reader sees the lens distortion


def test_parameters_and_model_reproduce_the_true_body(capture):
    params = from_thuman(load_npz(capture / "smpl_params.npz"), "smpl_params.npz")
    model = BodyModel.from_file(capture / "body_model.npz", dtype=torch.float64)
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    with torch.no_grad():
        posed = model(t(params.full_pose), t(params.betas), t(params.expression), t(params.transl)).vertices.numpy()
    truth = load_npz(capture / "gt_meshes.npz")["body_vertices"]
    np.testing.assert_allclose(posed, truth, atol=1e-5)  # float32 storage


def test_motion_bends_elbows_knees_and_spine(scene):
    pose = from_thuman(scene.thuman_params, "x").full_pose
    angle = np.linalg.norm(pose, axis=-1)
    assert angle[:, J["left_elbow"]].max() > 0.6 and angle[:, J["right_knee"]].max() > 0.3
    assert np.ptp(pose[:, J["spine1"], 0]) > 0.02 and angle[:, J["spine2"]].max() > 0.05
    assert np.ptp(pose[:, 0, 1]) > 0.2  # the body turns
    assert np.abs(pose[:, [J["left_eye"], J["right_eye"]]]).max() == 0


def test_motion_of_thuman4_length_never_shows_a_pose_twice():
    """2500 frames at 30 fps (THuman4's 2000 + 500, 83 s): every frame is nearer its neighbours than any frame two
    or more apart, so no two frames of a long capture share ground-truth pixels (round frequencies repeated every
    20 s)."""
    from pig.data.synthetic.motion import Motion

    motion, times = Motion(SyntheticConfig().seed, 0.0), np.arange(2500) / 30
    # Joint angles (rad) and the translation (m, x5: a 0.2 m shift reads like a 1 rad turn) as one vector a frame.
    x = np.concatenate([motion.full_pose(times).reshape(len(times), -1), 5 * motion.transl(times)], axis=1)
    steps = np.linalg.norm(np.diff(x, axis=0), axis=1)
    squared = (x * x).sum(axis=1)
    gaps = np.sqrt(np.maximum(squared[:, None] + squared[None] - 2 * x @ x.T, 0.0))
    frame = np.arange(len(times))
    gaps[np.abs(frame[:, None] - frame[None]) < 2] = np.inf
    assert gaps.min() > steps.max() > 0

def test_deterministic_per_seed(capture, tmp_path, cfg, scene):
    again = tmp_path / "again"
    assert generate.main(["--output", str(again), "--preset", "test", "--quiet"]) == 0
    files = sorted(p.relative_to(capture) for p in capture.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        if rel.suffix == ".npz":  # zip members carry a timestamp: compare the arrays
            first, second = load_npz(capture / rel), load_npz(again / rel)
            assert first.keys() == second.keys() and all(np.array_equal(first[k], second[k]) for k in first)
        else:
            assert (capture / rel).read_bytes() == (again / rel).read_bytes(), rel
    other = build_scene(dataclasses.replace(cfg, seed=cfg.seed + 1))
    assert not np.allclose(other.cameras[0].K, scene.cameras[0].K)
    assert not np.allclose(other.thuman_params["body_pose"], scene.thuman_params["body_pose"])


@pytest.mark.slow  # spawns two interpreters that import torch
def test_worker_processes_write_the_same_capture(tmp_path, cfg):
    small = dataclasses.replace(cfg, cameras=3, frames=2, width=40, height=32)
    one = generate_capture(tmp_path / "one", small, progress=False)
    timeline = synthetic_workers.RenderTimeline()
    two = generate_capture(tmp_path / "two", dataclasses.replace(small, workers=2), progress=False, timeline=timeline)
    images = sorted(p.relative_to(one) for p in one.rglob("*.jpg"))
    assert len(images) == 2 * 3 * 2
    assert all((one / rel).read_bytes() == (two / rel).read_bytes() for rel in images)
    # The timeline: every view once, from the workers (not this process), each task after its worker was ready.
    views = [(f, c) for r in timeline.tasks for f in r["frames"] for c in r["cameras"]]
    assert sorted(views) == [(f, c) for f in range(2) for c in range(3)]
    assert timeline.workers == 2 and 1 <= len({r["pid"] for r in timeline.tasks}) <= 2
    assert os.getpid() not in {r["pid"] for r in timeline.tasks}
    assert all(timeline.started <= r["ready"] <= r["start"] <= r["end"] <= timeline.ended for r in timeline.tasks)
    assert sum(r["parts"].get("rays_computed", 0) + r["parts"].get("rays_cached", 0) for r in timeline.tasks) == 6


@pytest.mark.parametrize("cameras, frames, width, height, supersample, workers", [
    (24, 10, 1330, 1150, 2, 16), (24, 120, 1330, 1150, 2, 16), (24, 10, 1330, 1150, 2, 32), (7, 5, 1330, 1150, 2, 3),
    (12, 24, 256, 256, 1, 2), (60, 3, 2048, 1500, 1, 64), (3, 2, 40, 32, 1, 2), (1, 1, 8, 8, 1, 4)])
def test_render_tasks_cover_every_view_once_in_groups_that_fit_the_ray_cache(cameras, frames, width, height,
                                                                             supersample, workers):
    run = SyntheticConfig(cameras=cameras, frames=frames, width=width, height=height, supersample=supersample,
                          workers=workers)
    tasks = synthetic_capture._tasks(run)
    views = [(f, c) for task_frames, cams in tasks for f in task_frames for c in cams]
    assert sorted(views) == [(f, c) for f in range(frames) for c in range(cameras)]
    ray_bytes = width * height * supersample**2 * 3 * 4
    assert all(len(cams) == 1 or len(cams) * ray_bytes <= RAY_CACHE_BYTES for _, cams in tasks)


@pytest.mark.parametrize("supersample", [1, 2])
def test_render_tasks_of_the_gpu_holds_compute_each_cameras_rays_at_most_twice_in_one_round(supersample):
    # benchmarks/fit_gpu.py's subject: 24 cameras x 10 frames at the paper's size (supersample 1 unless asked), 16
    # workers. A worker takes tasks in any order, so a task computes its cameras' rays (about a view's work each);
    # the old split computed rays for every view (20 tasks of one frame by 14 or 10 cameras at supersample 1, 80 of
    # one frame by 3 at 2), in 2 and 5 rounds.
    run = SyntheticConfig(cameras=24, frames=10, width=1330, height=1150, supersample=supersample, workers=16)
    tasks = synthetic_capture._tasks(run)
    assert sum(len(cams) for _, cams in tasks) <= 2 * run.cameras
    assert len(tasks) == run.workers  # one round of equal tasks: no worker waits on a tail
    assert len({(len(frames), len(cams)) for frames, cams in tasks}) == 1


@pytest.mark.slow  # spawns an interpreter
def test_render_workers_import_no_torch():
    # Their imports are most of their start-up (benchmarks/NOTES.md): numpy, OpenCV, trimesh and Embree suffice.
    with synthetic_workers.worker_pool(1, (None, None, None, None, "unused", 1, 90)) as pool:
        assert pool.apply(eval, ("sorted({'torch', 'pig.data.synthetic.workers'} & set(__import__('sys').modules))",)) \
            == ["pig.data.synthetic.workers"]


@pytest.mark.slow  # spawns interpreters that import torch
def test_render_workers_do_not_import_the_callers_main_module(tmp_path):
    # spawn re-imports the main script in every worker (as __mp_main__); benchmarks/fit_gpu.py's imports torch's
    # compiler and the fitting code, which the workers do not need.
    script = tmp_path / "caller.py"
    script.write_text(textwrap.dedent(f"""
        import pathlib, sys
        if __name__ != "__main__":
            pathlib.Path({str(tmp_path / "imported")!r}).write_text(__name__)
        from pig.data.synthetic import SyntheticConfig, generate_capture
        if __name__ == "__main__":
            cfg = SyntheticConfig(cameras=2, frames=2, width=16, height=16, workers=2)
            generate_capture(pathlib.Path({str(tmp_path / "subject")!r}), cfg, progress=False)
            main = sys.modules["__main__"]
            print(main.__file__, main.__spec__)
    """))
    source = str(Path(synthetic_capture.__file__).parents[3])  # this checkout's pig, not an installed one
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": source})
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(script), "None"]  # this process's main module as it was
    assert len(list((tmp_path / "subject" / "images").rglob("*.jpg"))) == 4
    assert not (tmp_path / "imported").exists()


@pytest.mark.slow  # spawns an interpreter that imports torch
def test_render_workers_start_with_one_blas_thread_and_leave_this_process_alone(monkeypatch):
    from pig.data.synthetic.workers import WORKER_THREAD_LIMITS, worker_pool

    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    with worker_pool(1, (None, None, None, None, "unused", 1, 90)) as pool:
        seen = {name: pool.apply(os.getenv, (name,)) for name in WORKER_THREAD_LIMITS}
    assert seen == WORKER_THREAD_LIMITS
    assert os.environ["OMP_NUM_THREADS"] == "7" and "OPENBLAS_NUM_THREADS" not in os.environ


def test_existing_output_is_refused_unless_it_is_a_generated_capture(tmp_path, capsys):
    foreign = tmp_path / "subject00"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert run_cli(generate.main, ["--output", str(foreign), "--preset", "test", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert f"generate: error: {foreign}: holds files the generate stage did not write (notes.txt); pass --overwrite" in err
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"] and [p.name for p in tmp_path.iterdir()] == ["subject00"]


def test_failed_generation_leaves_nothing(tmp_path, cfg, monkeypatch):
    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(synthetic_capture, "_render_all", fail)
    with pytest.raises(RuntimeError, match="disk full"):
        generate_capture(tmp_path / "subject00", cfg, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_bad_settings_are_named():
    with pytest.raises(SyntheticError, match="synthetic.cameras must be at least 1"):
        SyntheticConfig(cameras=0)
    with pytest.raises(ConfigError, match=r"test\.yaml: section 'synthetic': unknown key\(s\) \['camras'\]"):
        load_section(load_preset("test"), "synthetic", SyntheticConfig, {"camras": 3})
    with pytest.raises(SyntheticError, match="nowhere.npz does not exist"):
        synthetic_capture.body_model_arrays(SyntheticConfig(body_model="/nowhere.npz"))


# ---------------------------------------------------------------- garment


def leg_vertices(scene):
    weights = scene.model_arrays["weights"]
    legs = [J[f"{s}_{p}"] for s in ("left", "right") for p in ("hip", "knee", "ankle", "foot")]
    return weights[:, legs].sum(axis=1) > 0.5


def test_hem_hangs_clear_of_the_legs(scene):
    legs = leg_vertices(scene)
    for t in range(len(scene.times)):
        distance, _ = cKDTree(scene.body_vertices[t][legs]).query(scene.garment_vertices[t][scene.hem])
        assert distance.min() >= 0.08, f"frame {t}: hem {distance.min():.3f} m from a leg"


def test_garment_is_an_open_tube(scene):
    mesh = trimesh.Trimesh(scene.garment_rest, scene.garment_faces, process=False)
    assert not mesh.is_watertight
    edges = mesh.edges_sorted
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = np.unique(unique[counts == 1])
    assert len(boundary) == 2 * AROUND  # waist ring and hem
    assert set(scene.hem) <= set(boundary)
    assert np.all(scene.garment_rest[scene.hem, 1] < scene.garment_rest[:, 1].min() + 0.06)


def best_skinning_residual(scene, vertex, transforms):
    """RMS over frames of the best per-vertex blend of the pelvis, spine and leg transforms (weights sum to 1)."""
    joints = [J[n] for n in ("pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2")]
    rest = scene.garment_rest[vertex]
    moved = np.stack([(transforms[:, j, :3, :3] @ rest + transforms[:, j, :3, 3]).ravel() for j in joints], axis=1)
    target = (scene.garment_vertices[:, vertex] - scene.thuman_params["transl"]).ravel()
    system = moved[:, 1:] - moved[:, :1]
    rhs = target - moved[:, 0]
    weights, *_ = np.linalg.lstsq(system, rhs, rcond=None)
    return np.sqrt(((system @ weights - rhs).reshape(-1, 3) ** 2).sum(axis=1).mean())


def body_transforms(scene):
    params = from_thuman(scene.thuman_params, "x")
    model = BodyModel(scene.model_arrays, dtype=torch.float64)
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    with torch.no_grad():
        return model(t(params.full_pose), t(params.betas), t(params.expression)).transforms.numpy()


def test_garment_motion_is_not_explained_by_skinning(scene):
    transforms = body_transforms(scene)
    hem = np.array([best_skinning_residual(scene, v, transforms) for v in scene.hem])
    assert np.median(hem) > 0.025 and hem.max() > 0.04
    # The free motion fades to nothing at the waist: there the skirt's own skinning is exact.
    waist = np.arange(AROUND)
    per_vertex = np.einsum("vj,tjrc->tvrc", scene.garment_weights[waist], transforms)
    skinned = np.einsum("tvrc,vc->tvr", per_vertex[..., :3, :3], scene.garment_rest[waist]) + per_vertex[..., :3, 3]
    skinned += scene.thuman_params["transl"][:, None].astype(np.float64)
    np.testing.assert_allclose(scene.garment_vertices[:, waist], skinned, atol=1e-9)


# ---------------------------------------------------------------- cameras, images, masks


def test_rays_follow_the_lens_distortion(scene):
    for camera in scene.cameras:
        k1, k2, p1, p2, k3 = camera.dist
        assert abs(k1) >= 0.02 and abs(p1) > 0 and abs(p2) > 0 and k3 == 0
        origin, directions = pixel_rays(camera, supersample=2)
        points = origin + 3.0 * directions.reshape(-1, 3)
        rvec = cv2.Rodrigues(camera.R)[0]
        projected = cv2.projectPoints(points, rvec, camera.T, camera.K, camera.dist)[0].reshape(-1, 2)
        offsets = np.array([-0.25, 0.25])
        u = (np.arange(camera.width)[:, None] + offsets).ravel()
        v = (np.arange(camera.height)[:, None] + offsets).ravel()
        expected = np.stack(np.meshgrid(u, v), axis=-1).reshape(camera.height, 2, camera.width, 2, 2)
        expected = expected.transpose(0, 2, 1, 3, 4).reshape(-1, 2)
        np.testing.assert_allclose(projected, expected, atol=1e-6)
        pinhole = cv2.projectPoints(points, rvec, camera.T, camera.K, np.zeros(5))[0].reshape(-1, 2)
        assert np.abs(pinhole - expected).max() > 0.1  # distortion visibly moves the image


def background(scene, camera):
    rows = np.linspace(0, 1, camera.height)[:, None, None]
    return scene.appearance.background[0] * (1 - rows) + scene.appearance.background[1] * rows


def test_masks_agree_with_image_foreground(capture, scene, cfg):
    kernel = np.ones((3, 3), np.uint8)
    for camera in scene.cameras:
        for frame in range(cfg.frames):
            name = f"{camera.name}/{frame:08d}.jpg"
            image = cv2.cvtColor(cv2.imread(str(capture / "images" / name)), cv2.COLOR_BGR2RGB) / 255.0
            matte = read_gray(capture / "masks" / name)
            assert np.mean((matte > 40) & (matte < 215)) < 0.02  # a binary matte up to JPEG ringing
            mask = matte > 128
            assert 0.03 < mask.mean() < 0.6
            outside = cv2.erode((~mask).astype(np.uint8), kernel, iterations=2) > 0
            inside = cv2.erode(mask.astype(np.uint8), kernel) > 0
            error = np.abs(image - background(scene, camera)).max(axis=-1)
            assert error[outside].mean() < 0.02 and np.percentile(error[outside], 99) < 0.08
            assert error[inside].mean() > 0.08  # the subject stands out: 4x the background's error bound


def test_masks_cover_the_projected_meshes(capture, scene, cfg):
    meshes = load_npz(capture / "gt_meshes.npz")
    # Fingers are thinner than a pixel at the test size, so pixel-centre rays may miss them.
    hands = scene.model_arrays["weights"][:, [J["left_wrist"], J["right_wrist"]] + list(range(25, 55))].sum(axis=1) > 0.1
    for frame in (0, cfg.frames - 1):
        points = np.concatenate([meshes["body_vertices"][frame][~hands], meshes["garment_vertices"][frame]])
        points = points.astype(np.float64)
        for camera in scene.cameras:
            mask = read_gray(capture / "masks" / camera.name / f"{frame:08d}.jpg") > 128
            grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            pixels = cv2.projectPoints(points, cv2.Rodrigues(camera.R)[0], camera.T, camera.K, camera.dist)[0]
            col, row = np.round(pixels.reshape(-1, 2)).astype(int).T
            assert (col >= 0).all() and (col < camera.width).all() and (row >= 0).all() and (row < camera.height).all()
            assert grown[row, col].mean() > 0.995


def test_texture_is_a_fine_function_of_canonical_position(scene):
    noise = ValueNoise(0)
    line = np.stack([np.full(500, 0.05), np.linspace(0.0, 0.5, 500), np.full(500, 0.1)], axis=1)  # 1 mm steps
    body = body_albedo(line, noise, scene.appearance.body_palette)
    skirt = garment_albedo(line * [1, -1, 1], noise, scene.appearance.garment_palette)
    for albedo in (body, skirt):
        changes = np.abs(np.diff(albedo, axis=0)).max(axis=1)
        assert (changes > 0.05).sum() >= 10  # pattern edges every few centimetres
    assert np.abs(body - skirt).mean() > 0.05
