"""EasyMocap's SMPL-X parameters (`Rh`, `Th`, `poses` with hand PCA, `shapes`, `expression`) -> standard SMPL-X.

EasyMocap poses the body as `V = R(Rh) X + Th`, with `X` the model posed by `poses` (whose first 3 values, the
root, are kept zero) and shaped by `shapes` and `expression` (zju3dv/EasyMocap `easymocap/smplmodel/body_model.py`,
lines 343-368: the expression joins the shape coefficients before `lbs`, and the vertices are rotated by `Rh` and
moved by `Th` afterwards). Standard SMPL-X rotates about the pelvis joint `J0` of the shaped body instead, so the
same vertices need `global_orient = R(Rh) R(poses[:3])` and `transl = Th + R(Rh) J0 - J0`, `J0` regressed after the
shape *and* expression blend. EasyMocap's inverse, `convert_from_standard_smpl` (same file, lines 265-295, and
`easymocap/bodymodel/smpl.py` lines 278-298), regresses `J0` from its `shapes` argument alone (lines 279-284), so
the expression counts only where the caller appends it to the shapes; its `convert_to_standard_smpl` (`bodymodel/smpl.py` lines 244-276) adds `delta_center`, whose
definition is commented out (lines 258-261), so it raises a NameError; with that term gone its translation,
`Th - (R(Rh) J0 + J0)` (line 265), still has the wrong sign on `R(Rh) J0`. No paper equation: data preparation.

Poses (`body_model.py` lines 56 and 210-248): 66 + 2k + 9 values, body (22 joints, root first), k left and k right
hand PCA coefficients, then jaw and eyes (EasyMocap's SMPL-X form; its default k is 6, line 191); or the 165-value
full form in SMPL-X's own joint order. The hand PCA goes through the body model's `hands_components{l,r}` rows
(`poses @ components[:k]`, lines 235-236); with `flat_hand_mean=False` the model's `hands_mean` is added (lines
237-239; EasyMocap's SMPL-X layer uses the flat hand, line 199).
"""
from __future__ import annotations

import numpy as np
import torch

from .model import LEFT_HAND, NUM_JOINTS, RIGHT_HAND, BodyModel
from .params import ParamsError, SmplxParams
from .rotation import axis_angle_to_matrix, matrix_to_axis_angle

FULL_POSE = NUM_JOINTS * 3  # 165
BODY = 22 * 3  # root + 21 body joints
HEAD = 3 * 3  # jaw, left eye, right eye
HEAD_JOINTS = slice(22, 25)
OTHER_MODELS = {72: "an SMPL fit (24 joints)", 78: "an SMPL+H fit (22 joints and 2 x 6 hand PCA values)"}


def hand_components_of(length: int, source: str) -> int:
    """The number of hand PCA components k a pose vector of `length` values holds (0: the full 165-value form);
    ParamsError naming `source` for a length that fits no SMPL-X form."""
    if length == FULL_POSE:
        return 0
    k, odd = divmod(length - BODY - HEAD, 2)
    if odd or not 1 <= k < 45:
        what = OTHER_MODELS.get(length, "no SMPL-X form")
        raise ParamsError(f"{source}: 'poses' has {length} values, {what}; expected EasyMocap's SMPL-X forms, "
                          f"{BODY} + 2k + {HEAD} values (body, k hand PCA values a hand with 1 <= k <= 44, jaw and "
                          f"eyes; 87 with its default k = 6) or the full {FULL_POSE}")
    return k


def full_pose(poses: np.ndarray, model: BodyModel, flat_hand_mean: bool, source: str) -> np.ndarray:
    """(N, 55, 3) axis-angle SMPL-X pose, flat-hand-mean convention, of EasyMocap `poses` (N, L); the root stays
    as stored (EasyMocap's `Rh` is applied by `to_standard`)."""
    poses = np.asarray(poses, dtype=np.float64)
    n = poses.shape[0]
    k = hand_components_of(poses.shape[1], source)
    if k == 0:
        full = poses.reshape(n, NUM_JOINTS, 3).copy()
    else:
        components = model.hands_components.detach().cpu().double().numpy()
        if not model.has_hand_components:
            raise ParamsError(f"{source}: 'poses' holds {k} hand PCA values a hand, but the body model {model.source} "
                              "has no 'hands_componentsl' / 'hands_componentsr' to turn them into joint rotations "
                              "(use the SMPL-X model file the fit was made with)")
        if k > components.shape[1]:
            raise ParamsError(f"{source}: 'poses' holds {k} hand PCA values a hand, but the body model "
                              f"{model.source} has only {components.shape[1]} hand components")
        full = np.zeros((n, NUM_JOINTS, 3))
        full[:, :22] = poses[:, :BODY].reshape(n, 22, 3)
        full[:, LEFT_HAND] = (poses[:, BODY:BODY + k] @ components[0, :k]).reshape(n, 15, 3)
        full[:, RIGHT_HAND] = (poses[:, BODY + k:BODY + 2 * k] @ components[1, :k]).reshape(n, 15, 3)
        full[:, HEAD_JOINTS] = poses[:, BODY + 2 * k:].reshape(n, 3, 3)
    if not flat_hand_mean:
        mean = model.hands_mean.detach().cpu().double().numpy()
        full[:, LEFT_HAND] += mean[LEFT_HAND]
        full[:, RIGHT_HAND] += mean[RIGHT_HAND]
    return full


def to_standard(Rh: np.ndarray, Th: np.ndarray, poses: np.ndarray, shapes: np.ndarray, expression: np.ndarray,
                model: BodyModel, flat_hand_mean: bool = True, source: str = "EasyMocap parameters") -> SmplxParams:
    """Standard SMPL-X parameters posing `model` exactly as EasyMocap's (N frames): Rh, Th (N, 3), poses (N, L),
    shapes (nb,) shared by the frames, expression (N, ne); the pelvis in the model's dtype (build it in float64)."""
    Rh, Th = np.asarray(Rh, dtype=np.float64), np.asarray(Th, dtype=np.float64)
    shapes, expression = np.asarray(shapes, dtype=np.float64), np.asarray(expression, dtype=np.float64)
    if shapes.shape[-1] > model.num_betas:
        raise ParamsError(f"{source}: 'shapes' has {shapes.shape[-1]} values, the body model {model.source} has "
                          f"{model.num_betas} shape directions")
    pose = full_pose(poses, model, flat_hand_mean, source)
    rotation = axis_angle_to_matrix(torch.from_numpy(Rh))
    root = matrix_to_axis_angle(rotation @ axis_angle_to_matrix(torch.from_numpy(pose[:, 0])))
    pose[:, 0] = root.numpy()
    with torch.no_grad():
        j0 = _pelvis(model, shapes, expression)
    transl = Th + (rotation.numpy() @ j0[..., None])[..., 0] - j0
    return SmplxParams(full_pose=pose, betas=shapes, expression=expression, transl=transl)


def _pelvis(model: BodyModel, shapes: np.ndarray, expression: np.ndarray) -> np.ndarray:
    """(N, 3) pelvis joint of the rest body after the shape and expression blend."""
    _, joints = model.rest_shape(expression.shape[0], torch.from_numpy(shapes).to(model.dtype)[None],
                                 torch.from_numpy(expression).to(model.dtype))
    return joints[:, 0].double().numpy()
