"""The SMPL-X joint tree: joint count, parents, names and the hands' slices of the (55, 3) full pose.

Plain constants (FORMATS.md), apart from the skinning model, so that the capture readers, which the workflow
imports at DAG-building time, need no torch.
"""
from __future__ import annotations

NUM_JOINTS = 55
SMPLX_PARENTS = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
]
_FINGERS = ["index", "middle", "pinky", "ring", "thumb"]
SMPLX_JOINT_NAMES = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
    "left_eye", "right_eye",
] + [f"{side}_{finger}{k}" for side in ("left", "right") for finger in _FINGERS for k in (1, 2, 3)]
# Slices of the 55 x 3 full pose (FORMATS.md: global, body 21, jaw, eyes, hands 15 + 15).
LEFT_HAND = slice(25, 40)
RIGHT_HAND = slice(40, 55)
