"""Anchor sampling (area-uniform, on the surface), nested LOD sizes, time/LOD embeddings."""
import math

import numpy as np
import pytest
import torch

from pig.avatar.anchors import level_sizes, sample_attachment, triangle_areas
from pig.avatar.time_embedding import lod_input, num_frequencies, time_embedding


def test_sampling_is_area_uniform_and_on_surface():
    # Two triangles with areas 1 : 9; a third of zero area must never be chosen.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 1], [3, 0, 1], [0, 6, 1], [5, 5, 5], [6, 6, 6]], float)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 7]])
    att = sample_attachment(vertices, faces, 20000, levels=3, seed=0)
    counts = np.bincount(att.face_ids, minlength=3)
    assert counts[2] == 0
    # Binomial standard deviation of the first count is sqrt(n p (1-p)) = 42; allow 5 sigma.
    assert abs(counts[0] - 2000) < 5 * math.sqrt(20000 * 0.1 * 0.9)
    assert np.all(att.bary >= 0) and np.allclose(att.bary.sum(1), 1)
    np.testing.assert_allclose(att.x_init, np.einsum("nk,nkc->nc", att.bary, vertices[faces[att.face_ids]]))
    # Uniform inside a triangle: the mean barycentric is (1/3, 1/3, 1/3) (std of a mean ~ 0.002).
    np.testing.assert_allclose(att.bary.mean(0), 1 / 3, atol=0.01)
    # ... and the fraction within the sub-triangle of half the edge at corner 0 is 1/4.
    assert abs(np.mean(att.bary[:, 0] > 0.5) - 0.25) < 0.015


def test_level_sizes_are_nested_halvings():
    assert level_sizes(100_000, 4) == [12_500, 25_000, 50_000, 100_000]
    assert level_sizes(7, 3) == [2, 4, 7]
    assert level_sizes(5, 1) == [5]
    with pytest.raises(ValueError):
        level_sizes(3, 3)


def test_sampling_is_deterministic_per_seed():
    vertices = np.random.default_rng(0).normal(size=(30, 3))
    faces = np.random.default_rng(1).integers(0, 30, (40, 3))
    a, b = sample_attachment(vertices, faces, 100, 2, seed=3), sample_attachment(vertices, faces, 100, 2, seed=3)
    np.testing.assert_array_equal(a.face_ids, b.face_ids)
    np.testing.assert_array_equal(a.bary, b.bary)
    assert triangle_areas(vertices, faces).shape == (40,)


def test_time_embedding_closed_form():
    assert [num_frequencies(t) for t in (1, 2, 3, 4, 5, 120, 2000)] == [0, 1, 2, 2, 3, 7, 11]
    gamma = time_embedding(torch.tensor([0, 3, 4]), 5)
    assert gamma.shape == (3, 6)
    t = np.array([0, 0.75, 1.0])
    freqs = np.pi * np.array([1, 2, 4])
    expected = np.concatenate([np.sin(t[:, None] * freqs), np.cos(t[:, None] * freqs)], axis=1)
    np.testing.assert_allclose(gamma.numpy(), expected, atol=1e-6)
    assert time_embedding(torch.tensor([0]), 1).shape == (1, 0)
    assert lod_input(0, 1) == 0.0 and lod_input(0, 4) == 0.0 and lod_input(3, 4) == 1.0 and lod_input(1, 3) == 0.5
