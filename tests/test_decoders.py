"""Anchor decoders (Eqs. 8-11 parameterisations) and the body refinement MLP (Eqs. 12-14)."""
import pytest
import torch

from pig.avatar.decoders import AnchorDecoder
from pig.avatar.refine import BodyRefiner, refined_joints
from pig.avatar.time_embedding import time_embedding


@pytest.mark.parametrize("single_mlp", [False, True])
@pytest.mark.parametrize("sh_degree", [0, 3])
def test_decoder_outputs_are_valid(single_mlp, sh_degree):
    torch.manual_seed(0)
    dec = AnchorDecoder(16 + 6 + 1, 32, 2, sh_degree, single_mlp=single_mlp, output_gain=1.0)
    # Extreme inputs push the raw outputs far out: the parameterisations must still hold.
    y = torch.randn(5, 40, 23) * torch.tensor([1e-3, 1.0, 1e3]).repeat_interleave(torch.tensor([2, 2, 1]))[:, None, None]
    out = dec(y, log_scale_prior=-4.0)
    assert out.offset.shape == (5, 40, 3) and out.rotation.shape == (5, 40, 4) and out.scale.shape == (5, 40, 3)
    assert out.opacity.shape == (5, 40) and out.sh.shape == (5, 40, (sh_degree + 1) ** 2, 3)
    torch.testing.assert_close(out.rotation.norm(dim=-1), torch.ones(5, 40))
    assert (out.scale > 0).all() and torch.isfinite(out.scale).all()
    assert ((out.opacity >= 0) & (out.opacity <= 1)).all()
    assert ((out.opacity[:2] > 0) & (out.opacity[:2] < 1)).all()  # strictly inside for moderate inputs


def test_decoder_starts_near_prior_and_no_offsets_variant():
    torch.manual_seed(0)
    dec = AnchorDecoder(8, 16, 2, 1, init_opacity=0.2, output_gain=0.0)
    out = dec(torch.randn(10, 8), log_scale_prior=-3.0)
    torch.testing.assert_close(out.rotation, torch.tensor([1.0, 0, 0, 0]).expand(10, 4))
    torch.testing.assert_close(out.scale, torch.full((10, 3), torch.exp(torch.tensor(-3.0)).item()))
    torch.testing.assert_close(out.opacity, torch.full((10,), 0.2))
    no_off = AnchorDecoder(8, 16, 2, 1, offsets=False, output_gain=1.0)
    assert (no_off(torch.randn(10, 8)).offset == 0).all()


def test_refiner_shape_residual_is_time_mean_and_joints_selected():
    torch.manual_seed(0)
    joints = refined_joints(body=True, face=False, hands=False)
    ref = BodyRefiner(16 + 6, 32, 3, num_betas=10, joints=joints, output_gain=1.0).double()
    z = torch.randn(16, dtype=torch.float64)
    gamma = time_embedding(torch.arange(7), 7).double()
    steps = torch.tensor([2, 5])
    betas, pose = ref(z, gamma, steps)
    # Independent reference: evaluate every timestep separately and average.
    per_step = torch.stack([ref.net(torch.cat([z, gamma[t]])) for t in range(7)])
    torch.testing.assert_close(betas, per_step[:, :10].mean(0))
    torch.testing.assert_close(pose[:, joints].reshape(2, -1), per_step[steps, 10:])
    assert pose.shape == (2, 55, 3) and (pose[:, 22:] == 0).all()
    # Gradient of the shape residual reaches the network through all timesteps.
    betas.sum().backward()
    assert ref.net[0].weight.grad.abs().sum() > 0


def test_refiner_with_nothing_to_refine_predicts_zeros():
    ref = BodyRefiner(4, 8, 1, num_betas=0, joints=[])
    betas, pose = ref(torch.zeros(2), torch.zeros(3, 2), torch.tensor([1]))
    assert betas.shape == (0,) and (pose == 0).all() and ref.net is None
