"""Motion clips that drive a fitted avatar: reading AMASS, THuman4 and DNA-style files into SMPL-X
full poses, resampling them in time, and placing them in the capture's world (up axis, ground, centre).

A clip's world and the capture's world differ by a rotation and a translation (AMASS is z-up, captures
may be y-up or y-down). SMPL-X rotates the body about the shaped root joint J0(betas), so rotating the
world by Q maps (R_root, t) to (Q R_root, Q (J0 + t) - J0); the pose blend shapes depend on the other
joints only, so every posed vertex v becomes Q v. Data preparation for the paper's novel-pose driving.
"""
from __future__ import annotations

import argparse
import math
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from pig._io import atomic_path

from .model import LEFT_HAND, NUM_JOINTS, RIGHT_HAND, BodyModel
from .npz import npz_shapes, read_npz_rows
from .params import ParamsError, from_dna, from_thuman
from .rotation import (axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_quaternion, quaternion_to_axis_angle,
                       quaternion_to_matrix)

THUMAN4_FPS = 30.0  # FORMATS.md: THuman4.0 is captured at 30 fps
DNA_FPS = 15.0  # DNA-Rendering's capture rate as we understand it (UNVERIFIED); pass fps= to override
DEMO_MOTION = Path(__file__).resolve().parents[1] / "data" / "motions" / "demo.npz"

# SMPL-H (AMASS, 52 joints: root, body 21, left hand 15, right hand 15) -> SMPL-X joint index. SMPL-X
# inserts jaw (22) and the eyes (23, 24) between the body and the hands; those stay zero.
SMPLH_TO_SMPLX = np.array(list(range(22)) + list(range(25, 40)) + list(range(40, 55)))
SMPLH_JOINTS, SMPLX_JOINTS = 52, NUM_JOINTS
AMASS_LAYOUT = ("AMASS npz: `poses` (N, 156) SMPL-H or (N, 165) SMPL-X axis-angle, `trans` (N, 3), "
                "`mocap_framerate` (or `mocap_frame_rate`) scalar, optional `betas`")
THUMAN4_LAYOUT = ("THuman4 smpl_params.npz: `global_orient` (N, 3), `body_pose` (N, 63), `transl` (N, 3), `betas`, "
                  "optional `jaw_pose`, `left_hand_pose`, `right_hand_pose`, `expression`")
DNA_LAYOUT = "DNA-style npz: `fullpose` (N, 55, 3) axis-angle, `transl` (N, 3), optional `betas`"
_KEYS = ("poses", "trans", "mocap_framerate", "mocap_frame_rate", "betas", "global_orient", "body_pose", "jaw_pose",
         "left_hand_pose", "right_hand_pose", "expression", "transl", "fullpose")
# The members with a row per frame, read only at the frames asked for; `betas` (one shape) and the rate are not.
_FRAME_KEYS = ("poses", "trans", "global_orient", "body_pose", "jaw_pose", "left_hand_pose", "right_hand_pose",
               "expression", "transl", "fullpose")
_LAYOUT_KEYS = ("poses", "global_orient", "fullpose")  # the member that tells each layout, with a row per frame
# Bounds on what a motion may ask for (docs/animation.md). Each frame is posed and rendered, so MAX_FRAMES, checked
# after --frames and --fps and before anything is allocated, bounds memory and time: an hour at 30 fps.
MAX_FRAMES = 108_000
FPS_RANGE = (1.0, 1000.0)  # a clip's own rate and any rate asked for: mocap runs at 30-250 fps, VP9 below 0.1 fails
MAX_TRANSLATION_M = 1000.0  # a frame's root translation from the clip's origin: no capture volume is larger
MAX_ABS_BETA = 10.0  # SMPL-X shape coefficients are in standard deviations of the body-shape space
_AXES = {"x": 0, "y": 1, "z": 2}


class MotionError(ValueError):
    """A motion file is missing, not an npz, or not in a known layout."""


@dataclass
class Motion:
    """An SMPL-X motion clip in the flat-hand-mean convention."""

    full_pose: np.ndarray  # (N, 55, 3) float64 axis-angle
    transl: np.ndarray  # (N, 3) float64
    fps: float
    betas: np.ndarray | None = None  # informational: the avatar keeps its own refined shape
    source: str = "<arrays>"
    frames: np.ndarray | None = None  # each row's frame index in the source (None: 0, 1, ...)

    @property
    def num_frames(self) -> int:
        return self.full_pose.shape[0]

    @property
    def source_frames(self) -> np.ndarray:
        """Each row's frame index in the file (or arrays) the clip was read from."""
        return np.arange(self.num_frames) if self.frames is None else self.frames

    def select(self, frames: slice) -> "Motion":
        """The frames of a slice; a step s divides the frame rate by s."""
        if not isinstance(frames, slice):
            raise TypeError(f"Motion.select takes a slice, got {type(frames).__name__}")
        step = frames.step or 1
        picked = replace(self, full_pose=self.full_pose[frames], transl=self.transl[frames], fps=self.fps / abs(step),
                         frames=self.source_frames[frames])
        if picked.num_frames == 0:
            raise MotionError(f"{self.source}: frames {frames} select none of the {self.num_frames} frames")
        return picked

    def resample(self, fps: float) -> "Motion":
        """The clip at `fps`: frame k at time k / fps over the clip's span; joint rotations by slerp between the
        two neighbouring frames (smooth in video, unlike nearest-frame), translations linearly. MotionError,
        before anything is allocated, when that is more than MAX_FRAMES frames."""
        check_fps(fps, f"{self.source}: resampling to", MotionError)
        span = (self.num_frames - 1) / self.fps
        count = int(math.floor(span * fps + 1e-9)) + 1
        if count > MAX_FRAMES:
            raise MotionError(f"{self.source}: {span:g} s at {fps:g} fps is {count:,} frames, more than the "
                              f"{MAX_FRAMES:,} a motion may drive; select fewer frames or a lower rate")
        position = np.arange(count) * (self.fps / fps)  # fractional source frame
        lower = np.minimum(np.floor(position).astype(np.int64), self.num_frames - 1)
        upper = np.minimum(lower + 1, self.num_frames - 1)
        weight = position - lower
        quats = matrix_to_quaternion(axis_angle_to_matrix(torch.from_numpy(self.full_pose))).numpy()
        pose = quaternion_to_axis_angle(torch.from_numpy(slerp(quats[lower], quats[upper], weight[:, None]))).numpy()
        transl = (1 - weight[:, None]) * self.transl[lower] + weight[:, None] * self.transl[upper]
        return replace(self, full_pose=pose, transl=transl, fps=float(fps), frames=None)


def check_fps(fps: float, what: str, error: type[Exception] = MotionError) -> float:
    """`fps` if it lies in FPS_RANGE, else `error` naming `what` (the file and the key, or the option)."""
    low, high = FPS_RANGE
    if not (math.isfinite(fps) and low <= fps <= high):
        raise error(f"{what} {fps:g} fps; expected a frame rate from {low:g} to {high:g} fps")
    return float(fps)


def check_translations(transl: np.ndarray, source: str, frames=None) -> None:
    """MotionError naming `source`, the first bad frame and its value when a translation (N, 3) is not finite or lies
    more than MAX_TRANSLATION_M from the origin (no capture could hold it: placed in one, such a clip either
    collapses onto a few points or leaves the view). `frames` (N,): each row's frame index in `source`."""
    distance = np.linalg.norm(np.asarray(transl, dtype=np.float64), axis=1)
    bad = ~(distance <= MAX_TRANSLATION_M)  # NaN compares false
    if bad.any():
        row = int(np.argmax(bad))
        frame = row if frames is None else int(frames[row])
        raise MotionError(f"{source}: the translation of frame {frame} is {np.asarray(transl)[row].tolist()}, "
                          f"expected finite and within {MAX_TRANSLATION_M:g} m of the clip's origin")


def check_betas(betas: np.ndarray | None, source: str) -> None:
    """MotionError naming `source` and the first coefficient when a shape coefficient is not finite or exceeds
    MAX_ABS_BETA standard deviations in size."""
    if betas is None:
        return
    betas = np.asarray(betas, dtype=np.float64).reshape(-1)
    bad = ~(np.abs(betas) <= MAX_ABS_BETA)
    if bad.any():
        index = int(np.argmax(bad))
        raise MotionError(f"{source}: shape coefficient betas[{index}] is {betas[index]:g}, expected finite and "
                          f"within +-{MAX_ABS_BETA:g} (standard deviations of the body-shape space)")


def slerp(q0: np.ndarray, q1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions (..., 4) along the shorter arc; weight broadcasts over (...)."""
    dot = (q0 * q1).sum(-1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    angle = np.arccos(dot)[..., None]
    w = np.asarray(weight, dtype=np.float64)[..., None]
    small = angle < 1e-6  # nearly equal: the normalised lerp is exact to rounding
    sin_angle = np.where(small, 1.0, np.sin(angle))
    a = np.where(small, 1 - w, np.sin((1 - w) * angle) / sin_angle)
    b = np.where(small, w, np.sin(w * angle) / sin_angle)
    out = a * q0 + b * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


# -- reading ---------------------------------------------------------------------------------------

def read_motion(path: str | Path, fps: float | None = None, hands_mean: np.ndarray | None = None,
                frames: slice | None = None) -> Motion:
    """Read a motion clip: AMASS (`poses` SMPL-H or SMPL-X), THuman4 `smpl_params.npz`, or DNA-style `fullpose`.

    fps overrides the file's rate (AMASS `mocap_framerate`) or the default (THuman4 30, DNA 15).
    hands_mean (55, 3), e.g. `body_model.hands_mean`, is needed for the DNA layout only, whose fits use
    `flat_hand_mean=False`; it is added to the hand joints. frames (a slice of positive step, STOP at most the
    file's frame count) reads those frames alone (`Motion.frames` holds their indices), checked against MAX_FRAMES
    from the file's headers before anything is read. Never unpickles; MotionError on bad input, and on a rate
    outside FPS_RANGE, translations beyond MAX_TRANSLATION_M or shape coefficients beyond MAX_ABS_BETA.
    """
    path = Path(path)
    expected = f"one of: {AMASS_LAYOUT}; {THUMAN4_LAYOUT}; {DNA_LAYOUT}"
    if not path.is_file():
        raise MotionError(f"{path}: motion file not found; expected {expected}")
    shapes = npz_shapes(path, MotionError, expected, _LAYOUT_KEYS)
    frames_key = next((key for key in _LAYOUT_KEYS if key in shapes), None)
    if frames_key is None:
        with zipfile.ZipFile(path) as archive:  # npz_shapes checked it; list every member, not only the known ones
            keys = sorted(name[:-4] for name in archive.namelist() if name.endswith(".npy"))
        raise MotionError(f"{path}: no known motion layout (keys {keys}); expected {expected}")
    count = shapes[frames_key][0] if shapes[frames_key] else 0
    rows = _frame_rows(frames, count, path)
    if len(rows) > MAX_FRAMES:
        raise MotionError(f"{path}: {len(rows):,} frames selected (of {count:,}), more than the {MAX_FRAMES:,} a motion "
                          "may drive; select a part (frames START:STOP[:STEP])")
    arrays = read_npz_rows(path, MotionError, expected, _KEYS, _FRAME_KEYS, count, rows)
    transl = arrays.get("trans" if frames_key == "poses" else "transl")
    if transl is not None and transl.ndim == 2 and transl.shape[1] == 3 and transl.dtype.kind in "biuf":
        check_translations(transl, str(path), rows)  # first: it names the frame; the layouts check the rest
    if frames_key == "poses":
        motion = _from_amass(arrays, path)
    elif frames_key == "global_orient":
        motion = _from_params(arrays, path, from_thuman, THUMAN4_LAYOUT, THUMAN4_FPS, None)
    else:
        if hands_mean is None:
            raise MotionError(f"{path}: DNA-style `fullpose` uses flat_hand_mean=False; pass hands_mean= "
                              "(the body model's hands_mean) so it can be added to the hand joints")
        motion = _from_params(arrays, path, from_dna, DNA_LAYOUT, DNA_FPS, np.asarray(hands_mean, dtype=np.float64))
    motion.frames = np.asarray(rows, dtype=np.int64)
    rate = motion.fps if fps is None else check_fps(fps, f"{path}: the frame rate asked for is")
    motion.fps = rate / rows.step  # every STEP-th frame: the file's rate over STEP
    check_betas(motion.betas, str(path))
    return motion


def _frame_rows(frames: slice | None, count: int, path: Path) -> range:
    """The frame indices `frames` selects of a file's `count`; MotionError if it reaches past them."""
    if frames is None:
        return range(count)
    start, stop, step = frames.start or 0, frames.stop, frames.step or 1
    if not (0 <= start < stop and step >= 1):
        raise ValueError(f"read_motion: frames must be a slice with 0 <= START < STOP and STEP >= 1, got {frames}")
    if stop > count:
        shown = f"{start}:{stop}" + (f":{step}" if step > 1 else "")
        raise MotionError(f"frames {shown}: {path} has {count} frames (0..{count - 1}), so STOP may be at most {count}")
    return range(start, stop, step)


def _finite(arrays, key: str, path: Path, layout: str) -> np.ndarray:
    try:
        value = np.asarray(arrays[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise MotionError(f"{path}: `{key}` is not numeric (dtype {arrays[key].dtype}); expected {layout}") from None
    if not np.all(np.isfinite(value)):
        bad = np.argwhere(~np.isfinite(value))[0].tolist()
        raise MotionError(f"{path}: `{key}` contains NaN or infinite values (first at index {bad}); expected {layout}")
    return value


def _from_amass(arrays, path: Path) -> Motion:
    missing = [k for k in ("poses", "trans") if k not in arrays]
    rate_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in arrays), None)
    if missing or rate_key is None:
        missing += [] if rate_key else ["mocap_framerate"]
        raise MotionError(f"{path}: missing key(s) {missing}; expected {AMASS_LAYOUT}")
    poses = _finite(arrays, "poses", path, AMASS_LAYOUT)
    if poses.ndim != 2:
        raise MotionError(f"{path}: `poses` has shape {poses.shape}; expected (N, 156) or (N, 165) ({AMASS_LAYOUT})")
    if poses.shape[1] not in (SMPLH_JOINTS * 3, SMPLX_JOINTS * 3):
        raise MotionError(f"{path}: `poses` has {poses.shape[1]} columns; expected 156 (SMPL-H, AMASS) or 165 (SMPL-X)")
    n = _frame_count(poses, "poses", path, AMASS_LAYOUT)
    trans = _finite(arrays, "trans", path, AMASS_LAYOUT)
    if trans.shape != (n, 3):
        raise MotionError(f"{path}: `trans` has shape {trans.shape}; expected ({n}, 3) to match `poses` "
                          f"({AMASS_LAYOUT})")
    rate = _finite(arrays, rate_key, path, AMASS_LAYOUT)
    if rate.size != 1:
        raise MotionError(f"{path}: `{rate_key}` is {rate.tolist()}; expected one frame rate ({AMASS_LAYOUT})")
    check_fps(rate.item(), f"{path}: `{rate_key}` is")
    full_pose = np.zeros((n, SMPLX_JOINTS, 3))
    if poses.shape[1] == SMPLH_JOINTS * 3:
        full_pose[:, SMPLH_TO_SMPLX] = poses.reshape(n, SMPLH_JOINTS, 3)
    else:
        full_pose[:] = poses.reshape(n, SMPLX_JOINTS, 3)
    betas = None
    if "betas" in arrays and np.size(arrays["betas"]):
        betas = np.atleast_2d(_finite(arrays, "betas", path, AMASS_LAYOUT))[0]  # AMASS stores (16,)
    return Motion(full_pose, trans, float(rate.item()), betas, str(path))


def _frame_count(value: np.ndarray, key: str, path: Path, layout: str) -> int:
    if value.shape[0] == 0:
        raise MotionError(f"{path}: `{key}` has zero frames; expected {layout} with N >= 1")
    return value.shape[0]


def _from_params(arrays, path: Path, convert, layout: str, fps: float, hands_mean: np.ndarray | None) -> Motion:
    """THuman4 and DNA layouts through the capture readers' converters (pig.body.params)."""
    frames_key = "global_orient" if convert is from_thuman else "fullpose"
    _frame_count(np.asarray(arrays[frames_key]), frames_key, path, layout)
    has_betas = "betas" in arrays
    if not has_betas:  # the converters need a shape; a motion's is informational only
        arrays = dict(arrays, betas=np.zeros(10))
    try:
        params = convert(arrays, str(path))
    except ParamsError as err:
        raise MotionError(f"{err}; expected {layout}") from None
    full_pose = params.full_pose.astype(np.float64)
    if hands_mean is not None:
        if hands_mean.shape != (NUM_JOINTS, 3):
            raise ValueError(f"hands_mean has shape {hands_mean.shape}, expected ({NUM_JOINTS}, 3)")
        for part in (LEFT_HAND, RIGHT_HAND):
            full_pose[:, part] += hands_mean[part]
    return Motion(full_pose, params.transl.astype(np.float64), fps, params.betas if has_betas else None, str(path))


# -- orientation -----------------------------------------------------------------------------------

def body_up(full_pose: np.ndarray) -> np.ndarray:
    """Unit mean world direction of the body's up axis, R(root) @ [0, 1, 0] (SMPL-X's rest body is y-up)."""
    roots = axis_angle_to_matrix(torch.as_tensor(np.asarray(full_pose)[:, 0], dtype=torch.float64)).numpy()
    mean = roots[:, :, 1].mean(axis=0)
    norm = np.linalg.norm(mean)
    if norm < 1e-3:
        raise ValueError("body_up: the body's up axis averages to zero over the frames (no consistent up); "
                         "give the up axis explicitly (up_override)")
    return mean / norm


def parse_axis(axis: str) -> np.ndarray:
    """'+y', '-z', 'x' ... -> the unit axis vector."""
    text = axis.strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    name = text.lstrip("+-")
    if name not in _AXES or len(text) - len(name) > 1:
        raise ValueError(f"up axis {axis!r} not understood; expected one of +x, -x, +y, -y, +z, -z")
    out = np.zeros(3)
    out[_AXES[name]] = sign
    return out


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction a to direction b; for opposite directions a half turn
    about an axis perpendicular to a (the one closest to the coordinate axis least aligned with a)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    half = a + b
    norm = np.linalg.norm(half)
    if norm < 1e-6:
        other = np.eye(3)[np.argmin(np.abs(a))]
        axis = other - (other @ a) * a
        quat = np.concatenate([[0.0], axis / np.linalg.norm(axis)])
    else:
        half /= norm  # the rotation by twice the angle between a and the half-way vector
        quat = np.concatenate([[a @ half], np.cross(a, half)])
    return quaternion_to_matrix(torch.from_numpy(quat)).numpy()


def _rest_root(body_model: BodyModel, betas) -> np.ndarray:
    """J0(betas): the shaped root joint, about which SMPL-X applies the global orientation."""
    with torch.no_grad():
        rest = body_model(_tensor(np.zeros((1, NUM_JOINTS, 3)), body_model), _tensor(betas, body_model))
    return rest.joints[0, 0].double().cpu().numpy()


def _tensor(array, body_model: BodyModel) -> torch.Tensor:
    return torch.as_tensor(np.asarray(array), dtype=body_model.dtype, device=body_model.v_template.device)


def lowest_height(body_model: BodyModel, betas, full_pose: np.ndarray, transl: np.ndarray, up: np.ndarray,
                  chunk: int = 32) -> float:
    """The lowest posed vertex height along `up` over all frames (posed in chunks of frames)."""
    up_t = _tensor(up, body_model)
    lowest = math.inf
    with torch.no_grad():
        for start in range(0, len(full_pose), chunk):
            part = slice(start, start + chunk)
            out = body_model(_tensor(full_pose[part], body_model), _tensor(betas, body_model),
                             transl=_tensor(transl[part], body_model))
            lowest = min(lowest, float((out.vertices @ up_t).min()))
    return lowest


def capture_frame(source, num_frames: int = 8) -> tuple[np.ndarray, float, np.ndarray]:
    """(up (3,) unit, ground height along up, centre (3,)) of a capture, from its training poses.

    source: an AvatarModel (its `pose_init`, `transl`, `betas_init`, `body_model`) or a tuple
    (pose_init (T, 55, 3), transl (T, 3), betas, body_model). up: `body_up` of the training poses.
    ground: the lowest vertex height along up over `num_frames` evenly spaced training frames.
    centre: the mean root joint position over all training frames, dropped onto the ground plane.
    """
    if isinstance(source, tuple):
        pose, transl, betas, body_model = source
    else:
        pose, transl, betas, body_model = source.pose_init, source.transl, source.betas_init, source.body_model
    pose, transl, betas = (np.asarray(torch.as_tensor(x).detach().cpu().double()) for x in (pose, transl, betas))
    up = body_up(pose)
    frames = np.unique(np.linspace(0, len(pose) - 1, min(num_frames, len(pose))).round().astype(np.int64))
    ground = lowest_height(body_model, betas, pose[frames], transl[frames], up)
    root = (_rest_root(body_model, betas) + transl).mean(axis=0)
    centre = root - (root @ up - ground) * up
    return up, ground, centre


def align_motion(motion: Motion, body_model: BodyModel, betas, up, ground: float, centre,
                 up_override: str | None = None) -> Motion:
    """The clip in the capture's world: rotated so its `body_up` maps to `up` (or the `up_override` axis,
    e.g. "+y", "-y", "+z"), shifted so its mean root position lies over `centre` and its lowest vertex over
    the clip touches the ground plane (height `ground` along up). Rotation about the root pivot J0(betas):
    global_orient' = Q R, transl' = Q (J0 + t) - J0, so every posed vertex v maps to Q v."""
    target = parse_axis(up_override) if up_override is not None else np.asarray(up, dtype=np.float64)
    target = target / np.linalg.norm(target)
    betas = np.asarray(betas, dtype=np.float64)
    q = rotation_between(body_up(motion.full_pose), target)
    rotated = rotate_world(motion, q, _rest_root(body_model, betas))
    root = _rest_root(body_model, betas) + rotated.transl
    horizontal = np.asarray(centre, dtype=np.float64) - root.mean(axis=0)
    horizontal -= (horizontal @ target) * target
    lowest = lowest_height(body_model, betas, rotated.full_pose, rotated.transl, target)
    rotated.transl = rotated.transl + horizontal + (ground - lowest) * target
    return rotated


def rotate_world(motion: Motion, rotation: np.ndarray, root_joint: np.ndarray) -> Motion:
    """The clip with its world rotated by `rotation` (3, 3) about the origin; root_joint: J0(betas)."""
    q = torch.from_numpy(np.asarray(rotation, dtype=np.float64))
    roots = q @ axis_angle_to_matrix(torch.from_numpy(motion.full_pose[:, 0]))
    full_pose = motion.full_pose.copy()
    full_pose[:, 0] = matrix_to_axis_angle(roots).numpy()
    transl = (motion.transl + root_joint) @ rotation.T - root_joint
    return replace(motion, full_pose=full_pose, transl=transl)


# -- demo clip -------------------------------------------------------------------------------------

DEMO_SEED = 1  # the default synthetic subject trains on seed 0
DEMO_FRAMES = 144
DEMO_FPS = 30.0
DEMO_AMPLITUDE = 1.25  # joint angles scaled up from the generator's
DEMO_WALK_SPEED = 0.15  # m/s forward drift


def demo_motion_arrays() -> dict[str, np.ndarray]:
    """The shipped demo clip in the AMASS SMPL-X layout, z-up like AMASS, float32; deterministic.

    The synthetic generator's motion (pig.data.synthetic.motion) with another seed, larger joint angles
    and a slow forward walk, 4.8 s at 30 fps. World rotation y-up -> z-up with J0 taken as 0: any J0 only
    shifts every frame by one constant, which `align_motion` removes.
    """
    from pig.data.synthetic.motion import Motion as SyntheticMotion

    times = np.arange(DEMO_FRAMES) / DEMO_FPS
    generator = SyntheticMotion(DEMO_SEED, ground_offset=0.0)
    pose = generator.full_pose(times)
    pose[:, 1:] *= DEMO_AMPLITUDE
    transl = generator.transl(times)
    transl[:, 2] += DEMO_WALK_SPEED * times
    z_up = rotation_between([0.0, 1.0, 0.0], [0.0, 0.0, 1.0])
    clip = rotate_world(Motion(pose, transl, DEMO_FPS), z_up, np.zeros(3))
    return {"poses": clip.full_pose.reshape(DEMO_FRAMES, -1).astype(np.float32),
            "trans": clip.transl.astype(np.float32),
            "mocap_framerate": np.array(DEMO_FPS),
            "betas": np.zeros(10, dtype=np.float32)}


def write_demo_motion(path: str | Path = DEMO_MOTION) -> Path:
    """Write the demo clip (atomic); `python -m pig.body.motion --write-demo PATH` does the same."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez(handle, **demo_motion_arrays())
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write-demo", metavar="PATH", type=Path, required=True,
                        help="write the demo motion clip (shipped as pig/data/motions/demo.npz)")
    args = parser.parse_args(argv)
    print(write_demo_motion(args.write_demo))


if __name__ == "__main__":
    main()
