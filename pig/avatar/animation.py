"""Driving a fitted avatar with new motion: motion clips brought into the capture's frame, orbit or capture cameras,
and the rendered frames as a browser-playable video (WebM, VP9) with optional PNG (alpha) and EXR frames.

A novel pose takes the time embedding of the nearest training timestep and the avatar's own refined shape
(as the render stage's novel poses do); the clip's own betas are not used.
"""
from __future__ import annotations

import math
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

VIDEO_NAME = "animation.webm"
# VP9 in WebM: playable in browsers, and OpenCV's bundled FFmpeg encodes it (it has no H.264 encoder).
VIDEO_FOURCC = "VP90"


@dataclass
class Orbit:
    """A turntable camera path around `centre` about the unit `up` axis: one revolution every `period_s`
    seconds, at `radius` metres (None: fit the subject in view) and `height` metres above the centre, looking
    at the centre; `fov_deg` vertical field of view of a `width` x `height_px` pinhole camera."""

    radius: float | None = None
    height: float = 0.3
    period_s: float = 8.0
    fov_deg: float = 40.0
    width: int = 512
    height_px: int = 512


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera (4, 4) of a camera at `eye` looking at `target` with `up` pointing up in the image
    (OpenCV convention, as gsplat and the captures: x right, y down, z forward)."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: the view direction is parallel to the up axis; raise or lower the camera")
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ eye
    return viewmat


def orbit_cameras(count: int, fps: float, centre: np.ndarray, up: np.ndarray, extent: float, orbit: Orbit
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(viewmats (count, 4, 4), K (3, 3)) of `count` frames at `fps` along the orbit; `extent` is the subject's
    size (metres), used for the radius when the orbit has none: the subject fills ~75 % of the image height."""
    up = up / np.linalg.norm(up)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    other = np.cross(up, side)
    half_fov = math.radians(orbit.fov_deg) / 2
    radius = orbit.radius if orbit.radius is not None else 0.5 * extent / 0.75 / math.tan(half_fov)
    focal = 0.5 * orbit.height_px / math.tan(half_fov)
    K = np.array([[focal, 0, orbit.width / 2], [0, focal, orbit.height_px / 2], [0, 0, 1]])
    viewmats = []
    for i in range(count):
        angle = 2 * math.pi * (i / fps) / orbit.period_s
        eye = centre + radius * (math.cos(angle) * side + math.sin(angle) * other) + orbit.height * up
        viewmats.append(look_at(eye, centre, up))
    return np.stack(viewmats), K


# OpenCV checks the FourCC against the container's codec tag list and prints this line when it is not there. The
# WebM muxer has no such list (Matroska stores codec names, not tags), so it prints for every FourCC, yet encodes
# VP9 as asked: a false alarm, which `_without_tag_notice` keeps off stderr.
SPURIOUS_TAG_NOTICE = re.compile(r"OpenCV: FFMPEG: tag 0x[0-9a-f]{8}/'.{4}' is not supported with codec id \d+ and "
                                 r"format 'webm / WebM'\n?")


@contextmanager
def _without_tag_notice() -> Iterator[None]:
    """Run the block with the process's stderr (file descriptor 2, which OpenCV's C code writes to) captured, then
    pass on everything it wrote there but OpenCV's spurious WebM tag notice."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as captured:
            os.dup2(captured.fileno(), 2)
            try:
                yield
            finally:
                os.dup2(saved, 2)
                captured.seek(0)
                text = SPURIOUS_TAG_NOTICE.sub("", captured.read().decode(errors="replace"))
                if text:
                    sys.stderr.write(text)
                    sys.stderr.flush()
    finally:
        os.close(saved)


class VideoWriter:
    """Frames (H, W, 3) RGB float in [0, 1] -> a WebM (VP9) file; a one-line error when the codec is missing."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        self.path = Path(path)
        with _without_tag_notice():
            self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*VIDEO_FOURCC), float(fps),
                                           (width, height))
        if not self._writer.isOpened():
            raise RuntimeError(f"{self.path}: OpenCV cannot encode {VIDEO_FOURCC} video here (its FFmpeg lacks the encoder); "
                               "write PNG frames instead (--png)")

    def write(self, rgb: np.ndarray) -> None:
        frame = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)[..., ::-1]
        self._writer.write(np.ascontiguousarray(frame))

    def close(self) -> None:
        self._writer.release()


@torch.no_grad()
def subject_bounds(model, betas: torch.Tensor, poses: np.ndarray, transl: np.ndarray, samples: int = 16) -> tuple[np.ndarray, float]:
    """(centre (3,), size in metres) of the posed body over a motion: the middle of the vertices' bounding box over
    up to `samples` evenly spaced frames, and that box's largest side."""
    picks = np.unique(np.linspace(0, len(poses) - 1, min(samples, len(poses))).round().astype(int))
    body = model.body_model
    dtype, device = body.dtype, model.pose_init.device
    pose = torch.as_tensor(poses[picks], dtype=dtype, device=device)
    vertices = body(pose, betas, None, torch.as_tensor(transl[picks], dtype=dtype, device=device)).vertices
    vertices = vertices.reshape(-1, 3).cpu().double().numpy()
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    return (low + high) / 2, float((high - low).max())


def render_frame(driver_gaussians, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, background: torch.Tensor,
                 rasterizer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb (H, W, 3), alpha (H, W), depth (H, W)) of one set of Gaussians in one camera."""
    from pig.render.api import render_gaussians

    means, quats, scales, opacities, sh = driver_gaussians
    out = render_gaussians(means, quats, scales, opacities, sh, viewmat[None], K[None], width, height, background,
                           backend=rasterizer.backend, max_pairs=rasterizer.max_pairs)
    return (out.color[0].clamp(0, 1).cpu().numpy(), out.alpha[0, ..., 0].cpu().numpy(), out.depth[0, ..., 0].cpu().numpy())


def animate(checkpoint: Path, output: Path, motion_path: Path | None = None, camera: str | None = None,
            capture_dir: Path | None = None, lod: int | None = None, frames: str | None = None, fps: float | None = None,
            up: str | None = None, orbit: Orbit | None = None, static_seconds: float | None = None, png: bool = False,
            exr: bool = False, device: str = "cpu", rasterizer=None, overwrite: bool = False) -> Path:
    """Render `motion_path` (None: the avatar's first training pose, held still) on the avatar of `checkpoint` into
    `output`/animation.webm (+ frames/NNNNN.png with alpha, .exr with A and Z); returns the video's path.

    `camera` (with `capture_dir`) renders from a capture camera, otherwise the camera orbits (`orbit`). A still
    pose lasts `static_seconds` (default: one orbit period). `lod` defaults to the finest; `frames` selects motion
    frames (START:STOP[:STEP]); `fps` resamples the motion (default: the motion's own rate); `up` ("+y", "-z", ...)
    overrides the capture's up axis inferred from its training poses.
    """
    from pig.avatar.checkpoint import load_avatar
    from pig.avatar.driver import AvatarDriver
    from pig.avatar.export import capture_motion, parse_frames
    from pig.body.motion import MAX_FRAMES, Motion, MotionError, capture_frame, check_fps, read_motion
    from pig.config import resolve_device
    from pig.data.exr import write_exr
    from pig.progress import progress_bar
    from pig.render.api import RasterizerConfig
    from pig._io import write_json, write_png
    from pig._outputs import build_dir, claim_dir

    rasterizer = rasterizer or RasterizerConfig()
    orbit = orbit or Orbit()
    selection = parse_frames(frames)
    if fps is not None:
        check_fps(fps, "--fps", ValueError)
    inputs = tuple(p for p in (checkpoint, motion_path, capture_dir) if p is not None)
    output = claim_dir(output, "animate", inputs, overwrite)
    device = resolve_device(device, "--device")
    model = load_avatar(checkpoint, device)
    level = model.num_levels - 1 if lod is None else lod
    if not 0 <= level < model.num_levels:
        raise ValueError(f"--lod {lod}: the avatar has levels 0..{model.num_levels - 1}")
    driver = AvatarDriver(model)
    target_up, ground, centre = capture_frame(model)

    if motion_path is None:
        seconds = static_seconds if static_seconds is not None else orbit.period_s
        rate = fps or 30.0
        count = max(1, int(round(seconds * rate)))
        if count > MAX_FRAMES:
            raise MotionError(f"a still pose of {seconds:g} s at {rate:g} fps is {count:,} frames, more than the "
                              f"{MAX_FRAMES:,} an animation may have; shorten --seconds or lower --fps")
        pose = model.pose_init[:1].cpu().double().numpy().repeat(count, axis=0)
        motion = Motion(full_pose=pose, transl=model.transl[:1].cpu().double().numpy().repeat(count, axis=0), fps=rate,
                        betas=None, source=f"{checkpoint} (training timestep 0, still)")
    else:
        motion = read_motion(motion_path, hands_mean=model.body_model.hands_mean.cpu().numpy(),  # DNA-style fits
                             frames=selection)
        motion = capture_motion(motion, model.body_model, driver.refined()[0], (target_up, ground, centre), None,
                                fps, up)[0]
        check_fps(motion.fps, f"{motion.source}: with --frames {frames} the video would play at", ValueError)

    count = len(motion.full_pose)
    if camera is not None:
        from pig.data.capture import Capture

        if capture_dir is None:
            raise ValueError("--camera needs --capture DIR (the preprocessed capture the camera belongs to)")
        capture = Capture.load(capture_dir)
        if camera not in capture.cameras:
            raise ValueError(f"{capture_dir}: no camera {camera!r}; cameras: {', '.join(sorted(capture.cameras))}")
        cam = capture.cameras[camera]
        viewmats = np.repeat(cam.viewmat()[None], count, axis=0)
        K, width, height = np.asarray(cam.K), cam.width, cam.height
    else:
        centre_of_motion, extent = subject_bounds(model, driver.refined()[0], motion.full_pose, motion.transl)
        viewmats, K = orbit_cameras(count, motion.fps, centre_of_motion, target_up, extent, orbit)
        width, height = orbit.width, orbit.height_px

    viewmats_t = torch.as_tensor(viewmats, dtype=torch.float32, device=device)
    K_t = torch.as_tensor(K, dtype=torch.float32, device=device)
    black = torch.zeros(3, device=device)
    with build_dir(output, "animate") as tmp:
        video = VideoWriter(tmp / VIDEO_NAME, motion.fps, width, height)
        try:
            for i in progress_bar(range(count), desc="animate", unit="frame"):
                gaussians = driver.gaussians(level, motion.full_pose[i], motion.transl[i])
                rgb, alpha, depth = render_frame(gaussians, viewmats_t[i], K_t, width, height, black, rasterizer)
                video.write(rgb)
                if png:
                    write_png(tmp / "frames" / f"{i:05d}.png", np.concatenate([rgb, alpha[..., None]], axis=-1))
                if exr:
                    write_exr(tmp / "frames" / f"{i:05d}.exr", {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2],
                                                               "A": alpha, "Z": depth})
        finally:
            video.close()
        write_json(tmp / "animation.json", {
            "checkpoint": str(checkpoint), "motion": motion.source, "frames": count, "fps": motion.fps, "lod": level,
            "splats": model.level_sizes[level], "camera": camera or "orbit", "width": width, "height": height,
            "up": [float(v) for v in target_up], "video": VIDEO_NAME,
        })
    return output / VIDEO_NAME
