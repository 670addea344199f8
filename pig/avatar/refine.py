"""Global body-model refinement: an MLP on [mean anchor feature, gamma(t)] predicting shape and pose residuals.

Implements Eqs. 12-14: {d beta_t, d theta_t} = Psi_model([z_bar, gamma(t)]); d beta is the mean of
d beta_t over all timesteps; beta = beta_init + d beta, theta_t = theta_init_t + d theta_t.
"""
from __future__ import annotations

import torch
from torch import nn

from pig.body.model import NUM_JOINTS

from .decoders import mlp

BODY_JOINTS = list(range(0, 22))  # global orientation + 21 body joints
FACE_JOINTS = [22, 23, 24]  # jaw, eyes
HAND_JOINTS = list(range(25, 55))


def refined_joints(body: bool, face: bool, hands: bool) -> list[int]:
    return (BODY_JOINTS if body else []) + (FACE_JOINTS if face else []) + (HAND_JOINTS if hands else [])


class BodyRefiner(nn.Module):
    """Psi_model; joints left out of `joints` (and shape if `num_betas` is 0) are not predicted."""

    def __init__(self, inputs: int, width: int, layers: int, num_betas: int, joints: list[int], output_gain: float = 0.01):
        super().__init__()
        self.num_betas = num_betas
        self.register_buffer("joints", torch.tensor(joints, dtype=torch.long), persistent=False)
        self.outputs = num_betas + 3 * len(joints)
        self.net = mlp(inputs, width, layers, self.outputs, output_gain) if self.outputs else None

    def forward(self, z_mean: torch.Tensor, gamma_all: torch.Tensor, timesteps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z_mean (d,), gamma_all (T, 2F) for every training timestep, timesteps (K,) 0-based.

        Returns d beta (num_betas,) averaged over all T timesteps and d theta (K, 55, 3) (zeros
        on joints that are not refined).
        """
        pose = torch.zeros(timesteps.shape[0], NUM_JOINTS, 3, dtype=z_mean.dtype, device=z_mean.device)
        if self.net is None:
            return z_mean.new_zeros(self.num_betas), pose
        count = gamma_all.shape[0]
        y = torch.cat([z_mean.expand(count, -1), gamma_all.to(z_mean.dtype)], dim=-1)
        # Shape residuals need every timestep (their mean); pose residuals only the sampled ones.
        out = self.net(y) if self.num_betas else self.net(y[timesteps])
        betas = out[:, : self.num_betas].mean(dim=0)
        pose_out = out[timesteps, self.num_betas :] if self.num_betas else out
        pose = pose.index_copy(1, self.joints, pose_out.reshape(-1, len(self.joints), 3))
        return betas, pose
