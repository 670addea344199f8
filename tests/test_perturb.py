"""The body-parameter noise of the robustness table (`fit.sigma_body`, pig.avatar.training.perturb_params):
zero-mean Gaussian noise of std sigma on the global orientation and the 21 body joints and on the betas only,
seeded, never touching its input."""
import numpy as np
import pytest

from pig.avatar.training import perturb_params
from pig.body.params import SmplxParams


def _params(frames: int = 400) -> SmplxParams:
    rng = np.random.default_rng(7)
    return SmplxParams(rng.normal(size=(frames, 55, 3)), rng.normal(size=10), rng.normal(size=(frames, 10)),
                       rng.normal(size=(frames, 3)))


@pytest.mark.parametrize("sigma", [0.1, 0.25])
def test_noise_on_body_joints_and_betas_only_with_the_given_std(sigma):
    params = _params()
    before = [a.copy() for a in (params.full_pose, params.betas, params.expression, params.transl)]
    noisy = perturb_params(params, sigma, seed=3)
    for original, kept in zip(before, (params.full_pose, params.betas, params.expression, params.transl)):
        np.testing.assert_array_equal(original, kept)  # the input is left as it was
    pose_noise = noisy.full_pose - params.full_pose
    np.testing.assert_array_equal(pose_noise[:, 22:], 0)  # jaw, eyes and hands untouched
    np.testing.assert_array_equal(noisy.expression, params.expression)
    np.testing.assert_array_equal(noisy.transl, params.transl)
    body = pose_noise[:, :22].ravel()  # 400 x 22 x 3 = 26400 draws: the sample std lies within 2 % of sigma
    assert np.all(body != 0) and abs(body.std() / sigma - 1) < 0.02 and abs(body.mean()) < 4 * sigma / np.sqrt(body.size)
    for joint in (0, 1, 21):  # every one of the 22 joints gets noise, not only some
        assert abs(pose_noise[:, joint].std() / sigma - 1) < 0.1
    betas = noisy.betas - params.betas
    assert betas.shape == (10,) and np.all(betas != 0)
    small = _params(1)  # the betas over 400 seeds (4000 draws): their std lies within 5 % of sigma
    draws = np.concatenate([perturb_params(small, sigma, seed=s).betas - small.betas for s in range(400)])
    assert abs(draws.std() / sigma - 1) < 0.05 and abs(draws.mean()) < 4 * sigma / np.sqrt(draws.size)


def test_seeding_and_sigma_zero():
    params = _params(20)
    a, b, c = (perturb_params(params, 0.2, seed=s) for s in (0, 0, 1))
    np.testing.assert_array_equal(a.full_pose, b.full_pose)
    np.testing.assert_array_equal(a.betas, b.betas)
    assert not np.allclose(a.full_pose, c.full_pose) and not np.allclose(a.betas, c.betas)
    # The betas' draw is independent of the pose's (not a copy of its first values).
    assert not np.isin(a.betas - params.betas, a.full_pose - params.full_pose).any()
    assert perturb_params(params, 0.0, seed=0) is params
    # Noise scales with sigma: the same seed at twice the sigma gives twice the noise.
    d = perturb_params(params, 0.4, seed=0)
    np.testing.assert_allclose(d.full_pose - params.full_pose, 2 * (a.full_pose - params.full_pose), rtol=1e-12, atol=1e-12)
