"""Linear blend skinning of a body model stored in the SMPL-X npz layout (FORMATS.md).

Order: shape + expression blend, joints regressed from the shaped vertices, pose blend from
(R_j - I) of joints 1..54, rigid chain, skinning, translation last.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .npz import read_npz
from .rotation import axis_angle_to_matrix, small_matmul, small_matvec
# SMPLX_PARENTS and SMPLX_JOINT_NAMES: part of this module's interface, as its importers use them.
from .skeleton import LEFT_HAND, NUM_JOINTS, RIGHT_HAND, SMPLX_JOINT_NAMES, SMPLX_PARENTS  # noqa: F401

REQUIRED_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
HAND_MEAN_KEYS = ("hands_meanl", "hands_meanr")  # optional; zero when absent
# Optional (k <= 45 rows of 45): the hand poses' principal directions, through which fits stored as hand PCA
# coefficients (EasyMocap's, pig.body.easymocap) become axis-angle; a real SMPL-X file holds 45 each.
HAND_COMPONENT_KEYS = ("hands_componentsl", "hands_componentsr")


class BodyModelError(ValueError):
    """A body-model file does not follow the SMPL-X npz layout."""


@dataclass
class BodyOutput:
    vertices: torch.Tensor  # (B, V, 3) posed, translated
    joints: torch.Tensor  # (B, 55, 3) posed, translated
    transforms: torch.Tensor  # (B, 55, 4, 4) skinning transforms A_j (translation not included)
    shaped_vertices: torch.Tensor  # (B, V, 3) rest pose after shape + expression blend


def _dense(array) -> np.ndarray:
    if hasattr(array, "toarray"):  # scipy sparse J_regressor in some files
        return array.toarray()
    if array.dtype == object:  # a sparse matrix pickled into an npz 0-d object array
        return np.asarray(array.item().toarray())
    return np.asarray(array)


def _shape_split(num_columns: int) -> int:
    """Index where expression columns start: 300 in 400-column files, half in older ones."""
    return 300 if num_columns >= 400 else num_columns // 2


class BodyModel(nn.Module):
    """SMPL-X-layout skinning model; `forward` is batched over frames, in the buffers' dtype.

    Build with `dtype=torch.float64` for full precision: `.to(torch.float64)` of a float32 model
    keeps the float32-rounded buffers.
    """

    def __init__(self, arrays: dict[str, np.ndarray], source: str = "<arrays>", dtype: torch.dtype = torch.float32):
        super().__init__()
        missing = [k for k in REQUIRED_KEYS if k not in arrays]
        if missing:
            raise BodyModelError(f"{source}: missing key(s) {missing}; an SMPL-X model npz has {list(REQUIRED_KEYS)}")
        v_template = np.asarray(arrays["v_template"], dtype=np.float64)
        num_vertices = v_template.shape[0]
        faces = np.asarray(arrays["f"], dtype=np.int64)
        shapedirs = np.asarray(arrays["shapedirs"], dtype=np.float64)
        posedirs = np.asarray(arrays["posedirs"], dtype=np.float64)
        j_regressor = _dense(arrays["J_regressor"]).astype(np.float64)
        weights = np.asarray(arrays["weights"], dtype=np.float64)
        parents = np.asarray(arrays["kintree_table"])[0].astype(np.int64).copy()
        parents[0] = -1
        expected = {
            "v_template": (v_template.shape, (num_vertices, 3)),
            "shapedirs": (shapedirs.shape[:2], (num_vertices, 3)),
            "posedirs": (posedirs.shape, (num_vertices, 3, (NUM_JOINTS - 1) * 9)),
            "J_regressor": (j_regressor.shape, (NUM_JOINTS, num_vertices)),
            "weights": (weights.shape, (num_vertices, NUM_JOINTS)),
            "kintree_table": (parents.shape, (NUM_JOINTS,)),
        }
        for key, (found, want) in expected.items():
            if tuple(found) != tuple(want):
                raise BodyModelError(f"{source}: '{key}' has shape {tuple(found)}, expected {want}")
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= num_vertices:
            raise BodyModelError(f"{source}: 'f' must be (F, 3) vertex indices below {num_vertices}")
        if np.any(parents[1:] >= np.arange(1, NUM_JOINTS)) or np.any(parents[1:] < 0):
            raise BodyModelError(f"{source}: kintree_table parents must precede their children")
        split = _shape_split(shapedirs.shape[2])
        self.num_betas = split
        self.num_expression = shapedirs.shape[2] - split
        self.source = source
        self.register_buffer("v_template", torch.from_numpy(v_template))
        self.register_buffer("faces", torch.from_numpy(faces), persistent=False)
        self.register_buffer("shapedirs", torch.from_numpy(shapedirs))
        # (486, V*3): row k holds the vertex offsets of pose-feature entry k.
        self.register_buffer("posedirs", torch.from_numpy(posedirs.reshape(num_vertices * 3, -1).T.copy()))
        self.register_buffer("j_regressor", torch.from_numpy(j_regressor))
        self.register_buffer("weights", torch.from_numpy(weights))
        # A device tensor, not a list: indexing with a list copies it to the device on every call, which a
        # CUDA graph cannot capture (pig.avatar.driver's frame graph).
        self.register_buffer("parent_index", torch.from_numpy(parents[1:].copy()), persistent=False)
        # The rigid chain one tree depth at a time: ~10 batched products instead of 54 sequential ones.
        depth = np.zeros(NUM_JOINTS, dtype=np.int64)
        for j in range(1, NUM_JOINTS):
            depth[j] = depth[parents[j]] + 1
        self.chain_depth = int(depth.max())
        for d in range(1, self.chain_depth + 1):
            joints = np.flatnonzero(depth == d)
            self.register_buffer(f"chain_joints{d}", torch.from_numpy(joints), persistent=False)
            self.register_buffer(f"chain_parents{d}", torch.from_numpy(parents[joints]), persistent=False)
        hands_mean = np.zeros((NUM_JOINTS, 3))
        for key, part in zip(HAND_MEAN_KEYS, (LEFT_HAND, RIGHT_HAND)):
            if key in arrays:
                hands_mean[part] = np.asarray(arrays[key], dtype=np.float64).reshape(15, 3)
        self.register_buffer("hands_mean", torch.from_numpy(hands_mean))
        components = [self._hand_components(arrays, key, source) for key in HAND_COMPONENT_KEYS]
        self.has_hand_components = components[0] is not None and components[1] is not None
        if components[0] is None or components[1] is None:
            components = [np.zeros((0, 45)), np.zeros((0, 45))]
        if components[0].shape != components[1].shape:
            raise BodyModelError(f"{source}: 'hands_componentsl' has shape {components[0].shape} but "
                                 f"'hands_componentsr' {components[1].shape}; expected one shape (k, 45)")
        # (2, k, 45): left then right; row i is the i-th principal direction of the 15 x 3 hand pose.
        self.register_buffer("hands_components", torch.from_numpy(np.stack(components)))
        self.to(dtype)

    @staticmethod
    def _hand_components(arrays: dict, key: str, source: str) -> np.ndarray | None:
        if key not in arrays:
            return None
        value = np.asarray(arrays[key], dtype=np.float64)
        if value.ndim != 2 or value.shape[1] != 45 or not 1 <= value.shape[0] <= 45 or not np.all(np.isfinite(value)):
            raise BodyModelError(f"{source}: '{key}' has shape {value.shape}, expected finite (k, 45) with k <= 45 "
                                 "(hand pose principal components)")
        return value

    @classmethod
    def from_file(cls, path: str | Path, dtype: torch.dtype = torch.float32) -> "BodyModel":
        path = Path(path)
        if not path.exists():  # a FIFO or device is refused by read_npz, named as such
            raise BodyModelError(f"body model file {path} does not exist (expected an SMPL-X npz such as SMPLX_NEUTRAL.npz)")
        arrays = read_npz(path, BodyModelError, f"an SMPL-X model with {list(REQUIRED_KEYS)}",
                          keys=REQUIRED_KEYS + HAND_MEAN_KEYS + HAND_COMPONENT_KEYS, pickled=("J_regressor",))
        return cls(arrays, source=str(path), dtype=dtype)

    @property
    def dtype(self) -> torch.dtype:
        return self.v_template.dtype

    def with_hand_mean(self, full_pose: torch.Tensor) -> torch.Tensor:
        """Add the model's mean hand pose (for parameters fitted with `flat_hand_mean=False`)."""
        return full_pose + self.hands_mean.to(full_pose)

    def forward(
        self,
        full_pose: torch.Tensor,
        betas: torch.Tensor | None = None,
        expression: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
        rest: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> BodyOutput:
        """Pose the model.

        full_pose: (B, 55, 3) or (B, 165) axis-angle; betas: (nb,), (1, nb) or (B, nb), nb <= num_betas;
        expression: (B, ne) or (ne,); transl: (B, 3). Missing parameters are zeros. `rest`: the (shaped
        vertices (B, V, 3), rest joints (B, 55, 3)) of `rest_shape`, in place of betas and expression, where
        they are computed once for many poses (the real-time frame, pig.avatar.driver).
        """
        full_pose = full_pose.to(self.dtype).reshape(full_pose.shape[0], NUM_JOINTS, 3)
        shaped, joints_rest = self.rest_shape(full_pose.shape[0], betas, expression) if rest is None else rest
        return self._pose(full_pose, shaped, joints_rest, transl)

    def rest_shape(self, batch: int, betas: torch.Tensor | None = None,
                   expression: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Shaped rest-pose vertices (B, V, 3) (shape + expression blend) and the joints regressed from them
        (B, 55, 3); arguments as `forward`'s."""
        dtype, device = self.dtype, self.v_template.device
        coeffs = torch.zeros(batch, self.shapedirs.shape[2], dtype=dtype, device=device)
        if betas is not None:
            betas = betas.to(dtype).reshape(-1, betas.shape[-1])
            if betas.shape[-1] > self.num_betas:
                raise BodyModelError(f"{self.source}: {betas.shape[-1]} betas given, the model has {self.num_betas}")
            coeffs[:, : betas.shape[-1]] = betas.expand(batch, -1)
        if expression is not None:
            expression = expression.to(dtype).reshape(-1, expression.shape[-1])
            count = min(expression.shape[-1], self.num_expression)
            coeffs[:, self.num_betas : self.num_betas + count] = expression[:, :count].expand(batch, -1)
        shaped = self.v_template + torch.einsum("vcs,bs->bvc", self.shapedirs, coeffs)
        return shaped, torch.einsum("jv,bvc->bjc", self.j_regressor, shaped)

    def _pose(self, full_pose: torch.Tensor, shaped: torch.Tensor, joints_rest: torch.Tensor,
              transl: torch.Tensor | None) -> BodyOutput:
        """Pose blend, rigid chain and skinning of the shaped rest body; `full_pose` (B, 55, 3)."""
        dtype, device = self.dtype, self.v_template.device
        batch = full_pose.shape[0]
        rotations = axis_angle_to_matrix(full_pose)  # (B, 55, 3, 3)
        eye = torch.eye(3, dtype=dtype, device=device)
        pose_feature = (rotations[:, 1:] - eye).reshape(batch, -1)
        blended = shaped + (pose_feature @ self.posedirs).reshape(batch, -1, 3)

        # Rigid chain: G_j = G_parent [R_j | J_j - J_parent].
        rel_joints = joints_rest.clone()
        rel_joints[:, 1:] = joints_rest[:, 1:] - joints_rest[:, self.parent_index]
        local = torch.zeros(batch, NUM_JOINTS, 4, 4, dtype=dtype, device=device)
        local[..., :3, :3] = rotations
        local[..., :3, 3] = rel_joints
        local[..., 3, 3] = 1
        world = local
        for d in range(1, self.chain_depth + 1):
            joints = getattr(self, f"chain_joints{d}")
            world = world.index_copy(1, joints, small_matmul(world[:, getattr(self, f"chain_parents{d}")], local[:, joints]))
        posed_joints = world[..., :3, 3]
        # A_j: same rotation, translation t_j - R_j J_j, so it acts on rest-pose coordinates.
        transforms = world.clone()
        transforms[..., :3, 3] = posed_joints - small_matvec(world[..., :3, :3], joints_rest)

        per_vertex = torch.einsum("vj,bjrc->bvrc", self.weights, transforms)
        vertices = small_matvec(per_vertex[..., :3, :3], blended) + per_vertex[..., :3, 3]
        if transl is not None:
            offset = transl.to(dtype).reshape(-1, 1, 3)
            vertices = vertices + offset
            posed_joints = posed_joints + offset
        return BodyOutput(vertices=vertices, joints=posed_joints, transforms=transforms, shaped_vertices=shaped)
