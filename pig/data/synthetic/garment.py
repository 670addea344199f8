"""A flared skirt for the synthetic subject: an open tube skinned to pelvis and hips, plus secondary motion.

The sway, twist lag, flare and travelling hem waves come from damped springs driven by the pelvis
and from waves in time, so no skinning explains them: the off-body, open-boundary case of the paper.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pig.body.model import NUM_JOINTS, SMPLX_JOINT_NAMES

J = {name: i for i, name in enumerate(SMPLX_JOINT_NAMES)}
AROUND = 128  # vertices per ring
DOWN = 28  # rings below the waist ring
HIP_FOLLOW = 0.3  # how much of a leg's rotation the skirt side over it follows, at the hem
FLARE = 0.25  # hem radius minus waist radius, metres
SIM_HZ = 240.0  # clock of the spring integration, independent of the frame rate


@dataclass
class Skirt:
    rest: np.ndarray  # (Vg, 3) canonical rest positions (same space as the body template)
    faces: np.ndarray  # (Fg, 3)
    weights: np.ndarray  # (Vg, 55) skinning weights
    angle: np.ndarray  # (Vg,) angle around the body, 0 = front (+z), pi/2 = the person's left (+x)
    drop: np.ndarray  # (Vg,) 0 at the waist, 1 at the hem
    centre: np.ndarray  # (3,) waist centre
    radius: np.ndarray  # (Vg,) rest distance from the vertical axis through `centre`
    length: float  # waist to hem, metres

    @property
    def hem(self) -> np.ndarray:
        """Indices of the open lower boundary."""
        return np.arange(DOWN * AROUND, (DOWN + 1) * AROUND)


def _slice_extent(vertices: np.ndarray, y: float, centre: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Half-widths (x, z) of the body's horizontal slice at height y, about `centre`."""
    near = keep & (np.abs(vertices[:, 1] - y) < 0.02)
    if not near.any():
        raise ValueError(f"the body has no vertices at height {y:.3f} m to hang the skirt from")
    offsets = np.abs(vertices[near][:, [0, 2]] - centre[[0, 2]])
    return offsets.max(axis=0)


def build_skirt(shaped: np.ndarray, joints: np.ndarray, weights: np.ndarray) -> Skirt:
    """Hang a skirt from the waist of a rest-pose body (vertices `shaped`, rest `joints`, skinning `weights`).

    The waist ring sits just inside the body so no gap shows; the hem sits a hand above the knees.
    """
    arms = [J[f"{s}_{p}"] for s in ("left", "right") for p in ("collar", "shoulder", "elbow", "wrist")]
    trunk = weights[:, arms].sum(axis=1) < 0.5
    top = joints[J["spine1"], 1]
    bottom = 0.5 * (joints[J["left_knee"], 1] + joints[J["right_knee"], 1]) + 0.12
    centre = np.array([joints[J["pelvis"], 0], top, joints[J["pelvis"], 2]])
    waist = 0.96 * _slice_extent(shaped, top, centre, trunk)
    length = top - bottom
    angle = np.linspace(0, 2 * np.pi, AROUND, endpoint=False)
    drop = np.linspace(0, 1, DOWN + 1)
    a, s = np.meshgrid(angle, drop)  # (DOWN + 1, AROUND)
    a, s = a.ravel(), s.ravel()
    # Ellipse radius in direction a, flaring linearly, with pleats that deepen towards the hem.
    rx, rz = waist[0] + FLARE * s, waist[1] + FLARE * s
    radius = rx * rz / np.sqrt((rz * np.sin(a)) ** 2 + (rx * np.cos(a)) ** 2)
    radius = radius * (1 + 0.03 * s * np.sin(12 * a))
    rest = centre + np.stack([radius * np.sin(a), -length * s, radius * np.cos(a)], axis=1)

    rows = np.arange(DOWN)[:, None] * AROUND
    cols = np.arange(AROUND)[None, :]
    v00, v01 = rows + cols, rows + (cols + 1) % AROUND
    v10, v11 = v00 + AROUND, v01 + AROUND
    # Counter-clockwise seen from outside, so normals point away from the legs.
    faces = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])

    skin = np.zeros((len(rest), NUM_JOINTS))
    side = np.sin(a)  # +1 over the left leg, -1 over the right
    skin[:, J["left_hip"]] = HIP_FOLLOW * s * (0.5 + 0.5 * side)
    skin[:, J["right_hip"]] = HIP_FOLLOW * s * (0.5 - 0.5 * side)
    skin[:, J["pelvis"]] = 1 - skin[:, J["left_hip"]] - skin[:, J["right_hip"]]
    return Skirt(rest, faces.astype(np.int64), skin, a, s, centre, radius, length)


def _spring(drive: np.ndarray, hz: float, damping: float) -> np.ndarray:
    """x'' = -w^2 x - 2 z w x' + drive, semi-implicit Euler on the SIM_HZ clock, from rest."""
    omega, dt = 2 * np.pi * hz, 1.0 / SIM_HZ
    x = np.zeros(drive.shape[1:])
    v = np.zeros(drive.shape[1:])
    out = np.empty_like(drive)
    for k, force in enumerate(drive):
        v = v + dt * (force - omega * omega * x - 2 * damping * omega * v)
        x = x + dt * v
        out[k] = x
    return out


@dataclass
class SecondaryMotion:
    """Per-frame state of the skirt's free dynamics."""

    sway: np.ndarray  # (T, 3) world-space lag of the hem behind the pelvis, metres
    twist: np.ndarray  # (T,) lag of the hem behind the body's turn, radians
    flare: np.ndarray  # (T,) relative widening of the hem from spinning
    times: np.ndarray  # (T,) seconds


def secondary_motion(times: np.ndarray, pelvis_position, heading, warmup: float = 3.0) -> SecondaryMotion:
    """Integrate the springs from rest at `times[0] - warmup`, driven by the pelvis.

    `pelvis_position(t) -> (n, 3)` and `heading(t) -> (n,)` (yaw, radians) are continuous in t;
    the hem lags behind their accelerations like a pendulum hanging from the waist.
    """
    clock = np.arange(times[0] - warmup, times[-1] + 2 / SIM_HZ, 1 / SIM_HZ)
    dt = 1 / SIM_HZ
    position = pelvis_position(clock)
    accel = np.gradient(np.gradient(position, dt, axis=0), dt, axis=0)
    yaw = heading(clock)
    yaw_rate = np.gradient(yaw, dt)
    yaw_accel = np.gradient(yaw_rate, dt)
    sway = _spring(-accel * np.array([1.0, 0.3, 1.0]), hz=0.8, damping=0.2)
    twist = _spring(-yaw_accel[:, None], hz=0.9, damping=0.25)[:, 0]
    flare = _spring(3.0 * yaw_rate[:, None] ** 2, hz=1.0, damping=0.4)[:, 0]
    pick = lambda series: np.stack([np.interp(times, clock, c) for c in np.atleast_2d(series.T)], axis=-1)  # noqa: E731
    return SecondaryMotion(pick(sway), pick(twist)[:, 0], pick(flare)[:, 0], np.asarray(times, dtype=np.float64))


def pose_skirt(skirt: Skirt, transforms: np.ndarray, transl: np.ndarray, motion: SecondaryMotion,
               wave_phase: float = 0.0) -> np.ndarray:
    """(T, Vg, 3) world positions: canonical twist/flare/waves, then skinning, then the world-space sway.

    `transforms` (T, 55, 4, 4) and `transl` (T, 3) are the body's skinning transforms and translation.
    """
    s2 = skirt.drop**2  # free motion grows from nothing at the waist to full at the hem
    out = np.empty((len(transforms), len(skirt.rest), 3))
    for k, t in enumerate(motion.times):
        angle = skirt.angle + motion.twist[k] * s2
        waves = 0.02 * np.sin(5 * angle - 2 * np.pi * 0.7 * t + wave_phase) + 0.01 * np.sin(8 * angle + 2 * np.pi * 1.1 * t)
        radius = skirt.radius * (1 + motion.flare[k] * s2) + waves * s2
        local = np.stack([radius * np.sin(angle), skirt.rest[:, 1] - skirt.centre[1], radius * np.cos(angle)], axis=1)
        canonical = skirt.centre + local
        per_vertex = np.einsum("vj,jrc->vrc", skirt.weights, transforms[k])
        posed = np.einsum("vrc,vc->vr", per_vertex[:, :3, :3], canonical) + per_vertex[:, :3, 3]
        sway = motion.sway[k]
        # The hem swings on a pendulum of the skirt's length, so it rises as it swings out.
        lift = (sway[0] ** 2 + sway[2] ** 2) / (2 * skirt.length)
        out[k] = posed + transl[k] + s2[:, None] * (sway + np.array([0.0, lift, 0.0]))
    return out
