"""Training views streamed from a capture with bounded memory: one random LOD, K timesteps x V views per iteration.

The sampling of Section 3.5 / 3.6 (4 views x 5 timesteps per iteration); no paper equation. An iteration's
picks are a function of (seed, iteration) alone, so batches staged ahead of the training loop, and the
batches of a resumed fit, are exactly those an uninterrupted fit draws.

Views are decoded by a pool of threads (OpenCV's decoding releases the GIL) into staging buffers: uint8 RGB
and one uint8 a pixel for the mask (bit 0) and, when the source is given a band radius, the silhouette band of
Eq. 15's loss (bit 1, `pig.avatar.losses.boundary_band_host`): the threads then do the band's work instead of
the training device. On CUDA the buffers are pinned and copied with non_blocking=True: the host goes on
launching the iteration's work while the copy runs (on the compute stream, ahead of that work). A bounded LRU
cache keeps recently decoded views. Decoded views in host memory at any time, whatever the capture's size: at
most `cache_views` in the cache plus the staging slots of the batches staged and not yet handed out,
(prefetch + 1) x V x K while training (`ViewSource.peak_held` counts both), plus one view in transit per
decode thread and the batch being trained on.
"""
from __future__ import annotations

import threading
import time
import zlib
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from pig.avatar.losses import boundary_band_host

MASK_BIT, BAND_BIT = 1, 2  # of the staged uint8 mask


def host_to_device(array: np.ndarray, device: torch.device) -> torch.Tensor:
    """A small host array on `device`; to a GPU from pinned memory, so that the copy does not wait for the device's
    queue to drain (a blocking copy is a host synchronisation)."""
    tensor = torch.from_numpy(array)
    return tensor.pin_memory().to(device, non_blocking=True) if device.type == "cuda" else tensor.to(device)


@dataclass
class ViewBatch:
    """Views of one timestep that share an image size."""

    timestep: int  # index into the training frames
    cameras: list[str]
    viewmats: torch.Tensor  # (V, 4, 4) world-to-camera
    Ks: torch.Tensor  # (V, 3, 3)
    images: torch.Tensor  # (V, H, W, 3) float in [0, 1]
    masks: torch.Tensor  # (V, H, W) bool
    width: int
    height: int
    bands: torch.Tensor | None = None  # (V, H, W) bool silhouette band, when the source computes it


@dataclass(frozen=True)
class ViewShare:
    """A process's part of an iteration's views in a data-parallel fit (pig.avatar.distributed): (index of the
    timestep among its picks, camera, place among the iteration's `total` views) of each of its views, and a digest
    of the whole iteration's picks."""

    places: tuple[tuple[int, str, int], ...]
    total: int
    digest: int


@dataclass
class Picks:
    """What one iteration trains on: a level of detail and (timestep, cameras) pairs; `share` where these are one
    process's part of the iteration's picks."""

    lod: int
    steps: list[tuple[int, list[str]]]
    share: ViewShare | None = None

    def whole(self) -> ViewShare:
        """The share of one process that trains on all of these picks: every view at its place in their order
        (timesteps, then each timestep's cameras), the order in which the LPIPS term draws its views."""
        places = [(k, cam) for k, (_, cams) in enumerate(self.steps) for cam in cams]
        return ViewShare(tuple((k, cam, position) for position, (k, cam) in enumerate(places)), len(places),
                         picks_digest(self))


def picks_digest(picks: Picks) -> int:
    """A checksum of an iteration's picks (LOD, timesteps, cameras), to check that every rank drew the same."""
    return zlib.crc32(repr((picks.lod, picks.steps)).encode())


@dataclass
class TrainingBatch:
    """The views of one iteration, on the training device."""

    iteration: int
    lod: int
    timesteps: list[int]
    views: list[list[ViewBatch]]  # per timestep, grouped by image size
    wait_s: float  # how long the caller blocked for this batch
    share: ViewShare  # Picks.share, or in one process the whole picks' (Picks.whole)

    def places(self) -> tuple[dict[tuple[int, str], int], int]:
        """({(index into `timesteps`, camera): place among the iteration's views}, the iteration's view count)."""
        return {(k, cam): position for k, cam, position in self.share.places}, self.share.total

    def timestep_tensor(self, device: torch.device) -> torch.Tensor:
        """`timesteps` (K,) int64 on `device` (host_to_device: a tensor of the list moved there would be a blocking
        copy, one host synchronisation a step)."""
        return host_to_device(np.asarray(self.timesteps, dtype=np.int64), device)

    def uniform(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, int, int, torch.Tensor | None] | None:
        """When every timestep has one view batch of the same size and camera count: (viewmats (K, V, 4, 4),
        Ks (K, V, 3, 3), images (K V, H, W, 3), masks (K V, H, W), width, height, bands (K V, H, W) or None) for
        one render of all; else None."""
        batches = [step_batches[0] for step_batches in self.views if len(step_batches) == 1]
        if len(batches) != len(self.views) or len({(b.width, b.height, len(b.cameras)) for b in batches}) != 1:
            return None
        bands = torch.cat([b.bands for b in batches]) if batches[0].bands is not None else None
        return (torch.stack([b.viewmats for b in batches]), torch.stack([b.Ks for b in batches]),
                torch.cat([b.images for b in batches]), torch.cat([b.masks for b in batches]), batches[0].width,
                batches[0].height, bands)


@dataclass(frozen=True)
class Sampler:
    """Picks of an iteration from (seed, iteration) alone: one LOD of `levels`, `timesteps` distinct timesteps of
    those with views, each with `views` distinct cameras of those that see it (fewer when fewer exist)."""

    seed: int
    levels: int
    cameras: tuple[tuple[str, ...], ...]  # per timestep, the cameras with a view of it
    timesteps: int
    views: int

    def picks(self, iteration: int) -> Picks:
        rng = np.random.default_rng([self.seed, iteration])
        lod = int(rng.integers(self.levels))
        seen = [t for t, cams in enumerate(self.cameras) if cams]
        steps = [seen[i] for i in rng.permutation(len(seen))[: self.timesteps]]
        chosen = []
        for step in steps:
            cams = self.cameras[step]
            chosen.append((step, [cams[i] for i in rng.permutation(len(cams))[: self.views]]))
        return Picks(lod, chosen)


@dataclass
class _Staged:
    """Views being decoded into staging buffers: `layout` lists, per timestep, (size, cameras, first row)."""

    layout: list[tuple[int, list[tuple[tuple[int, int], list[str], int]]]]
    buffers: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]]  # (width, height) -> (n, H, W, 3), (n, H, W) uint8
    futures: list[Future]
    count: int


class ViewSource:
    """Views of a capture's `frames` (indexed by timestep), decoded by `workers` threads through an LRU cache of
    at most `cache_views` uint8 views, delivered as `ViewBatch`es on `device`; with `band_radius` (image height ->
    radius) each with its silhouette band.

    Reads through `capture` (load it with cache_mb=0: this cache takes the place of the capture's own). A
    decoding error (a corrupt or missing image: CaptureError naming the file) is raised by `views` for the
    batch that needs the view. Close it (or use it as a context manager) to stop the threads.
    """

    def __init__(self, capture, frames: list[int], device: torch.device | str, cache_views: int, workers: int,
                 band_radius: Callable[[int], int] | None = None):
        self.capture = capture
        self.frames = list(frames)
        self.device = torch.device(device)
        self.cache_views = cache_views
        self.band_radius = band_radius  # image height -> band radius; None: no bands
        self._pin = self.device.type == "cuda"
        self._viewmats = {c: torch.as_tensor(cam.viewmat(), dtype=torch.float32, device=self.device)
                          for c, cam in capture.cameras.items()}
        self._Ks = {c: torch.as_tensor(cam.K, dtype=torch.float32, device=self.device) for c, cam in capture.cameras.items()}
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="pig-views")
        self._lock = threading.Lock()
        self._cache: OrderedDict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()  # -> (RGB, mask)
        self._staged_views = 0  # staging slots of batches staged and not yet handed out
        self.peak_cached = 0  # most views the cache held at once
        self.peak_held = 0  # most views the cache and the staging slots held at once
        self.decoded = 0
        self.hits = 0

    def __enter__(self) -> "ViewSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Cancel staged decodes not yet started and wait for the running ones."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def stage(self, steps: list[tuple[int, list[str]]]) -> _Staged:
        """Start decoding the views of (timestep, cameras) pairs; returns at once."""
        sizes: dict[tuple[int, int], int] = {}  # views per image size
        layout = []
        for step, cameras in steps:
            groups: dict[tuple[int, int], list[str]] = {}
            for cam in cameras:
                groups.setdefault((self.capture.cameras[cam].width, self.capture.cameras[cam].height), []).append(cam)
            entry = []
            for size, cams in groups.items():
                entry.append((size, cams, sizes.get(size, 0)))
                sizes[size] = sizes.get(size, 0) + len(cams)
            layout.append((step, entry))
        buffers = {(w, h): (torch.empty((n, h, w, 3), dtype=torch.uint8, pin_memory=self._pin),
                            torch.empty((n, h, w), dtype=torch.uint8, pin_memory=self._pin)) for (w, h), n in sizes.items()}
        count = sum(sizes.values())
        with self._lock:
            self._staged_views += count
            self.peak_held = max(self.peak_held, len(self._cache) + self._staged_views)
        slots = {size: (rgb.numpy(), mask.numpy()) for size, (rgb, mask) in buffers.items()}
        futures = [self._pool.submit(self._fill, cam, self.frames[step], slots[size][0][first + i], slots[size][1][first + i])
                   for step, entry in layout for size, cams, first in entry for i, cam in enumerate(cams)]
        return _Staged(layout, buffers, futures, count)

    def views(self, staged: _Staged) -> list[list[ViewBatch]]:
        """Wait for staged views; per timestep, one `ViewBatch` per image size, on the device."""
        try:
            for future in staged.futures:
                future.result()  # re-raises a decoding error of the worker, message and all
        except BaseException:
            for future in staged.futures:
                future.cancel()
            raise
        finally:
            with self._lock:
                self._staged_views -= staged.count
        uploaded = {}
        for size, (rgb, packed) in staged.buffers.items():
            packed = packed.to(self.device, non_blocking=True)
            uploaded[size] = (rgb.to(self.device, non_blocking=True).float().div_(255), (packed & MASK_BIT).bool(),
                              (packed & BAND_BIT).bool() if self.band_radius else None)
        out = []
        for step, entry in staged.layout:
            batches = []
            for size, cams, first in entry:
                rows = slice(first, first + len(cams))
                images, masks, bands = uploaded[size]
                batches.append(ViewBatch(step, cams, torch.stack([self._viewmats[c] for c in cams]),
                                         torch.stack([self._Ks[c] for c in cams]), images[rows], masks[rows], *size,
                                         None if bands is None else bands[rows]))
            out.append(batches)
        return out

    def _fill(self, camera: str, frame: int, rgb: np.ndarray, mask: np.ndarray) -> None:
        """Write the view's RGB (H, W, 3) and packed mask and band (H, W) into the staging slots, from the cache or
        decoded."""
        key = (camera, frame)
        with self._lock:
            view = self._cache.get(key)
            if view is not None:
                self._cache.move_to_end(key)
                self.hits += 1
        if view is not None:
            rgb[...], mask[...] = view
            return
        rgb[...] = self.capture._read("images", camera, frame)
        silhouette = self.capture.mask(camera, frame)
        mask[...] = silhouette * MASK_BIT
        if self.band_radius is not None:
            mask[boundary_band_host(silhouette, self.band_radius(silhouette.shape[0]))] |= BAND_BIT
        view = (rgb.copy(), mask.copy()) if self.cache_views > 0 else None
        with self._lock:
            self.decoded += 1
            if view is None:
                return
            self._cache[key] = view
            self._cache.move_to_end(key)
            while len(self._cache) > self.cache_views:
                self._cache.popitem(last=False)
            self.peak_cached = max(self.peak_cached, len(self._cache))
            self.peak_held = max(self.peak_held, len(self._cache) + self._staged_views)


class TrainingBatches:
    """The batch of each iteration of [start, stop), staged `prefetch` iterations ahead of the one asked for;
    iterations are asked for in order."""

    def __init__(self, source: ViewSource, sampler: Sampler, stop: int, prefetch: int):
        self.source, self.sampler, self.stop, self.prefetch = source, sampler, stop, prefetch
        self._staged: dict[int, tuple[Picks, _Staged]] = {}

    def get(self, iteration: int) -> TrainingBatch:
        started = time.perf_counter()
        for ahead in range(iteration, min(iteration + self.prefetch + 1, self.stop)):
            if ahead not in self._staged:
                picks = self.sampler.picks(ahead)
                self._staged[ahead] = (picks, self.source.stage(picks.steps))
        picks, staged = self._staged.pop(iteration)
        views = self.source.views(staged)
        return TrainingBatch(iteration, picks.lod, [step for step, _ in picks.steps], views, time.perf_counter() - started,
                             picks.whole() if picks.share is None else picks.share)
