"""The latent grid against an independent trilinear formula; box mapping, clamping and gradients."""
import numpy as np
import pytest
import torch

from pig.config import load_preset, load_section
from pig.field.latent_grid import FieldConfig, LatentGrid
from pig.field.precondition import PrecondConfig


def trilinear_reference(volume: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Feature of `volume` (d, X, Y, Z) at [-1, 1]^3 `coords` (N, 3), vertices on the box corners, clamped."""
    shape = np.array(volume.shape[1:])
    u = np.clip((coords + 1.0) / 2.0, 0.0, 1.0) * (shape - 1)
    lo = np.minimum(np.floor(u).astype(int), np.maximum(shape - 2, 0))
    frac = u - lo
    out = np.zeros((len(coords), volume.shape[0]))
    for corner in np.ndindex(2, 2, 2):
        idx = np.minimum(lo + np.array(corner), shape - 1)
        w = np.prod(np.where(np.array(corner) == 1, frac, 1.0 - frac), axis=1)
        out += w[:, None] * volume[:, idx[:, 0], idx[:, 1], idx[:, 2]].T
    return out


def random_grid(resolutions, features=3, lo=(-0.5, -1.0, 0.2), hi=(0.7, 0.9, 0.5), margin=0.05, seed=0):
    grid = LatentGrid(resolutions, features, lo, hi, margin).double()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for level in grid.levels:
            level.param.copy_(torch.randn(level.param.shape, generator=gen, dtype=torch.float64))
    return grid


@pytest.mark.parametrize("resolutions", [[8, 24], [2, 5, 3], [1, 4]])
def test_matches_trilinear_reference(resolutions, rng):
    grid = random_grid(resolutions)
    points = rng.uniform(-0.6, 0.9, size=(500, 3))  # partly outside the box: clamped
    coords = grid.normalize(torch.from_numpy(points)).numpy()
    ref = np.mean([trilinear_reference(level.param.detach().numpy(), coords) for level in grid.levels], axis=0)
    np.testing.assert_allclose(grid(torch.from_numpy(points)).detach().numpy(), ref, rtol=0, atol=1e-12)


def test_box_corners_map_to_plus_minus_one_and_vertices_are_exact():
    grid = random_grid([5], lo=(0.0, 0.0, 0.0), hi=(1.0, 2.0, 4.0), margin=0.5)
    corners = torch.tensor([[-0.5, -0.5, -0.5], [1.5, 2.5, 4.5]], dtype=torch.float64)
    torch.testing.assert_close(grid.normalize(corners), torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64))
    # Vertex (i, j, k) of a 5^3 level sits at lo + (i, j, k) / 4 * extent.
    vol = grid.levels[0].param.detach()
    ijk = torch.tensor([[0, 0, 0], [4, 1, 3], [2, 4, 0]])
    points = torch.tensor([-0.5, -0.5, -0.5], dtype=torch.float64) + ijk / 4.0 * torch.tensor([2.0, 3.0, 5.0], dtype=torch.float64)
    torch.testing.assert_close(grid(points), vol[:, ijk[:, 0], ijk[:, 1], ijk[:, 2]].T, rtol=0, atol=1e-12)


def test_outside_points_read_the_clamped_border():
    grid = random_grid([6, 9])
    inside = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    far = inside + torch.tensor([[100.0, 0.0, -100.0]], dtype=torch.float64)
    clamped = torch.stack([grid.box_max[0], inside[0, 1], grid.box_min[2]]).reshape(1, 3)
    torch.testing.assert_close(grid(far), grid(clamped), rtol=0, atol=1e-12)
    assert not torch.allclose(grid(far), grid(inside))


def test_gradcheck_features_and_points(rng):
    grid = random_grid([3, 4], features=2)
    points = torch.from_numpy(rng.uniform(-0.4, 0.6, size=(7, 3))).requires_grad_(True)
    volumes = [level.param.detach().clone().requires_grad_(True) for level in grid.levels]
    assert torch.autograd.gradcheck(lambda p, a, b: grid(p, [a, b]), (points, *volumes), eps=1e-6, atol=1e-8)


def test_preconditioned_levels_read_x_not_u(rng):
    cfg = PrecondConfig(form="substitute")
    grid = LatentGrid.from_config(FieldConfig(resolutions=[4, 6], features=2), cfg, [0, 0, 0], [1, 1, 1]).double()
    values = [torch.from_numpy(rng.normal(size=level.param.shape)) for level in grid.levels]
    for level, value in zip(grid.levels, values):
        level.set_value(value)
    points = torch.from_numpy(rng.uniform(0, 1, size=(20, 3)))
    plain = LatentGrid([4, 6], 2, [0, 0, 0], [1, 1, 1], 0.1).double()
    with torch.no_grad():
        for level, value in zip(plain.levels, values):
            level.param.copy_(value)
    torch.testing.assert_close(grid(points), plain(points), rtol=1e-10, atol=1e-12)


def test_preset_and_bad_input():
    cfg = load_section(load_preset("test"), "field", FieldConfig)
    grid = LatentGrid.from_config(cfg, PrecondConfig(), [-1, -1, -1], [1, 1, 1])
    assert grid(torch.zeros(5, 3)).shape == (5, cfg.features)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        grid(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="empty box"):
        LatentGrid([4], 2, [0, 0, 0], [1, 0, 1], margin=0.0)
    with pytest.raises(ValueError, match="one lambda per level"):
        LatentGrid([4, 8], 2, [0, 0, 0], [1, 1, 1], form="filter", lambdas=[1.0])
