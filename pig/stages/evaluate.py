"""Evaluate stage: per-image PSNR, SSIM, LPIPS and per-set FID of one split's renders at every LOD.

Follows the paper's protocol (Section 4.2): full frame, black background, ground truth masked to
black. Writes metrics/{split}_lod{l}.csv (per image) and metrics/{split}_lod{l}.json (summary, with the render
stage's timing and its note on the avatar's fit, `fit_note`) for each LOD, then metrics/{split}.json (the pass:
its LODs, views a second, the seconds spent waiting for decoding and for the device). One pass scores every LOD:
each ground-truth view is decoded once, and its LPIPS and Inception features are computed once for all LODs.
Views are decoded on worker threads a few batches ahead of the metrics, and FID keeps running feature statistics
on the device, so memory does not grow with the split.

A capture with true meshes (synthetic, gt_meshes.npz) also gets PSNR/SSIM per region (garment, body, background;
pig.metrics.regions) per image and in the summary, and the geometry error and correspondence drift of the render
stage's splats (lod{l}/splats.npz; pig.metrics.geometry) in the summary. Real captures have none of these columns.
The region labels are cast on `evaluate.label_workers` threads ahead of the scoring, as the views are decoded, and
kept for the process (`LABELS`): a second evaluation of the same capture in one process (a fit's weight average,
then its last iterate) casts none. The geometry metrics are computed meanwhile on another thread.
"""
from __future__ import annotations

import math
import re
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pandas as pd
import torch

from pig.config import Bounds, load_preset, load_section, resolve_device
from pig.data.capture_record import read_capture_record, require_same_capture
from pig.data.ground_truth import GT_MESHES, SPLATS, SplatTrack, TrueMeshes
from pig.data.raw import CaptureError
from pig.data.render_store import RenderReader
from pig.metrics.fid import DEFAULT_MIN_IMAGES, FeatureStatistics, InceptionFeatures, fid_from_statistics
from pig.metrics.geometry import ground_truth_geometry
from pig.metrics.lpips import LPIPS
from pig.metrics.protocol import Protocol, crop_to_mask_box, protocol, ssim_uniform
from pig.metrics.psnr import psnr
from pig.metrics.regions import REGIONS, LabelCache, RegionLabeller, region_psnr, region_ssim
from pig.metrics.ssim import ssim, ssim_map
from pig.metrics.weights import (INCEPTION_FILE, LPIPS_LINEAR_FILES, TORCHVISION_FILES, WeightsMissing, locate,
                                 lpips_package_weights)
from pig.progress import progress_bar
from pig.resources import host_cores
from pig._cli import add_common_arguments, add_device_argument, add_preset_argument, run_cli, stage_parser
from pig._io import file_sha256, read_record, write_json, write_text
from pig._outputs import claim_files


@dataclass
class EvaluateConfig:
    """Preset section `evaluate` (read by the render, evaluate and tables stages)."""

    # How peers score (pig.metrics.protocol): `ours`, or `animatable_gaussians` (its SSIM window and crop); the
    # summaries and the tables name it.
    protocol: Literal["ours", "animatable_gaussians"] = "ours"
    lpips_net: Literal["alex", "vgg"] = "alex"  # LPIPS backbone; peers report either, the tables name it
    lpips_backbone_weights: str | None = None  # torchvision checkpoint; None: torch hub cache
    lpips_linear_weights: str | None = None  # lpips package's alex.pth / vgg.pth; None: hub cache or package
    inception_weights: str | None = None  # TorchScript inception-2015-12-05.pt; None: torch hub cache
    fid_min_images: int = DEFAULT_MIN_IMAGES  # FID over fewer images per set is flagged as biased (still computed)
    # Arithmetic of the LPIPS backbone and of the FID Inception (pig.metrics.precision): float32 (the reference), or
    # float16 / bfloat16 under autocast, every distance and statistic of the features in float32; PSNR and SSIM
    # stay float32. Lower precision only where its parity with float32 is shown (benchmarks/NOTES.md, "Lower-
    # precision metric networks"): LPIPS-VGG is most of the device's time, the Inception ~3 % of it.
    lpips_precision: Literal["float32", "float16", "bfloat16"] = "float32"
    fid_precision: Literal["float32", "float16", "bfloat16"] = "float32"
    channels_last: bool = False  # both networks' weights and inputs in channels-last memory format
    # LPIPS of a batch computed over the part of the frame where a render or the mask is not black, grown by the
    # backbone's receptive field (LPIPS.window): the same values (outside it the compared taps are equal, their terms
    # zero), on fewer pixels. The loader finds each image's nonzero box on its threads; the `ours` protocol only.
    lpips_window: bool = False
    batch_size: Annotated[int, Bounds(ge=1)] = 8
    device: str = "auto"  # "auto": CUDA when available
    timing_frames: Annotated[int, Bounds(ge=1)] = 5  # frames timed per LOD for the FPS column (after one warm-up frame)
    # Frames of a split, evenly spaced with its first and last, on which a synthetic capture's geometry error is
    # measured: each costs an exact nearest-surface query per splat. The drift follows all frames.
    geometry_frames: int = 4
    # Render storage (pig.data.render_store): lossless codec, frames per chunk file, threads that encode (render)
    # and decode (evaluate) views, and whether to also write every view as PNG + alpha/depth EXR. `png` encodes
    # ~6x faster than `webp` (OpenCV's lossless WebP), which is ~25-45 % smaller (benchmarks/NOTES.md).
    render_codec: Literal["png", "webp"] = "png"
    chunk_frames: Annotated[int, Bounds(ge=1)] = 16
    encode_workers: Annotated[int, Bounds(ge=1)] = 2
    every_view: bool = False
    # Threads that cast a synthetic capture's region labels (pig.metrics.regions) ahead of the scoring; 0: one per
    # core. The casts release the GIL: on the GPU machine they were most of an evaluation's host time (issue 38).
    label_workers: Annotated[int, Bounds(ge=0)] = 0


# The render stage passes on the note of the avatar's fit (pig.avatar.losses.fit_note: the LPIPS term of Eq. 15
# left out or not the paper's) in timing.json; renders of an older render stage lack it.
UNRECORDED_FIT_NOTE = "fit's LPIPS term unknown (renders written before the render stage recorded it, re-run render)"


def split_record_name(split: str) -> str:
    """The evaluate stage's record of one split's pass (its LODs' summaries, views, where the seconds went),
    written after every LOD's files: the workflow's output of the stage."""
    return f"{split}.json"


def render_levels(split_dir: Path) -> list[int]:
    """LOD indices rendered under renders/{split}/ (folders lod0, lod1, ...)."""
    levels = sorted(int(m.group(1)) for p in split_dir.glob("lod*") if (m := re.fullmatch(r"lod(\d+)", p.name)))
    if not levels:
        raise FileNotFoundError(f"{split_dir}: no lod*/ folders; expected the render stage's output for one split")
    return levels


def _load_metric(build, what: str) -> tuple[torch.nn.Module | None, str]:
    try:
        return build(), ""
    except WeightsMissing as err:
        print(f"[evaluate] {what} is NaN: {err}")
        # The table's note names the file; the full search path list stays in the log.
        return None, f"{what} is NaN: {str(err).split(' (searched')[0]}"


def weights_note(cfg: EvaluateConfig, lpips_loaded: bool, inception_loaded: bool) -> str:
    """Which files scored the LPIPS and FID columns (found as the metrics find them), each with the first 12 hex
    digits of its SHA-256, for the summaries and the tables' notes; '' when neither metric had weights."""
    files = []
    if lpips_loaded:
        files += [locate(TORCHVISION_FILES[cfg.lpips_net], cfg.lpips_backbone_weights, [], "LPIPS backbone"),
                  locate(LPIPS_LINEAR_FILES[cfg.lpips_net], cfg.lpips_linear_weights, [lpips_package_weights()],
                         "LPIPS linear layers")]
    if inception_loaded:
        files.append(locate(INCEPTION_FILE, cfg.inception_weights, [], "FID Inception network"))
    if not files:
        return ""
    return "scored with weights " + ", ".join(f"{path.name} (sha256 {file_sha256(path)[:12]})" for path in files)


def precision_note(cfg: EvaluateConfig) -> str:
    """The tables' note on LPIPS or FID scored by a network below float32 ('' when both ran in float32)."""
    lowered = [f"{metric} network in {precision}" for metric, precision in
               (("LPIPS", cfg.lpips_precision), ("FID", cfg.fid_precision)) if precision != "float32"]
    return "; ".join(lowered) + " (features widened to float32)" if lowered else ""


REGION_KEYS = [f"{metric}_{region}" for metric in ("psnr", "ssim") for region in ("garment", "body", "background")]
# Region labels of the views this process scored, by content (LabelCache): a paper-sized subject's 86 held-out
# views take 130 MB at 1330 x 1150.
LABELS = LabelCache(1 << 30)


def _mean_of_present(values: pd.Series) -> float:
    """Mean over the images where the value exists (a region can be absent from a view); NaN when none has it."""
    present = values.dropna()
    return float(present.mean()) if len(present) else math.nan


def view_batches(capture, split: str, batch_size: int) -> list[list[tuple[str, int]]]:
    """The split's views in batches of `batch_size`, camera-major; a batch never mixes image sizes (DNA-Rendering's
    two camera groups differ)."""
    by_size: dict[tuple[int, int], list] = {}
    for c, f in capture.views(split):
        by_size.setdefault((capture.cameras[c].width, capture.cameras[c].height), []).append((c, f))
    return [pairs[i:i + batch_size] for pairs in by_size.values() for i in range(0, len(pairs), batch_size)]


@dataclass
class LoadedBatch:
    """One batch as tensors on the host: the ground truth before masking (B, H, W, 3) uint8, its masks (B, H, W)
    bool, each LOD's renders (B, H, W, 3) uint8 and, with true meshes, the region labels (B, H, W) uint8."""

    views: list[tuple[str, int]]
    truths: torch.Tensor
    masks: torch.Tensor
    renders: dict[int, torch.Tensor]
    labels: torch.Tensor | None = None
    # With the loader's `boxes`: (B, 1 + LODs, 4) the nonzero box (top, bottom, left, right) of each view's mask and
    # of each LOD's render of it, (H, 0, W, 0) where all is zero.
    boxes: np.ndarray | None = None

    def changed_box(self) -> tuple[int, int, int, int]:
        """The box outside which every render equals its masked truth (black where the mask and the render are):
        the union of `boxes`; (0, 1, 0, 1) where the whole batch is black."""
        return union_box(self.boxes) or (0, 1, 0, 1)


class BatchLoader:
    """Decodes each batch's ground truth once and every LOD's renders of it on `workers` threads (OpenCV releases
    the GIL), `ahead` batches in front of the one being scored, straight into uint8 buffers: page-locked when
    `pin` (a GPU's copies then run asynchronously), a quarter of the float32 bytes either way. With a `labeller`
    (pig.metrics.regions.RegionLabeller) each view's region labels are cast on `label_workers` threads of their
    own, up to 4 views a thread ahead of the scoring (views of several cameras at once: each camera's pixel rays are
    built once, on the thread that first needs them). With `boxes`, each decoding thread also finds its image's
    nonzero box (LoadedBatch.boxes). Iterating yields LoadedBatch; `wait_s` sums the time the scoring waited for
    decoding and labels."""

    def __init__(self, capture, readers: dict[int, RenderReader], batches: list[list[tuple[str, int]]], workers: int,
                 pin: bool = False, ahead: int = 2, labeller: RegionLabeller | None = None, label_workers: int = 1,
                 boxes: bool = False):
        self.capture, self.readers, self.batches = capture, readers, batches
        self.workers, self.pin, self.ahead = workers, pin, ahead
        self.labeller, self.label_workers, self.boxes = labeller, label_workers, boxes
        self.wait_s = 0.0

    def __iter__(self):
        # The labels' pool starts no thread unless a labeller submits to it.
        views = [view for batch in self.batches for view in batch]
        window = 4 * self.label_workers if self.labeller is not None else 0  # labels held ahead: bounded memory
        labels: list = []  # each view's labels (a future; None once copied into its batch)
        with ThreadPoolExecutor(self.workers, thread_name_prefix="evaluate-decode") as pool, \
                ThreadPoolExecutor(self.label_workers, thread_name_prefix="evaluate-labels") as label_pool:

            def label_ahead(end: int) -> None:
                while len(labels) < min(end, len(views)):
                    labels.append(label_pool.submit(self.labeller, *views[len(labels)]))

            label_ahead(window)
            # Each (LOD, camera)'s chunk index built once, in parallel, before the views race to build it.
            cameras = sorted({camera for batch in self.batches for camera, _ in batch})
            for job in [pool.submit(reader.has, camera, -1) for reader in self.readers.values() for camera in cameras]:
                job.result()
            pending = [self._submit(pool, batch) for batch in self.batches[:self.ahead + 1]]
            first = 0  # the batch's first view
            for b in range(len(self.batches)):
                loaded, jobs = pending.pop(0)
                if window:  # this batch's labels and `window` views after it
                    label_ahead(first + len(loaded.views) + window)
                start = time.perf_counter()
                for job in jobs:
                    job.result()  # re-raises a decoding error naming its file
                if loaded.labels is not None:
                    for i in range(len(loaded.views)):
                        loaded.labels[i].numpy()[...] = labels[first + i].result()
                        labels[first + i] = None
                self.wait_s += time.perf_counter() - start
                first += len(loaded.views)
                if b + self.ahead + 1 < len(self.batches):
                    pending.append(self._submit(pool, self.batches[b + self.ahead + 1]))
                yield loaded

    def _submit(self, pool: ThreadPoolExecutor, views: list[tuple[str, int]]):
        camera = self.capture.cameras[views[0][0]]
        shape = (len(views), camera.height, camera.width)
        loaded = LoadedBatch(views, self._empty(*shape, 3), self._empty(*shape, dtype=torch.bool),
                             {level: self._empty(*shape, 3) for level in self.readers})
        if self.labeller is not None:  # filled from the labels' own threads when the batch is due
            loaded.labels = self._empty(*shape)
        if self.boxes:
            loaded.boxes = np.zeros((len(views), 1 + len(self.readers), 4), dtype=np.int64)
        box = (lambda i, k: loaded.boxes[i, k]) if self.boxes else (lambda i, k: None)
        jobs = []
        for i, view in enumerate(views):
            jobs.append(pool.submit(self._truth, view, loaded.truths[i].numpy(), loaded.masks[i].numpy(), box(i, 0)))
            jobs += [pool.submit(self._render, reader, view, loaded.renders[level][i].numpy(), box(i, 1 + k))
                     for k, (level, reader) in enumerate(self.readers.items())]
        return loaded, jobs

    def _empty(self, *shape: int, dtype: torch.dtype = torch.uint8) -> torch.Tensor:
        return torch.empty(shape, dtype=dtype, pin_memory=self.pin)

    def _truth(self, view: tuple[str, int], image: np.ndarray, mask: np.ndarray, box: np.ndarray | None) -> None:
        image[...] = self.capture.image_u8(*view)
        mask[...] = self.capture.mask(*view)
        if box is not None:
            box[...] = nonzero_box(mask)

    @staticmethod
    def _render(reader: RenderReader, view: tuple[str, int], out: np.ndarray, box: np.ndarray | None) -> None:
        image = reader.image_u8(*view)
        if image.shape != out.shape:
            raise ValueError(f"{reader.source(*view)}: render is {image.shape[1]}x{image.shape[0]} but the capture's "
                             f"image is {out.shape[1]}x{out.shape[0]}")
        out[...] = image
        if box is not None:
            box[...] = nonzero_box(image)


def nonzero_box(image: np.ndarray) -> tuple[int, int, int, int]:
    """(top, bottom, left, right), half-open, of the pixels of an (H, W) or (H, W, C) bool or unsigned image with a
    nonzero value; (H, 0, W, 0) when there is none."""
    if image.dtype.kind not in "bu":
        raise ValueError(f"nonzero_box: a bool or unsigned image, found {image.dtype}")
    height, width = image.shape[:2]
    # Row maxima rather than `any` over the pixel axes: numpy's max of uint8 is vectorised (a 1330 x 1150 render's
    # box in 0.4 ms instead of 15).
    rows = np.flatnonzero(image.reshape(height, -1).max(axis=1))
    if rows.size == 0:
        return height, 0, width, 0
    cols = np.flatnonzero(image[rows[0]:rows[-1] + 1].max(axis=0).reshape(width, -1).max(axis=1))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def union_box(boxes) -> tuple[int, int, int, int] | None:
    """The smallest box holding `boxes` (..., 4) of `nonzero_box`; None when every one is empty."""
    boxes = np.asarray(boxes).reshape(-1, 4)
    top, bottom, left, right = boxes[:, 0].min(), boxes[:, 1].max(), boxes[:, 2].min(), boxes[:, 3].max()
    return None if bottom <= top else (int(top), int(bottom), int(left), int(right))


def _unit_floats(images: torch.Tensor, device) -> torch.Tensor:
    """(B, H, W, 3) uint8 -> (B, 3, H, W) float32 in [0, 1] on `device`: the values read_png gives."""
    return (images.to(device, non_blocking=True).float() / 255).permute(0, 3, 1, 2)


def evaluate_levels(capture, split: str, level_dirs: dict[int, Path], cfg: EvaluateConfig, lpips_net, inception,
                    device, fid_note: str = "", labeller: RegionLabeller | None = None,
                    seconds: dict | None = None) -> dict[int, tuple[pd.DataFrame, dict]]:
    """Per-image metrics (DataFrame) and summary (dict) of one split at each LOD of `level_dirs` ({level: folder}),
    over the split's views that have ground truth, in one pass: each ground-truth view is decoded, masked and
    passed through the LPIPS and Inception networks once for all LODs. Without `inception` the FID is NaN with
    `fid_note`. With a `labeller` (true meshes), also PSNR/SSIM per region (REGION_KEYS). `seconds`, when given,
    gets the wall time (`total_s`) and the time spent waiting for decoding and labels (`decode_wait_s`) and for the
    device (`device_wait_s`)."""
    device = torch.device(device)
    rules = protocol(cfg.protocol)
    batches = view_batches(capture, split, cfg.batch_size)
    sizes = {name: (camera.width, camera.height) for name, camera in capture.cameras.items()}  # chunks checked against
    windowed = lpips_net is not None and cfg.lpips_window and not rules.crop
    loader = BatchLoader(capture, {level: RenderReader(path, sizes) for level, path in level_dirs.items()}, batches,
                         cfg.encode_workers, pin=device.type == "cuda", labeller=labeller,
                         label_workers=cfg.label_workers or host_cores(), boxes=windowed)
    values: dict[int, list[dict[str, torch.Tensor]]] = {level: [] for level in level_dirs}
    fake_features = {level: FeatureStatistics() for level in level_dirs}
    real_features = FeatureStatistics()
    in_flight: list = []  # one event per batch queued on a GPU: the host runs at most two batches ahead
    start, device_wait = time.perf_counter(), 0.0
    for loaded in progress_bar(loader, total=len(batches), desc=f"evaluate {split}", unit="batch"):
        with torch.no_grad():
            masks = loaded.masks.to(device, non_blocking=True)
            y = ((loaded.truths.to(device, non_blocking=True).float() / 255) * masks[..., None]).permute(0, 3, 1, 2)
            # LPIPS and FID see the protocol's crop; PSNR, SSIM and the regions the full frame.
            yc = crop_to_mask_box(y, masks) if rules.crop else y
            truth_only = {"psnr_blank": psnr(torch.zeros_like(y), y),
                          "ssim_blank": ssim(torch.zeros_like(y), y, reduction="none")}
            window = lpips_net.window(loaded.changed_box(), *y.shape[-2:]) if windowed else None
            reference = (lpips_net.reference(y[..., window[0], window[1]] if window else yc)
                         if lpips_net is not None else None)
            if inception is not None:
                real_features.update(inception(yc).double())
            labels = loaded.labels.to(device, non_blocking=True) if loaded.labels is not None else None
            for level, renders in loaded.renders.items():
                x = _unit_floats(renders, device)
                values[level].append(_score(x, y, masks, rules, lpips_net, reference, labels, truth_only, window))
                if inception is not None:
                    fake_features[level].update(inception(crop_to_mask_box(x, masks) if rules.crop else x).double())
            del reference
        if device.type == "cuda":
            in_flight.append(torch.cuda.Event())
            in_flight[-1].record()
            if len(in_flight) > 2:
                wait = time.perf_counter()
                in_flight.pop(0).synchronize()
                device_wait += time.perf_counter() - wait
    results = {}
    views = [view for batch in batches for view in batch]
    for level in level_dirs:
        columns = {key: torch.cat([batch[key] for batch in values[level]]).cpu().numpy() for key in values[level][0]}
        table = pd.DataFrame({"camera": [cam for cam, _ in views], "frame": [frame for _, frame in views],
                              **{key: column.astype(np.float64) for key, column in columns.items()}})
        summary = {k: float(table[k].mean()) for k in ("psnr", "ssim", "lpips", "psnr_blank", "ssim_blank")}
        if labeller is not None:
            summary.update({key: _mean_of_present(table[key]) for key in REGION_KEYS})
        summary["images"] = len(table)
        fid, note = math.nan, fid_note
        if inception is not None:
            fid, note = fid_from_statistics(fake_features[level], real_features, cfg.fid_min_images)
        summary.update(fid=fid, fid_images=len(table), fid_min_images=cfg.fid_min_images, fid_note=note)
        results[level] = table, summary
    if seconds is not None:
        seconds.update(total_s=time.perf_counter() - start, decode_wait_s=loader.wait_s, device_wait_s=device_wait)
    return results


def _score(x, y, masks, rules: Protocol, lpips_net, reference, labels, truth_only: dict,
           window: tuple[slice, slice] | None = None) -> dict[str, torch.Tensor]:
    """(B,) metric values of renders `x` against the masked truth `y` by the protocol's `rules`, on their device;
    LPIPS over the frames' `window` (LPIPS.window) where one is given."""
    similarity = ssim_map(x, y)
    if lpips_net is None:
        perceptual = torch.full((len(x),), math.nan, device=x.device)
    elif window is not None:
        perceptual = lpips_net.distance(x[..., window[0], window[1]], reference, frame=tuple(x.shape[-2:]))
    else:
        perceptual = lpips_net.distance(crop_to_mask_box(x, masks) if rules.crop else x, reference)
    values = {
        "psnr": psnr(x, y),
        "ssim": similarity.flatten(1).mean(1) if rules.ssim_window == "gaussian11" else ssim_uniform(x, y).float(),
        "lpips": perceptual,
        **truth_only,
    }
    if labels is not None:
        region_values = {"psnr": region_psnr(x, y, labels), "ssim": region_ssim(similarity, labels)}
        for metric, per_region in region_values.items():
            for region, code in REGIONS.items():
                values[f"{metric}_{region}"] = per_region[:, code]
    return values


def evaluate_split(capture_dir: Path, split_dir: Path, split: str, output_dir: Path, cfg: EvaluateConfig,
                   levels: list[int] | None = None, overwrite: bool = False) -> list[Path]:
    """Evaluate the given LODs (default: every LOD rendered under `split_dir`); returns the CSV paths written.

    Files of the same names in `output_dir` are replaced only when it is an evaluate output folder, or with
    `overwrite`."""
    from pig.data.capture import Capture

    rendered = render_levels(split_dir)
    missing = sorted(set(levels or []) - set(rendered))
    if missing:
        raise FileNotFoundError(f"{split_dir}: LOD(s) {missing} were not rendered; found lod{rendered}: the avatar "
                                "rendered has fewer levels; was `avatar.levels` (or the variant's override) changed "
                                "after its fit? Rerun fit and render, e.g. `snakemake -R fit_avatar`")
    levels = levels if levels is not None else rendered
    claim_files(output_dir, [*(f"{split}_lod{level}{ext}" for level in levels for ext in (".csv", ".json")),
                             split_record_name(split)], "evaluate", (capture_dir, split_dir), overwrite)
    # Each view is read once: a cache would only hold decoded images that are never asked for again.
    capture = Capture.load(capture_dir, cache_mb=0)
    record = read_capture_record(split_dir, "render")  # renders of another capture are not scored against this one
    require_same_capture(split_dir, record["fingerprint"], record["capture"], capture)
    if split not in capture.split:
        raise KeyError(f"{capture_dir}/split.json: no split {split!r}; found {sorted(capture.split)}")
    views, listed = len(capture.views(split)), len(capture.split[split]["cameras"]) * len(capture.split[split]["frames"])
    if views == 0:
        raise FileNotFoundError(f"{capture_dir}: split {split!r} has no view with an image and a mask to score")
    if views < listed:
        print(f"[evaluate] {split}: {listed - views} of {listed} views have no image in the capture (missing raw "
              f"frames); scoring the other {views}")
    device = resolve_device(cfg.device)
    lpips_net, lpips_note = _load_metric(
        lambda: LPIPS(cfg.lpips_net, cfg.lpips_backbone_weights, cfg.lpips_linear_weights,
                      precision=cfg.lpips_precision, channels_last=cfg.channels_last).to(device), "LPIPS")
    rules = protocol(cfg.protocol)
    inception, fid_note = _load_metric(
        lambda: InceptionFeatures(cfg.inception_weights, rules.fid_resize, precision=cfg.fid_precision,
                                  channels_last=cfg.channels_last).to(device), "FID")
    weights = weights_note(cfg, lpips_net is not None, inception is not None)
    truth = TrueMeshes.load(capture_dir / GT_MESHES) if (capture_dir / GT_MESHES).is_file() else None
    labeller = None
    if truth is not None:
        truth.require_frames(capture.split[split]["frames"], f"split {split!r}")
        labeller = RegionLabeller(truth, capture.cameras, LABELS)
        for level in levels:  # before any work: renders of an older render stage lack them
            SplatTrack.require(split_dir / f"lod{level}" / SPLATS)
    # Before the pass, as the splat tracks: renders without a timing record fail at once, not after scoring.
    timings = {level: read_record(split_dir / f"lod{level}" / "timing.json",
                                  "the render stage's timing record (splats, model_mb, fps, device)") for level in levels}
    seconds: dict = {}
    with ThreadPoolExecutor(1, thread_name_prefix="evaluate-geometry") as pool:
        # The geometry metrics need only the splat tracks and the true meshes: on the host while the views are scored.
        geometry = {level: pool.submit(_geometry, split_dir / f"lod{level}", capture, split, truth, cfg.geometry_frames)
                    for level in (levels if truth is not None else [])}
        results = evaluate_levels(capture, split, {level: split_dir / f"lod{level}" for level in levels}, cfg,
                                  lpips_net, inception, device, fid_note, labeller, seconds)
        geometry = {level: job.result() for level, job in geometry.items()}
    written = []
    for level, (table, summary) in results.items():
        level_dir = split_dir / f"lod{level}"
        summary.update(geometry.get(level, {}))
        timing = {"fit_note": UNRECORDED_FIT_NOTE, **timings[level]}
        summary.update(split=split, lod=level, lpips_net=cfg.lpips_net, lpips_note=lpips_note, protocol=cfg.protocol,
                       protocol_note=rules.note if cfg.protocol != "ours" else "", weights_note=weights,
                       lpips_precision=cfg.lpips_precision, fid_precision=cfg.fid_precision,
                       precision_note=precision_note(cfg), **timing)
        csv_path = output_dir / f"{split}_lod{level}.csv"
        write_text(csv_path, table.to_csv(index=False, float_format="%.6g"))
        write_json(output_dir / f"{split}_lod{level}.json", summary)
        written.append(csv_path)
        print(f"[evaluate] {split} lod{level}: PSNR {summary['psnr']:.2f} SSIM {summary['ssim']:.4f} "
              f"(blank {summary['psnr_blank']:.2f} / {summary['ssim_blank']:.4f}) FID {summary['fid']:.2f} "
              f"over {summary['images']} images")
        if truth is not None:
            print(f"[evaluate] {split} lod{level}: PSNR garment {summary['psnr_garment']:.2f} body "
                  f"{summary['psnr_body']:.2f} background {summary['psnr_background']:.2f}; accuracy garment "
                  f"{summary['accuracy_mm_garment']:.1f} body {summary['accuracy_mm_body']:.1f} mm, completeness "
                  f"garment {summary['completeness_mm_garment']:.1f} body {summary['completeness_mm_body']:.1f} mm, "
                  f"drift {summary['drift_mm']:.1f} mm (last frame {summary['drift_mm_last']:.1f})")
        for note in (summary["fid_note"], summary["fit_note"]):
            if note:
                print(f"[evaluate] {split} lod{level}: {note}")
    scored = views * len(levels)
    # Written last: the workflow's output of the split, present only once every LOD's files are.
    write_json(output_dir / split_record_name(split), {
        "split": split, "levels": levels, "views": views, "device": str(device),
        "summaries": [f"{split}_lod{level}.json" for level in levels], **seconds,
        "views_per_s": scored / seconds["total_s"] if seconds["total_s"] > 0 else math.nan})
    print(f"[evaluate] {split}: {views} views x {len(levels)} LODs in {seconds['total_s']:.1f} s "
          f"({scored / max(seconds['total_s'], 1e-9):.1f} views/s); waited {seconds['decode_wait_s']:.1f} s for "
          f"decoding{' and region labels' if truth is not None else ''} and {seconds['device_wait_s']:.1f} s for the "
          "device")
    return written


def _geometry(level_dir: Path, capture, split: str, truth: TrueMeshes, geometry_frames: int) -> dict[str, float]:
    """The summary's geometry keys of one LOD's splat track (pig.metrics.geometry.ground_truth_geometry)."""
    return ground_truth_geometry(_splat_track(level_dir, capture, split), truth, geometry_frames)


def _splat_track(level_dir: Path, capture, split: str) -> SplatTrack:
    """The render stage's splat track of one LOD, which must cover the split's frames."""
    track = SplatTrack.load(level_dir / SPLATS)
    frames = sorted(int(f) for f in capture.split[split]["frames"])
    if track.frames.tolist() != frames:
        raise CaptureError(f"{level_dir / SPLATS}: frames {track.frames.tolist()[:8]} are not the frames of split "
                           f"{split!r} ({frames[:8]}...); the renders are of another split or capture: rerun render")
    return track


def add_encode_workers_argument(parser, work: str) -> None:
    parser.add_argument("--encode-workers", type=int, default=None, metavar="N",
                        help=f"threads that {work} (default: the preset's evaluate.encode_workers; the workflow passes "
                             f"its job's threads)")


def evaluate_section(preset: dict, args) -> EvaluateConfig:
    """The preset's evaluate section with the stage's --device and --encode-workers, where given."""
    overrides = {key: value for key, value in (("device", args.device), ("encode_workers", args.encode_workers))
                 if value is not None}
    return load_section(preset, "evaluate", EvaluateConfig, overrides or None)


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("evaluate", __doc__, "pig evaluate --capture results/synthetic/subject00/capture --renders "
                                               "results/synthetic/subject00/pig/renders/novel_view --split novel_view --output results/synthetic/subject00/pig/metrics")
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture directory")
    parser.add_argument("--renders", type=Path, required=True, help="renders/{split} directory of the render stage")
    parser.add_argument("--split", required=True, choices=["novel_view", "novel_pose", "train"],
                        help="the split the renders are of")
    parser.add_argument("--output", type=Path, required=True, help="metrics directory ({split}_lod{l}.csv/.json and {split}.json go here)")
    parser.add_argument("--lod", type=int, nargs="*", default=None, help="levels to evaluate (default: all rendered)")
    add_preset_argument(parser, "its evaluate section")
    add_device_argument(parser, None, "the preset's evaluate.device")
    add_encode_workers_argument(parser, "decode the ground truth and the renders")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace files of the same names in an --output folder the evaluate stage did not write")
    args = parser.parse_args(argv)
    cfg = evaluate_section(load_preset(args.preset), args)
    evaluate_split(args.capture, args.renders, args.split, args.output, cfg, args.lod, args.overwrite)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
