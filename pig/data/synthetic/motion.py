"""A seeded, smooth body motion for the synthetic capture: SMPL-X full poses and translations as functions of time.

Bends spine, elbows, knees and fingers and turns the body, so the transport of the paper (Eqs. 2-3)
and the pose-conditioned decoders (Eqs. 6-11) see real articulation; continuous in time, so the
garment's secondary motion can be integrated on a finer clock than the frames.
"""
from __future__ import annotations

import numpy as np

from pig.body.model import NUM_JOINTS, SMPLX_JOINT_NAMES

J = {name: i for i, name in enumerate(SMPLX_JOINT_NAMES)}
# The cycles' frequencies (mHz) share no period under 1000 s, so a capture of THuman4's length (2500 frames, 83 s)
# never shows one pose twice: with round frequencies the motion repeated every 20 s, and its evaluation scored the
# same ground-truth pixels more than once.
STEP_HZ = 0.6  # leg and arm cycle
TURN_HZ = 0.24  # slow turn of the whole body
SWAY_HZ = 0.625  # lateral pelvis sway that drives the skirt
SLOW_HZ = 0.309  # spine bend, shoulders, wrists
HEAD_HZ = 0.188
JAW_HZ = 0.686
CURL_HZ = 0.494  # fingers
DRIFT_HZ = 0.308  # forward-backward drift of the whole body


class Motion:
    """`full_pose(t)` (T, 55, 3) axis-angle and `transl(t)` (T, 3) for times `t` in seconds.

    The person stands with feet near y = 0 (`ground_offset` = -lowest rest vertex height relative
    to the world origin) and faces +z on average. Eye poses stay zero (THuman4 stores none).
    """

    def __init__(self, seed: int, ground_offset: float):
        rng = np.random.default_rng(seed)
        self.phase = rng.uniform(0, 2 * np.pi, size=8)
        self.gain = rng.uniform(0.85, 1.15, size=8)
        self.ground_offset = ground_offset

    def _cycles(self, t: np.ndarray):
        step = 2 * np.pi * STEP_HZ * t + self.phase[0]
        turn = 2 * np.pi * TURN_HZ * t + self.phase[1]
        slow = 2 * np.pi * SLOW_HZ * t + self.phase[2]
        return step, turn, slow

    def full_pose(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        step, turn, slow = self._cycles(t)
        g = self.gain
        pose = np.zeros((len(t), NUM_JOINTS, 3))

        def set_(name, x=0.0, y=0.0, z=0.0):
            pose[:, J[name]] = np.stack(np.broadcast_arrays(x, y, z, t)[:3], axis=-1)

        set_("pelvis", x=0.05 * np.sin(step), y=0.5 * g[0] * np.sin(turn))
        # Hip flexion is a negative rotation about x (thigh forward); knee flexion positive (shin back).
        swing = 0.28 * g[1] * np.sin(step)
        set_("left_hip", x=-swing, z=0.05)
        set_("right_hip", x=swing, z=-0.05)
        set_("left_knee", x=0.15 + 0.45 * g[2] * (0.5 - 0.5 * np.cos(step - 0.3)))
        set_("right_knee", x=0.15 + 0.45 * g[2] * (0.5 + 0.5 * np.cos(step - 0.3)))
        set_("left_ankle", x=-0.1 * np.sin(step))
        set_("right_ankle", x=0.1 * np.sin(step))
        for name, share in (("spine1", 0.4), ("spine2", 0.35), ("spine3", 0.25)):
            set_(name, x=share * (0.2 + 0.2 * g[3] * np.sin(slow)), y=share * 0.25 * np.sin(step),
                 z=share * 0.15 * np.sin(step + 1.0))
        set_("neck", x=0.1 * np.sin(slow + 1.0), y=0.15 * np.sin(turn + 0.5))
        set_("head", x=0.05, y=0.25 * g[4] * np.sin(2 * np.pi * HEAD_HZ * t + self.phase[3]))
        set_("jaw", x=0.12 + 0.08 * np.sin(2 * np.pi * JAW_HZ * t + self.phase[4]))
        # Arms come down from the T-pose (about z) and swing against the legs (about y); the
        # person's left arm points along +x, so its signs mirror the right arm's.
        for side, sign in (("left", 1.0), ("right", -1.0)):
            arm_swing = 0.3 * g[5] * np.sin(step + (0.0 if side == "left" else np.pi))
            set_(f"{side}_collar", z=-sign * 0.1)
            set_(f"{side}_shoulder", y=sign * arm_swing, z=-sign * (0.75 + 0.12 * np.sin(slow)))
            bend = 0.4 + 0.9 * g[6] * (0.5 + 0.5 * np.sin(step + 1.2 + (0.0 if side == "left" else np.pi)))
            set_(f"{side}_elbow", y=-sign * bend)
            set_(f"{side}_wrist", x=0.2 * np.sin(slow + 2.0), z=-sign * 0.15)
            curl_phase = self.phase[5] + (0.0 if side == "left" else 1.0)
            curl = 0.25 + 0.2 * g[7] * np.sin(2 * np.pi * CURL_HZ * t + curl_phase)
            for finger in ("index", "middle", "ring", "pinky"):
                for k in (1, 2, 3):
                    # The stand-in's palms face +z: curling towards the palm is a rotation about y.
                    set_(f"{side}_{finger}{k}", y=-sign * curl * (1.2 - 0.2 * k))
            for k in (1, 2, 3):
                set_(f"{side}_thumb{k}", x=0.4 * curl)
        return pose

    def transl(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        step, _, slow = self._cycles(t)
        knee_mean = 0.15 + 0.225 * self.gain[2]
        out = np.zeros((len(t), 3))
        out[:, 0] = 0.055 * self.gain[0] * np.sin(2 * np.pi * SWAY_HZ * t + self.phase[6])
        out[:, 1] = self.ground_offset - 0.03 * knee_mean - 0.015 * np.cos(2 * step)
        out[:, 2] = 0.04 * np.sin(2 * np.pi * DRIFT_HZ * t + self.phase[7])
        return out
