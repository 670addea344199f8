"""The avatar: canonical anchors + latent field, transported by the body model and decoded into Gaussians.

Composes Eqs. 1-14: z(x~) from the grid (Eq. 1), transport (Eqs. 2-3), decoder input [z, gamma(t), l~]
(Eqs. 6-7), decoders (Eqs. 8-9), mu = x(theta_t) + d mu and q = q(R) d q (Eqs. 10-11), refinement (12-14).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from pig.body.model import BodyModel
from pig.body.params import SmplxParams
from pig.body.rotation import matrix_to_quaternion, quaternion_multiply
from pig.body.transport import barycentric_points, surface_frames, transport_points, transport_rotation

from .anchors import Attachment, triangle_areas
from .config import AvatarConfig
from .decoders import AnchorDecoder, DecodedAnchors
from .nearest_pose import nearest_timestep
from .refine import BodyRefiner, refined_joints
from .time_embedding import lod_input, num_frequencies, time_embedding


@dataclass
class Gaussians:
    """Splat parameters of K timesteps: means (K, n, 3), quats (K, n, 4) wxyz, scales (K, n, 3),
    opacities (K, n), sh (K, n, (deg+1)^2, 3); n = anchors of the level."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor


class AvatarModel(nn.Module):
    """Anchors on a canonical body, a latent field, decoders and the body refiner.

    `grid` maps canonical points (n, 3) to features (n, d); `anchors` is a module whose `forward()`
    returns the current canonical anchor positions (N, 3) (a preconditioned parameter), or None for
    the `fixed_anchors` ablation. Timesteps are 0-based indices into the training frames `frame_ids`.
    """

    def __init__(self, cfg: AvatarConfig, body_model: BodyModel, params: SmplxParams, frame_ids, attachment: Attachment,
                 canonical_vertices: torch.Tensor, grid: nn.Module, anchors: nn.Module | None):
        super().__init__()
        self.cfg = cfg
        self.body_model = body_model
        self.grid = grid
        self.anchors = anchors
        self.level_sizes = list(attachment.level_sizes)
        self.num_timesteps = params.num_frames
        self.frame_ids = [int(f) for f in frame_ids]
        dtype = body_model.dtype
        faces = body_model.faces
        self.register_buffer("face_ids", torch.as_tensor(attachment.face_ids, dtype=torch.long))
        self.register_buffer("bary", torch.as_tensor(attachment.bary, dtype=dtype))
        self.register_buffer("x_init", torch.as_tensor(attachment.x_init, dtype=dtype))
        canon = canonical_vertices.to(dtype)[None]
        self.register_buffer("canonical_frames", surface_frames(canon, faces, self.face_ids)[0])
        # Per-level scale prior: the mean spacing sqrt(area / N_l) of area-uniform samples.
        area = float(triangle_areas(canonical_vertices.double().cpu().numpy(), faces.cpu().numpy()).sum())
        self.log_scale_prior = [math.log(cfg.scale_prior * math.sqrt(area / n)) for n in self.level_sizes]
        self.register_buffer("pose_init", torch.as_tensor(params.full_pose, dtype=dtype))
        self.register_buffer("betas_init", torch.as_tensor(params.betas, dtype=dtype))
        self.register_buffer("expression", torch.as_tensor(params.expression, dtype=dtype))
        self.register_buffer("transl", torch.as_tensor(params.transl, dtype=dtype))
        self.register_buffer("gamma_all", time_embedding(torch.arange(self.num_timesteps), self.num_timesteps).to(dtype))
        features = grid.features
        inputs = features + 2 * num_frequencies(self.num_timesteps) + 1
        self.decoder = AnchorDecoder(inputs, cfg.hidden_width, cfg.hidden_layers, cfg.sh_degree, single_mlp=cfg.single_mlp,
                                     offsets=cfg.offsets, init_opacity=cfg.init_opacity, offset_scale=cfg.offset_scale,
                                     output_gain=cfg.output_init_gain)
        joints = refined_joints(cfg.refine_body, cfg.refine_face, cfg.refine_hands)
        num_betas = len(params.betas) if cfg.refine_shape else 0
        self.refiner = BodyRefiner(features + 2 * num_frequencies(self.num_timesteps), cfg.refine_hidden_width,
                                   cfg.refine_hidden_layers, num_betas, joints, cfg.output_init_gain)
        self._compiled_posing = None  # `_posed_splats_sync_free` compiled by compile_posing

    @property
    def num_levels(self) -> int:
        return len(self.level_sizes)

    def canonical_anchors(self) -> torch.Tensor:
        """Current canonical anchor positions (N, 3)."""
        return self.x_init if self.anchors is None else self.anchors()

    def refined_params(self, timesteps: torch.Tensor, z_mean: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Eq. 14: (betas (nb,), full pose (K, 55, 3)) of training timesteps after refinement."""
        if self.refiner.net is None or z_mean is None:
            return self.betas_init, self.pose_init[timesteps]
        d_betas, d_pose = self.refiner(z_mean, self.gamma_all, timesteps)
        betas = self.betas_init + d_betas if d_betas.numel() else self.betas_init
        return betas, self.pose_init[timesteps] + d_pose

    def forward(self, timesteps: torch.Tensor, lod: int, poses: torch.Tensor | None = None,
                transl: torch.Tensor | None = None) -> Gaussians:
        """Gaussians of `timesteps` (K,) at level `lod` (0 = coarsest).

        `poses` (K, 55, 3) / `transl` (K, 3) replace the training pose (novel pose): the query pose
        drives the transport with the refined shape, while `timesteps` still feed gamma(t).
        """
        if not 0 <= lod < self.num_levels:
            raise ValueError(f"lod must lie in 0..{self.num_levels - 1}, got {lod}")
        timesteps = timesteps.to(self.pose_init.device)
        x = self.canonical_anchors()
        z, z_mean = self.anchor_features(x, lod)
        betas, pose = self.refined_params(timesteps, z_mean)
        if poses is not None:
            pose = poses.to(pose)
        translation = self.transl[timesteps] if transl is None else transl.to(self.transl)
        decoded = self.decode(z, timesteps, lod)
        # The compiled region serves training steps only: evaluations (no grad) vary K and would recompile it.
        posing = self._compiled_posing if self._compiled_posing is not None and torch.is_grad_enabled() else self.posed_splats
        return posing(x, lod, pose, betas, self.expression[timesteps], translation, decoded)

    def posed_splats(self, x: torch.Tensor, lod: int, pose: torch.Tensor, betas: torch.Tensor | None,
                     expression: torch.Tensor | None, translation: torch.Tensor, decoded: DecodedAnchors,
                     sync_free: bool = False, rest: tuple[torch.Tensor, torch.Tensor] | None = None) -> Gaussians:
        """Eqs. 2-3 and 10-11: the body in `pose` (K, 55, 3), the level's anchors among canonical `x` (N, 3)
        transported onto it, and the splats of their `decoded` attributes. `rest`: the body's rest shape in place
        of betas and expression (BodyModel.forward)."""
        body = self.body_model(pose, betas, expression, translation, rest=rest)
        centres, rotation = self.transport(x, body.vertices, lod, sync_free)
        return self.splats(centres, rotation, decoded)

    def _posed_splats_sync_free(self, *args) -> Gaussians:
        return self.posed_splats(*args, sync_free=True)

    def compile_posing(self, mode: str = "default") -> None:
        """Training steps run `posed_splats` through torch.compile: the body's rigid chain and the transport's
        3 x 3 products fuse into a few kernels (pig.body.rotation.small_matmul), forward and backward. It runs
        sync-free (the same frames, pig.body.transport.surface_frames), so the step has no host synchronisation
        there; one static graph per LOD. `mode`: torch.compile's."""
        if self._compiled_posing is None:
            self._compiled_posing = torch.compile(self._posed_splats_sync_free, dynamic=False, mode=mode)

    def anchor_features(self, x: torch.Tensor, lod: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Grid features z (n, d) of the level's anchors among canonical anchors `x` (N, 3), and the refiner's
        z_bar (d,) over all anchors (None without a refiner)."""
        n = self.level_sizes[lod]
        refine = self.refiner.net is not None
        # Only the refiner needs every anchor's feature (its global mean z_bar); decoders use the level's.
        z_all = self.grid(x if refine else x[:n])
        return z_all[:n], z_all.mean(dim=0) if refine else None

    def transport(self, x: torch.Tensor, vertices: torch.Tensor, lod: int,
                  sync_free: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Eqs. 2-3 for the level's anchors: posed centres (K, n, 3) and rotations (K, n, 3, 3) on the
        posed body `vertices` (K, V, 3); `x` (N, 3) are the canonical anchors (`sync_free`: see surface_frames)."""
        n = self.level_sizes[lod]
        face_ids = self.face_ids[:n]
        faces = self.body_model.faces
        frames = surface_frames(vertices, faces, face_ids, sync_free)
        rotation = transport_rotation(frames, self.canonical_frames[:n])
        posed_init = barycentric_points(vertices, faces, face_ids, self.bary[:n])
        return transport_points(x[:n], self.x_init[:n], posed_init, rotation), rotation

    def decode(self, z: torch.Tensor, timesteps: torch.Tensor, lod: int) -> DecodedAnchors:
        """Eqs. 6-9: decoded attributes (K, n, ...) of the level's features z (n, d) at `timesteps` (K,)."""
        count, n = timesteps.shape[0], z.shape[0]
        gamma = self.gamma_all[timesteps].to(z.dtype)
        level = torch.full((count, n, 1), lod_input(lod, self.num_levels), dtype=z.dtype, device=z.device)
        y = torch.cat([z.expand(count, n, -1), gamma[:, None].expand(count, n, -1), level], dim=-1)
        return self.decoder(y, self.log_scale_prior[lod])

    def splats(self, centres: torch.Tensor, rotation: torch.Tensor, decoded: DecodedAnchors) -> Gaussians:
        """Eqs. 10-11: mu = x(theta) + d mu, q = q(R) d q, with the decoded scale, opacity and SH.

        With `offset_frame: local` the decoded d mu is in the anchor's frame and turns with it: mu = x(theta) + R d mu.
        """
        offset = decoded.offset
        if self.cfg.offset_frame == "local":
            offset = torch.einsum("...ij,...j->...i", rotation.to(offset.dtype), offset)
        quats = quaternion_multiply(matrix_to_quaternion(rotation), decoded.rotation)
        return Gaussians(means=centres + offset, quats=quats, scales=decoded.scale, opacities=decoded.opacity,
                         sh=decoded.sh)

    def timestep_of_frame(self, frame_id: int) -> int:
        """Training timestep index of a training frame id."""
        try:
            return self.frame_ids.index(int(frame_id))
        except ValueError:
            raise ValueError(f"frame {frame_id} is not a training frame (training frames: "
                             f"{self.frame_ids[0]}..{self.frame_ids[-1]}); use nearest_timestep for novel poses") from None

    def nearest_timestep(self, full_pose: torch.Tensor) -> int:
        """Training timestep whose pose is nearest (summed per-joint geodesic distance) to (55, 3) `full_pose`."""
        query = torch.as_tensor(full_pose, dtype=self.pose_init.dtype, device=self.pose_init.device).reshape(1, -1, 3)
        return int(nearest_timestep(query, self.pose_init)[0])

    @torch.no_grad()
    def gaussians(self, frame_index: int, lod: int, pose: SmplxParams | None = None) -> tuple[torch.Tensor, ...]:
        """Render-stage entry: (means, quats, scales, opacities, sh) of one timestep, each without the K axis.

        `frame_index` is the training timestep (0-based; see `timestep_of_frame`, `nearest_timestep`).
        `pose`, a one-row SmplxParams, overrides the body pose and translation (novel pose).
        """
        steps = torch.tensor([frame_index])
        poses = transl = None
        if pose is not None:
            poses = torch.as_tensor(np.asarray(pose.full_pose).reshape(1, -1, 3))
            transl = torch.as_tensor(np.asarray(pose.transl).reshape(1, 3))
        g = self(steps, lod, poses, transl)
        return g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0]
