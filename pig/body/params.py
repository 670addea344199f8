"""Per-frame SMPL-X parameters in one canonical form: a (N, 55, 3) full pose, betas, expression, translation.

Converts the THuman4 layout (separate keys, no eye poses) and DNA-Rendering's `fullpose`, and
checks shapes and finiteness, naming the file and key on failure.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import warnings

import numpy as np

from pig._io import atomic_path

from .skeleton import NUM_JOINTS
from .npz import read_npz

# THuman4 keys -> joint slice of the full pose; eyes (23, 24) stay zero.
THUMAN_POSE_KEYS = {
    "global_orient": slice(0, 1),
    "body_pose": slice(1, 22),
    "jaw_pose": slice(22, 23),
    "left_hand_pose": slice(25, 40),
    "right_hand_pose": slice(40, 55),
}
THUMAN_KEYS = ("betas", "transl", "expression", *THUMAN_POSE_KEYS)  # the members `from_thuman` reads
PARAMS_KEYS = ("poses", "betas", "expression", "transl", "frames")  # the preprocessed smplx.npz


class ParamsError(ValueError):
    """Body parameters are missing, malformed or not finite."""


@dataclass
class SmplxParams:
    full_pose: np.ndarray  # (N, 55, 3) axis-angle, flat-hand-mean convention
    betas: np.ndarray  # (nb,) shared by all frames
    expression: np.ndarray  # (N, ne)
    transl: np.ndarray  # (N, 3)

    @property
    def num_frames(self) -> int:
        return self.full_pose.shape[0]

    def select(self, frames) -> "SmplxParams":
        frames = np.asarray(frames)
        return SmplxParams(self.full_pose[frames], self.betas, self.expression[frames], self.transl[frames])

    def save(self, path: str | Path, frame_ids=None) -> None:
        """Write the preprocessed `smplx.npz` (poses as (N, 165)); atomic."""
        ids = np.arange(self.num_frames) if frame_ids is None else np.asarray(frame_ids)
        with atomic_path(path) as tmp:
            np.savez(tmp, poses=self.full_pose.reshape(self.num_frames, -1), betas=self.betas[None],
                     expression=self.expression, transl=self.transl, frames=ids)

    @classmethod
    def load(cls, path: str | Path) -> tuple["SmplxParams", np.ndarray]:
        """Read a preprocessed `smplx.npz`; returns the parameters and their frame ids."""
        arrays = _read_npz(path)
        _require(arrays, PARAMS_KEYS, path)
        poses = _array(arrays, "poses", path)
        n = poses.shape[0]
        _check_shape(poses, (n, NUM_JOINTS * 3), "poses", path)
        params = cls(
            full_pose=poses.reshape(n, NUM_JOINTS, 3),
            betas=_first_row(_array(arrays, "betas", path), "betas", n, path),
            expression=_frames_by(_array(arrays, "expression", path), n, "expression", path),
            transl=_check_shape(_array(arrays, "transl", path), (n, 3), "transl", path),
        )
        return params, np.asarray(arrays["frames"]).astype(np.int64)


def _read_npz(path) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise ParamsError(f"{path}: body parameter file not found")
    return read_npz(path, ParamsError, "SMPL-X body parameters", keys=PARAMS_KEYS)


def _require(arrays, keys, path) -> None:
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise ParamsError(f"{path}: missing key(s) {missing}; found {sorted(arrays)}")


def _array(arrays, key, path) -> np.ndarray:
    value = np.asarray(arrays[key], dtype=np.float64)
    if not np.all(np.isfinite(value)):
        bad = np.argwhere(~np.isfinite(value))[0].tolist()
        raise ParamsError(f"{path}: '{key}' contains NaN or infinite values (first at index {bad})")
    return value


def _check_shape(value, shape, key, path) -> np.ndarray:
    if value.shape != tuple(shape):
        raise ParamsError(f"{path}: '{key}' has shape {value.shape}, expected {tuple(shape)}")
    return value


def _first_row(value, key, n, path) -> np.ndarray:
    """Betas come as (nb,), (1, nb) or (N, nb); all frames share row 0."""
    if value.ndim == 1:
        return value
    if value.ndim == 2 and value.shape[0] in (1, n):
        if np.abs(value - value[0]).max() > 1e-6:
            warnings.warn(f"{path}: '{key}' rows differ (max {np.abs(value - value[0]).max():.3g}); using row 0 for every frame")
        return value[0]
    raise ParamsError(f"{path}: '{key}' has shape {value.shape}, expected (nb,), (1, nb) or ({n}, nb)")


def _frames_by(value, n, key, path) -> np.ndarray:
    if value.ndim == 1:
        value = np.broadcast_to(value, (n, value.shape[0])).copy()
    if value.ndim != 2 or value.shape[0] != n:
        raise ParamsError(f"{path}: '{key}' has shape {value.shape}, expected ({n}, k)")
    return value


def from_thuman(arrays: dict[str, np.ndarray], source: str) -> SmplxParams:
    """THuman4 `smpl_params.npz`: separate pose keys, no eye poses, betas with 1 or N rows."""
    _require(arrays, ("betas", "global_orient", "transl", "body_pose"), source)
    n = np.asarray(arrays["global_orient"]).reshape(-1, 3).shape[0]
    full_pose = np.zeros((n, NUM_JOINTS, 3))
    for key, part in THUMAN_POSE_KEYS.items():
        if key not in arrays:
            if key in ("global_orient", "body_pose"):
                raise ParamsError(f"{source}: missing key '{key}'")
            continue  # jaw and hands default to zero
        value = _array(arrays, key, source)
        width = (part.stop - part.start) * 3
        _check_shape(value.reshape(value.shape[0], -1), (n, width), key, source)
        full_pose[:, part] = value.reshape(n, -1, 3)
    expression = _array(arrays, "expression", source) if "expression" in arrays else np.zeros((n, 10))
    return SmplxParams(
        full_pose=full_pose,
        betas=_first_row(_array(arrays, "betas", source), "betas", n, source),
        expression=_frames_by(expression, n, "expression", source),
        transl=_check_shape(_array(arrays, "transl", source), (n, 3), "transl", source),
    )


def from_dna(arrays: dict[str, np.ndarray], source: str) -> SmplxParams:
    """DNA-Rendering `SMPLx` group: `fullpose` (N, 55, 3); the frame count comes from `fullpose`.

    The result is still in the file's hand convention: DNA fits use `flat_hand_mean=False`,
    so callers add `BodyModel.hands_mean` to the hand joints.
    """
    _require(arrays, ("betas", "fullpose", "transl"), source)
    full_pose = _array(arrays, "fullpose", source)
    n = full_pose.shape[0]
    _check_shape(full_pose.reshape(n, -1), (n, NUM_JOINTS * 3), "fullpose", source)
    expression = _array(arrays, "expression", source) if "expression" in arrays else np.zeros((n, 10))
    return SmplxParams(
        full_pose=full_pose.reshape(n, NUM_JOINTS, 3),
        betas=_first_row(_array(arrays, "betas", source), "betas", n, source),
        expression=_frames_by(expression, n, "expression", source),
        transl=_check_shape(_array(arrays, "transl", source), (n, 3), "transl", source),
    )
