"""Streaming FID statistics against np.cov on the same features, and the stages' strict JSON (null for NaN)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from pig.metrics.fid import FeatureStatistics, fid_from_statistics, frechet_distance
from pig._io import nan_for_null, write_json


def _accumulate(features: np.ndarray, sizes, chunk_rows: int) -> FeatureStatistics:
    stats = FeatureStatistics(chunk_rows)
    start = 0
    for size in sizes:
        stats.update(features[start:start + size])
        start += size
    assert start == len(features)
    return stats


@pytest.mark.parametrize("chunk_rows", [1, 5, 512])
def test_statistics_match_np_cov_over_batches_of_varied_sizes(rng, chunk_rows):
    sizes = [1, 0, 3, 7, 1, 1, 40, 2, 0, 13, 89]
    features = rng.normal(size=(sum(sizes), 6)) @ rng.normal(size=(6, 6)) + rng.normal(size=6)
    stats = _accumulate(features, sizes, chunk_rows)
    assert stats.count == len(features)
    np.testing.assert_allclose(stats.mean, features.mean(0), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(stats.covariance(), np.cov(features, rowvar=False), rtol=1e-12, atol=1e-13)
    # Adding more after a read continues the same statistics.
    more = rng.normal(size=(9, 6))
    stats.update(more)
    np.testing.assert_allclose(stats.covariance(), np.cov(np.vstack([features, more]), rowvar=False), rtol=1e-12, atol=1e-13)


def test_two_images_one_per_batch(rng):
    features = rng.normal(size=(2, 4))
    stats = _accumulate(features, [1, 1], chunk_rows=1)  # two single-row batches: only the cross term
    np.testing.assert_allclose(stats.covariance(), np.cov(features, rowvar=False), rtol=1e-14, atol=1e-15)
    value, note = fid_from_statistics(stats, stats, min_images=2000)
    assert value == pytest.approx(0.0, abs=1e-12) and note.startswith("FID over 2 images (< 2000)")
    one = FeatureStatistics()
    one.update(features[:1])
    value, note = fid_from_statistics(one, stats)
    assert math.isnan(value) and note == "FID is NaN: needs >= 2 images per set, have 1"
    with pytest.raises(ValueError, match="needs >= 2 feature vectors, have 1"):
        one.covariance()


def test_large_mean_keeps_precision(rng):
    """Features of mean 1e8 and unit spread: a sum of outer products loses every digit, the centred merge none."""
    spread = rng.normal(size=(300, 3)) @ np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.2], [0.0, 0.0, 0.3]])
    features = 1e8 + spread
    reference = np.cov(features - 1e8, rowvar=False)  # the subtraction is exact at this magnitude
    stats = _accumulate(features, [7, 1, 50, 3, 39, 200], chunk_rows=8)
    np.testing.assert_allclose(stats.covariance(), reference, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(stats.mean - 1e8, spread.mean(0), atol=1e-7)
    naive = (features.T @ features - len(features) * np.outer(features.mean(0), features.mean(0))) / (len(features) - 1)
    assert np.abs(naive - reference).max() > 1.0  # the case is stiff enough to tell the two apart


def test_fid_from_statistics_equals_dense_reference(rng):
    a = rng.normal(size=(60, 5))
    b = rng.normal(size=(45, 5)) * 1.5 + 0.3
    stats = [_accumulate(x, [4] * (len(x) // 4) + [len(x) % 4], chunk_rows=16) for x in (a, b)]
    expected = frechet_distance(a.mean(0), np.cov(a, rowvar=False), b.mean(0), np.cov(b, rowvar=False))
    value, note = fid_from_statistics(*stats, min_images=45)
    assert value == pytest.approx(expected, rel=1e-12) and note == ""
    assert fid_from_statistics(*stats, min_images=46)[1] == ("FID over 45 images (< 46): biased high, "
                                                            "compare only at equal N")


def test_statistics_reject_changing_dimensions():
    stats = FeatureStatistics()
    stats.update(np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"expects \(B, 3\) features, found \(2, 4\)"):
        stats.update(np.zeros((2, 4)))
    with pytest.raises(ValueError, match=r"expects \(B, D\) features, found \(5,\)"):
        FeatureStatistics().update(np.zeros(5))


def test_memory_does_not_grow_with_the_number_of_images(rng):
    """The float64 tensors held between batches (buffered rows, mean, scatter) over 200 and over 4000 feature
    vectors (batches of 8, D = 256) peak at the same size, within the O(D^2 + chunk_rows D) bound."""
    batch, dim, chunk_rows = rng.normal(size=(8, 256)), 256, 64

    def peak(images: int) -> int:
        stats, held = FeatureStatistics(chunk_rows=chunk_rows), 0
        for _ in range(images // 8):
            stats.update(batch)
            tensors = [*stats._pending, *(t for t in (stats._mean, stats._scatter) if t is not None)]
            held = max(held, sum(t.numel() * t.element_size() for t in tensors))
        np.testing.assert_allclose(stats.covariance(), np.cov(np.tile(batch, (images // 8, 1)), rowvar=False), rtol=1e-9,
                                   atol=1e-12)
        return held

    small, large = peak(200), peak(4000)
    assert small == large <= 8 * (dim * dim + (chunk_rows + 8 + 1) * dim), (small, large)


def test_statistics_stay_on_the_device_of_the_features(rng):
    """Tensor batches are summed where they are (here the CPU, as a GPU's would be on the GPU), in float64 from
    float32 features, equal to np.cov of the float64 values; features from another device are refused."""
    features = torch.from_numpy(rng.normal(size=(40, 5)).astype(np.float32))
    stats = FeatureStatistics(chunk_rows=16)
    for rows in torch.split(features, 7):
        stats.update(rows)
    assert stats._scatter.dtype == torch.float64 and stats._scatter.device == features.device
    np.testing.assert_allclose(stats.covariance(), np.cov(features.double().numpy(), rowvar=False), rtol=1e-12,
                               atol=1e-13)
    with pytest.raises(ValueError, match="holds sums on cpu, found features on meta"):
        stats.update(torch.zeros(2, 5, device="meta"))


def _strict(text: str):
    def refuse(token):
        raise ValueError(f"non-standard JSON constant {token}")

    return json.loads(text, parse_constant=refuse)


def test_write_json_writes_null_for_non_finite_numbers(tmp_path):
    data = {"fid": math.nan, "psnr": math.inf, "nested": {"values": [-math.inf, np.float32("nan"), np.float64(1.5),
                                                                      np.int64(3), (np.nan, 2.0)]},
            "array": np.array([[1.0, np.nan]]), "flag": np.bool_(True), "scalar": np.float64(np.inf), "text": "NaN"}
    write_json(tmp_path / "s.json", data)
    parsed = _strict((tmp_path / "s.json").read_text())
    assert parsed == {"fid": None, "psnr": None, "nested": {"values": [None, None, 1.5, 3, [None, 2.0]]},
                      "array": [[1.0, None]], "flag": True, "scalar": None, "text": "NaN"}
    back = nan_for_null(parsed)
    assert math.isnan(back["fid"]) and math.isnan(back["psnr"]) and back["text"] == "NaN"
