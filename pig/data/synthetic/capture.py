"""The synthetic capture: a skirted, textured stand-in body in motion, filmed by distorted cameras, in the THuman4 layout.

It is the project's default dataset and test bed for the whole method (paper Sec. 3), with the true
per-frame meshes kept for geometry error; see DESIGN.md section 4.
"""
from __future__ import annotations

import functools
import math
import time
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
from .render import RAY_CACHE_BYTES, SceneAppearance
from .rig import make_ring
from .workers import RenderTimeline, init_worker, render_and_write, worker_pool


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


# The cost model that picks the tasks (benchmarks/NOTES.md, "Synthetic capture generator: workers start together"),
# in the time to intersect, shade and write one ray (a supersample) of a view, measured in one process: computing a
# camera's rays costs RAY_COST times a view of it, a frame's scene (mesh, normals, Embree's BVH) SCENE_COST rays.
RAY_COST = 1.3
SCENE_COST = 7.5e4


def _tasks(cfg: SyntheticConfig) -> list[tuple[list[int], list[int]]]:
    """(frames, cameras) work items: each camera group's rays are computed once per item (a worker takes items in any
    order, so an item cannot count on the rays of its last one), each frame's scene once per item; the group (whose
    rays must fit a worker's cache) and the frame block are chosen to end soonest, modelled as rounds of equal items
    over the workers. Every (frame, camera) view is in exactly one item."""
    rays = cfg.width * cfg.height * cfg.supersample**2
    largest_group = max(1, min(cfg.cameras, RAY_CACHE_BYTES // (rays * 3 * 4)))
    best = None
    for group in range(1, largest_group + 1):
        for block in range(1, cfg.frames + 1):
            items = math.ceil(cfg.cameras / group) * math.ceil(cfg.frames / block)
            item_cost = group * RAY_COST * rays + block * (SCENE_COST + group * rays)
            key = (math.ceil(items / cfg.workers) * item_cost, items * item_cost)  # then the least work in all
            if best is None or key < best[0]:
                best = key, group, block
    _, group, block = best
    camera_groups = [list(range(c, min(c + group, cfg.cameras))) for c in range(0, cfg.cameras, group)]
    frame_blocks = [list(range(f, min(f + block, cfg.frames))) for f in range(0, cfg.frames, block)]
    return [(frames, cams) for frames in frame_blocks for cams in camera_groups]


def generate_capture(out_dir: Path, cfg: SyntheticConfig, overwrite: bool = False, progress: bool = True,
                     timeline: RenderTimeline | None = None) -> Path:
    """Write a THuman4-layout subject folder at `out_dir` (built next to it, then renamed into place).

    Contents: images/camXX/%08d.jpg, masks/camXX/%08d.jpg (0/255), calibration.json, smpl_params.npz,
    body_model.npz (the model used) and gt_meshes.npz (true per-frame body and garment vertices).
    An existing `out_dir` is replaced only when it is an earlier generated capture, or with `overwrite`.
    A `timeline` given receives the render workers' records (benchmarks read it).
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
        _render_all(scene, tmp, cfg, progress, timeline)
    return out_dir


def _render_all(scene: SyntheticScene, root: Path, cfg: SyntheticConfig, progress: bool,
                timeline: RenderTimeline | None) -> None:
    tasks = _tasks(cfg)
    init = (scene.appearance, scene.cameras, scene.body_vertices, scene.garment_vertices, str(root), cfg.supersample,
            cfg.jpeg_quality)
    bar = progress_bar(total=cfg.frames * cfg.cameras, desc="render views", unit="view", disable=not progress)
    workers = min(cfg.workers, len(tasks))
    timeline = timeline if timeline is not None else RenderTimeline()
    timeline.workers, timeline.started = workers, time.perf_counter()
    if workers == 1:  # one frame an item (the progress bar moves), each camera group's frames in a row (cached rays)
        init_worker(*init)
        tasks = [([frame], cams) for frames, cams in sorted(tasks, key=lambda task: task[1][0]) for frame in frames]
        for record in map(render_and_write, tasks):
            timeline.tasks.append(record)
            bar.update(record["views"])
    else:
        with worker_pool(workers, init) as pool:
            for record in pool.imap_unordered(render_and_write, tasks):
                timeline.tasks.append(record)
                bar.update(record["views"])
    timeline.ended = time.perf_counter()
    bar.close()
