"""The synthetic capture: a skirted, textured stand-in body in motion, filmed by distorted cameras, in the THuman4 layout.

It is the project's default dataset and test bed for the whole method (paper Sec. 3), with the true
per-frame meshes kept for geometry error; see DESIGN.md section 4.
"""
from __future__ import annotations

import functools
import multiprocessing
import multiprocessing.pool
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from pig.body.model import BodyModel
from pig.body.npz import read_npz
from pig.body.standin import make_standin_arrays
from pig.data.raw import RawCamera
from pig.progress import progress_bar
from pig._io import write_json
from pig._outputs import build_dir, claim_dir

from .config import SyntheticConfig, SyntheticError
from .garment import build_skirt, pose_skirt, secondary_motion
from .motion import Motion
from .render import RAY_CACHE_BYTES, SceneAppearance, render_frame
from .rig import make_ring


@functools.lru_cache(maxsize=2)
def _standin(seed: int) -> dict[str, np.ndarray]:
    return make_standin_arrays(seed)


def body_model_arrays(cfg: SyntheticConfig) -> dict[str, np.ndarray]:
    """The body model the capture is built on, as SMPL-X npz arrays."""
    if cfg.body_model is None:
        return {k: v.copy() for k, v in _standin(0).items()}
    path = Path(cfg.body_model)
    if not path.is_file():
        raise SyntheticError(f"synthetic.body_model: {path} does not exist (expected an SMPL-X model npz)")
    return read_npz(path, SyntheticError, "an SMPL-X model npz", pickled=("J_regressor",))


@dataclass
class SyntheticScene:
    """Everything about the capture except its images."""

    model_arrays: dict[str, np.ndarray]
    thuman_params: dict[str, np.ndarray]  # smpl_params.npz content (float32, as stored)
    body_vertices: np.ndarray  # (T, V, 3) world
    body_rest: np.ndarray  # (V, 3) shaped rest pose
    body_faces: np.ndarray
    garment_vertices: np.ndarray  # (T, Vg, 3) world
    garment_rest: np.ndarray  # (Vg, 3)
    garment_faces: np.ndarray
    garment_weights: np.ndarray  # (Vg, 55) the skinning part of the garment's motion
    hem: np.ndarray  # garment vertex ids of the open hem
    times: np.ndarray  # (T,) seconds
    cameras: list[RawCamera]
    appearance: SceneAppearance


def build_scene(cfg: SyntheticConfig) -> SyntheticScene:
    """Pose body and skirt over time and place the cameras (deterministic in `cfg.seed`)."""
    rng = np.random.default_rng(cfg.seed)
    arrays = body_model_arrays(cfg)
    model = BodyModel(arrays, source=cfg.body_model or "<stand-in>", dtype=torch.float64)
    betas = np.clip(rng.normal(0.0, 0.6, size=10), -1.5, 1.5)
    with torch.no_grad():
        rest = model(torch.zeros(1, 55, 3, dtype=torch.float64), torch.from_numpy(betas))
    shaped = rest.shaped_vertices[0].numpy()
    rest_joints = rest.joints[0].numpy()

    times = np.arange(cfg.frames) * (cfg.duration_s / cfg.frames)
    motion = Motion(cfg.seed, ground_offset=-shaped[:, 1].min())
    expression_phase = rng.uniform(0, 2 * np.pi, size=10)
    expression = 0.8 * np.sin(2 * np.pi * 0.4 * times[:, None] + expression_phase)
    full_pose = motion.full_pose(times)
    params = {
        "betas": betas[None],
        "global_orient": full_pose[:, 0],
        "transl": motion.transl(times),
        "body_pose": full_pose[:, 1:22].reshape(-1, 63),
        "jaw_pose": full_pose[:, 22],
        "expression": expression,
        "left_hand_pose": full_pose[:, 25:40].reshape(-1, 45),
        "right_hand_pose": full_pose[:, 40:55].reshape(-1, 45),
    }
    params = {k: v.astype(np.float32) for k, v in params.items()}
    # Pose from the stored float32 values, so the files reproduce the ground-truth meshes exactly.
    stored_pose = np.zeros_like(full_pose)
    stored_pose[:, 0] = params["global_orient"]
    stored_pose[:, 1:22] = params["body_pose"].reshape(-1, 21, 3)
    stored_pose[:, 22] = params["jaw_pose"]
    stored_pose[:, 25:40] = params["left_hand_pose"].reshape(-1, 15, 3)
    stored_pose[:, 40:55] = params["right_hand_pose"].reshape(-1, 15, 3)
    t64 = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    with torch.no_grad():
        posed = model(t64(stored_pose), t64(params["betas"]), t64(params["expression"]), t64(params["transl"]))

    skirt = build_skirt(shaped, rest_joints, arrays["weights"])
    pelvis = rest_joints[0]
    dynamics = secondary_motion(times, lambda t: pelvis + motion.transl(t), lambda t: motion.full_pose(t)[:, 0, 1])
    garment = pose_skirt(skirt, posed.transforms.numpy(), params["transl"].astype(np.float64), dynamics,
                         wave_phase=rng.uniform(0, 2 * np.pi))

    height = shaped[:, 1].max() - shaped[:, 1].min()
    centre = np.array([0.0, 0.5 * height, 0.0])
    centre[[0, 2]] = (pelvis + params["transl"]).mean(axis=0)[[0, 2]]
    cameras = make_ring(cfg.cameras, cfg.width, cfg.height, centre, height, rng, cfg.distortion, cfg.camera_distance)
    appearance = SceneAppearance(
        body_faces=np.asarray(arrays["f"], dtype=np.int64),
        garment_faces=skirt.faces,
        body_canonical=shaped - pelvis,
        garment_canonical=skirt.rest - skirt.centre,
        body_palette=_palette(rng, 4),
        garment_palette=_palette(rng, 3),
        background=np.array([[0.32, 0.34, 0.38], [0.18, 0.18, 0.2]]),
        seed=cfg.seed,
    )
    return SyntheticScene(arrays, params, posed.vertices.numpy(), shaped, appearance.body_faces, garment, skirt.rest,
                          skirt.faces, skirt.weights, skirt.hem, times, cameras, appearance)


def _palette(rng: np.random.Generator, count: int) -> np.ndarray:
    """Distinct saturated colours; the first entry of a body palette is a skin tone."""
    hues = (rng.uniform() + np.arange(count) / count) % 1.0
    hsv = np.stack([hues * 180, np.full(count, 150.0), rng.uniform(140, 230, size=count)], axis=1)
    rgb = cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0] / 255.0
    if count == 4:
        rgb[0] = np.array([0.85, 0.64, 0.52]) * rng.uniform(0.6, 1.05)
    return rgb


def calibration_json(cameras: list[RawCamera]) -> dict:
    return {
        cam.name: {"K": cam.K.tolist(), "R": cam.R.tolist(), "T": cam.T.tolist(), "imgSize": [cam.width, cam.height],
                   "distCoeff": cam.dist.tolist()}
        for cam in cameras
    }


_WORKER: dict = {}


def _init_worker(appearance, cameras, body, garment, root, supersample, quality) -> None:
    _WORKER.update(appearance=appearance, cameras=cameras, body=body, garment=garment, root=Path(root),
                   supersample=supersample, quality=quality)
    cv2.setNumThreads(1)


def _render_and_write(task: tuple[list[int], list[int]]) -> int:
    """Render and write the views of some frames seen by some cameras; returns the number of views."""
    frames, camera_ids = task
    w = _WORKER
    cameras = [w["cameras"][c] for c in camera_ids]
    for frame in frames:
        for camera, rgb, mask in render_frame(w["appearance"], w["body"][frame], w["garment"][frame], cameras,
                                              w["supersample"]):
            name = f"{frame:08d}.jpg"
            image = cv2.cvtColor((rgb * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
            _imwrite(w["root"] / "images" / camera.name / name, image, w["quality"])
            _imwrite(w["root"] / "masks" / camera.name / name, mask.astype(np.uint8) * 255, w["quality"])
    return len(frames) * len(cameras)


def _tasks(cfg: SyntheticConfig) -> list[tuple[list[int], list[int]]]:
    """(frames, cameras) work items: camera groups whose rays fit a worker's cache, frames split ~4 items per worker."""
    ray_bytes = cfg.width * cfg.height * cfg.supersample**2 * 3 * 4
    group = max(1, min(cfg.cameras, RAY_CACHE_BYTES // ray_bytes))
    camera_groups = [list(range(c, min(c + group, cfg.cameras))) for c in range(0, cfg.cameras, group)]
    step = max(1, round(cfg.frames * len(camera_groups) / (4 * cfg.workers)))
    frame_groups = [list(range(f, min(f + step, cfg.frames))) for f in range(0, cfg.frames, step)]
    return [(frames, cams) for frames in frame_groups for cams in camera_groups]


def _imwrite(path: Path, image: np.ndarray, quality: int) -> None:
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, quality]):
        raise OSError(f"could not write {path}")


def generate_capture(out_dir: Path, cfg: SyntheticConfig, overwrite: bool = False, progress: bool = True) -> Path:
    """Write a THuman4-layout subject folder at `out_dir` (built next to it, then renamed into place).

    Contents: images/camXX/%08d.jpg, masks/camXX/%08d.jpg (0/255), calibration.json, smpl_params.npz,
    body_model.npz (the model used) and gt_meshes.npz (true per-frame body and garment vertices).
    An existing `out_dir` is replaced only when it is an earlier generated capture, or with `overwrite`.
    """
    out_dir = claim_dir(out_dir, "generate", overwrite=overwrite)
    scene = build_scene(cfg)
    with build_dir(out_dir, "generate") as tmp:
        for kind in ("images", "masks"):
            for camera in scene.cameras:
                (tmp / kind / camera.name).mkdir(parents=True)
        write_json(tmp / "calibration.json", calibration_json(scene.cameras))
        np.savez(tmp / "smpl_params.npz", **scene.thuman_params)
        np.savez_compressed(tmp / "body_model.npz", **scene.model_arrays)
        np.savez_compressed(
            tmp / "gt_meshes.npz",
            body_vertices=scene.body_vertices.astype(np.float32), body_faces=scene.body_faces.astype(np.int32),
            garment_vertices=scene.garment_vertices.astype(np.float32),
            garment_faces=scene.garment_faces.astype(np.int32), body_rest_vertices=scene.body_rest.astype(np.float32),
            garment_rest_vertices=scene.garment_rest.astype(np.float32), garment_weights=scene.garment_weights,
            garment_hem=scene.hem, times=scene.times, frames=np.arange(cfg.frames),
        )
        _render_all(scene, tmp, cfg, progress)
    return out_dir


# Set for the render workers as they start: one BLAS (and OpenMP) thread each. OpenBLAS otherwise starts a thread per
# core of the host in every worker, and its idle threads spin: on a 64-core host 16 workers spent 57 CPU-minutes
# on 240 views, ~14 CPU-s a view against ~3 in one single-threaded process (benchmarks/NOTES.md, "Synthetic capture
# generator"). The workers already split the views across the cores.
WORKER_THREAD_LIMITS = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def worker_pool(workers: int, init: tuple) -> multiprocessing.pool.Pool:
    """`workers` spawned render processes (spawn, not fork: the parent holds torch's thread pools, which do not
    survive a fork), started with WORKER_THREAD_LIMITS in their environment; this process's is left as it was."""
    context = multiprocessing.get_context("spawn")
    saved = {name: os.environ.get(name) for name in WORKER_THREAD_LIMITS}
    os.environ.update(WORKER_THREAD_LIMITS)
    try:
        return context.Pool(workers, initializer=_init_worker, initargs=init)  # the workers start here
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name)
            else:
                os.environ[name] = value


def _render_all(scene: SyntheticScene, root: Path, cfg: SyntheticConfig, progress: bool) -> None:
    tasks = _tasks(cfg)
    init = (scene.appearance, scene.cameras, scene.body_vertices, scene.garment_vertices, str(root), cfg.supersample,
            cfg.jpeg_quality)
    bar = progress_bar(total=cfg.frames * cfg.cameras, desc="render views", unit="view", disable=not progress)
    workers = min(cfg.workers, len(tasks))
    if workers == 1:
        _init_worker(*init)
        for task in tasks:
            bar.update(_render_and_write(task))
    else:
        with worker_pool(workers, init) as pool:
            for views in pool.imap_unordered(_render_and_write, tasks):
                bar.update(views)
    bar.close()
