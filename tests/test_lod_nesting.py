"""Nested levels of detail by value (Section 3.1): level l's splats are the first N_l splats of level l + 1.

The decoders read the LOD input l~ (Eq. 6) and each level has its own scale prior, so only those differ between
the levels; with the level input's weights zeroed the coarse splats must equal the finer level's first ones,
scales up to the ratio of the priors.
"""
import math

import numpy as np
import pytest
import torch

from pig.body.params import SmplxParams
from avatar_fixture import small_avatar


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    from pig.body.standin import write_standin

    path = tmp_path_factory.mktemp("standin") / "body_model.npz"
    write_standin(path)
    rng = np.random.default_rng(1)
    params = SmplxParams(rng.normal(scale=0.2, size=(2, 55, 3)), np.zeros(10), np.zeros((2, 10)), np.zeros((2, 3)))
    model = small_avatar(path.read_bytes(), params, True, num_anchors=400, levels=3, sh_degree=1, hidden_layers=1,
                         hidden_width=16)
    with torch.no_grad():  # learned anchors and grid away from their initial values, so that a mix-up shows
        model.anchors.param.add_(0.01 * torch.randn_like(model.anchors.param))
        for level in model.grid.levels:
            level.param.add_(torch.randn_like(level.param))
    return model


def test_coarse_anchors_are_the_first_anchors_of_the_finer_level(model):
    x = model.canonical_anchors()
    with torch.no_grad():
        vertices = model.body_model(model.pose_init, model.betas_init, model.expression, model.transl).vertices
        levels = [model.transport(x, vertices, lod) for lod in range(model.num_levels)]
        features = [model.anchor_features(x, lod)[0] for lod in range(model.num_levels)]
    assert model.level_sizes == [100, 200, 400]
    for lod in range(model.num_levels - 1):
        n = model.level_sizes[lod]
        for coarse, fine in zip(levels[lod], levels[lod + 1]):  # posed centres x(theta), rotations R
            assert torch.equal(coarse, fine[:, :n])
        assert torch.equal(features[lod], features[lod + 1][:n])
        assert not torch.equal(features[lod], features[lod + 1][n:2 * n])  # the check can tell anchors apart


def test_coarse_splats_are_the_first_splats_of_the_finer_level(model):
    with torch.no_grad():
        for net in (model.decoder.shape, model.decoder.colour):
            net[0].weight[:, -1] = 0  # the LOD input l~, the last decoder input
        steps = torch.tensor([0, 1])
        levels = [model(steps, lod) for lod in range(model.num_levels)]
    for lod in range(model.num_levels - 1):
        n = model.level_sizes[lod]
        coarse, fine = levels[lod], levels[lod + 1]
        for name in ("means", "quats", "opacities", "sh"):
            torch.testing.assert_close(getattr(coarse, name), getattr(fine, name)[:, :n], rtol=0, atol=1e-6, msg=name)
        ratio = math.exp(model.log_scale_prior[lod] - model.log_scale_prior[lod + 1])
        torch.testing.assert_close(coarse.scales, fine.scales[:, :n] * ratio, rtol=1e-5, atol=0)
        assert (coarse.means - fine.means[:, n:2 * n]).abs().max() > 1e-3
