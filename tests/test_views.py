"""Streamed training views: bounded cache, exact pixels, sampling from (seed, iteration), decoding errors."""
import re
import shutil
from collections import Counter

import pytest
import torch

from pig.avatar.batches import Sampler, TrainingBatches, ViewSource
from pig.avatar.losses import boundary_band
from pig.data.capture import Capture
from pig.data.raw import CaptureError


def _check_pixels(batch_views, reference: Capture, frames: list[int]) -> list[tuple[str, int]]:
    """Assert every view equals a direct read of the capture; returns the (camera, frame) pairs seen."""
    seen = []
    for step_batches in batch_views:
        for vb in step_batches:
            frame = frames[vb.timestep]
            cam0 = reference.cameras[vb.cameras[0]]
            assert (vb.width, vb.height) == (cam0.width, cam0.height)
            assert vb.images.dtype == torch.float32 and vb.images.is_contiguous() and vb.masks.dtype == torch.bool
            for j, cam in enumerate(vb.cameras):
                assert torch.equal(vb.images[j], torch.from_numpy(reference.image(cam, frame))), (cam, frame)
                assert torch.equal(vb.masks[j], torch.from_numpy(reference.mask(cam, frame))), (cam, frame)
                assert torch.equal(vb.viewmats[j], torch.tensor(reference.cameras[cam].viewmat(), dtype=torch.float32))
                assert torch.equal(vb.Ks[j], torch.tensor(reference.cameras[cam].K, dtype=torch.float32))
                seen.append((cam, frame))
    return seen


def test_capture_larger_than_the_cache_never_holds_more_than_the_bound(small_capture):
    """20 views through a cache of 3, 2 views x 2 timesteps an iteration, 2 iterations staged ahead, 3 threads:
    never more than 3 cached views, nor more than 3 + (2 + 1) x 2 x 2 = 15 cached or staged ones, and every view
    handed out equals a direct read of the capture, pixel for pixel."""
    capture = Capture.load(small_capture, cache_mb=0)
    reference = Capture.load(small_capture)
    cameras, frames = sorted(capture.cameras), capture.frames
    assert len(cameras) * len(frames) == 20
    cache, prefetch, views, timesteps, iterations = 3, 2, 2, 2, 40
    bound = cache + (prefetch + 1) * views * timesteps
    sampler = Sampler(0, 2, tuple(tuple(cameras) for _ in frames), timesteps, views)
    seen = []
    with ViewSource(capture, frames, "cpu", cache, workers=3) as source:
        batches = TrainingBatches(source, sampler, iterations, prefetch)
        for i in range(iterations):
            batch = batches.get(i)
            picks = sampler.picks(i)
            assert batch.lod == picks.lod and batch.timesteps == [step for step, _ in picks.steps]
            seen += _check_pixels(batch.views, reference, frames)
            assert len(source._cache) <= cache
            if i == 20:  # a held-out read while training batches are staged
                seen += _check_pixels(source.views(source.stage([(1, cameras[:views])])), reference, frames)
        assert len(seen) == iterations * views * timesteps + views
        assert len(set(seen)) == 20  # the whole capture went through the cache of 3
        assert source.peak_cached == cache and cache < source.peak_held <= bound
        assert source.decoded + source.hits == len(seen) and source.decoded > 20  # evicted views were decoded again


def test_a_cache_that_holds_the_capture_decodes_each_view_once(small_capture):
    capture = Capture.load(small_capture, cache_mb=0)
    cameras, frames = sorted(capture.cameras), capture.frames
    sampler = Sampler(3, 1, tuple(tuple(cameras) for _ in frames), 2, 3)
    with ViewSource(capture, frames, "cpu", 20, workers=2) as source:
        batches = TrainingBatches(source, sampler, 30, 0)
        requested = {(cam, frames[step]) for i in range(30) for step, cams in sampler.picks(i).steps for cam in cams}
        for i in range(30):
            batches.get(i)
        assert source.decoded == len(requested) and source.hits == 30 * 2 * 3 - len(requested)
        assert source.peak_held <= 20 + 2 * 3


def test_views_carry_the_band_of_their_mask_when_the_source_computes_it(small_capture):
    """`fit.host_band`: the loader threads compute each view's silhouette band; it equals the device's
    `boundary_band` of the view's mask at the radius of its height, for decoded and cached views alike, and the
    masks and pixels stay those of the capture."""
    capture = Capture.load(small_capture, cache_mb=0)
    reference = Capture.load(small_capture)
    cameras, frames = sorted(capture.cameras), capture.frames
    sampler = Sampler(1, 2, tuple(tuple(cameras) for _ in frames), 2, 3)
    heights = []

    def radius(height: int) -> int:
        heights.append(height)
        return 2

    with ViewSource(capture, frames, "cpu", 8, workers=2, band_radius=radius) as source:
        batches = TrainingBatches(source, sampler, 12, 1)
        banded = 0
        for i in range(12):
            views = batches.get(i).views
            _check_pixels(views, reference, frames)
            for vb in (vb for step_batches in views for vb in step_batches):
                assert vb.bands.dtype == torch.bool and vb.bands.shape == vb.masks.shape
                assert torch.equal(vb.bands, boundary_band(vb.masks, 2))
                banded += int(vb.bands.any())
        assert source.hits > 0 and banded > 0
    assert set(heights) == {reference.cameras[c].height for c in cameras}
    with ViewSource(capture, frames, "cpu", 8, workers=1) as plain:  # no radius: no bands
        assert plain.views(plain.stage([(0, cameras[:2])]))[0][0].bands is None


def test_picks_depend_on_seed_and_iteration_only_and_skip_missing_views():
    # Timestep 2 has no views, camera "c" none at timestep 0.
    cameras = (("a", "b"), ("a", "b", "c"), (), ("a", "b", "c"), ("a", "c"))
    sampler = Sampler(7, 4, cameras, timesteps=3, views=2)
    again = Sampler(7, 4, cameras, timesteps=3, views=2)
    picks = [sampler.picks(i) for i in range(3000)]
    assert [again.picks(i) for i in (2999, 0, 1500)] == [picks[2999], picks[0], picks[1500]]  # any order
    assert [Sampler(8, 4, cameras, 3, 2).picks(i) for i in range(10)] != picks[:10]
    lods, steps, views = Counter(), Counter(), Counter()
    for p in picks:
        lods[p.lod] += 1
        assert len(p.steps) == 3 and len({s for s, _ in p.steps}) == 3
        for step, cams in p.steps:
            assert len(cams) == 2 and len(set(cams)) == 2 and set(cams) <= set(cameras[step])
            steps[step] += 1
            views.update((step, c) for c in cams)
    assert set(lods) == {0, 1, 2, 3} and min(lods.values()) > 3000 / 4 * 0.85
    # 3 of the 4 timesteps with views each iteration: each 3/4 of the iterations; 2 of n cameras: 2/n of those.
    assert 2 not in steps and all(abs(steps[t] / 3000 - 0.75) < 0.04 for t in (0, 1, 3, 4))
    for (step, cam), count in views.items():
        assert abs(count / steps[step] - 2 / len(cameras[step])) < 0.05, (step, cam)
    single = Sampler(0, 1, (("a",),), timesteps=5, views=4).picks(0)  # fewer timesteps and cameras than asked for
    assert single.lod == 0 and single.steps == [(0, ["a"])]


def test_a_corrupt_view_fails_the_batch_that_needs_it_with_its_path(small_capture, tmp_path):
    root = tmp_path / "capture"
    shutil.copytree(small_capture, root)
    capture = Capture.load(root, cache_mb=0)
    cam = sorted(capture.cameras)[1]
    [path] = (root / "images" / cam).glob(f"{capture.frames[2]:08d}.*")
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with ViewSource(capture, capture.frames, "cpu", 4, workers=2) as source:
        bad = source.stage([(2, sorted(capture.cameras))])
        good = source.stage([(1, sorted(capture.cameras))])
        with pytest.raises(CaptureError, match=f"^{re.escape(str(path))}: truncated"):
            source.views(bad)
        assert len(source.views(good)[0][0].cameras) == 5  # the source still serves other views
        assert all(key != (cam, capture.frames[2]) for key in source._cache)
        with pytest.raises(CaptureError, match=f"^{re.escape(str(path))}: truncated"):  # not cached as decoded, raised again
            source.views(source.stage([(2, [cam])]))


def test_fit_config_refuses_negative_loader_settings():
    from pig.config import ConfigError
    from pig.avatar.training import FitConfig

    with pytest.raises(ConfigError, match=r"^fit.loader_workers must be at least 1, found 0$"):
        FitConfig(loader_workers=0)
    with pytest.raises(ConfigError, match=r"^fit.prefetch must be at least 0, found -1$"):
        FitConfig(prefetch=-1)
    assert FitConfig(view_cache=0, prefetch=0).view_cache == 0
