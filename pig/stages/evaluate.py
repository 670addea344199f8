"""Evaluate stage: per-image PSNR, SSIM, LPIPS and per-set FID of one split's renders at every LOD.

Follows the paper's protocol (Section 4.2): full frame, black background, ground truth masked to
black. Writes metrics/{split}_lod{l}.csv (per image) and metrics/{split}_lod{l}.json (summary, with the render
stage's timing and its note on the avatar's fit, `fit_note`). Views are read one batch at a time and FID keeps
running feature statistics, so memory does not grow with the split.

A capture with true meshes (synthetic, gt_meshes.npz) also gets PSNR/SSIM per region (garment, body, background;
pig.metrics.regions) per image and in the summary, and the geometry error and correspondence drift of the render
stage's splats (lod{l}/splats.npz; pig.metrics.geometry) in the summary. Real captures have none of these columns.
"""
from __future__ import annotations

import math
import re
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
from pig.metrics.regions import REGIONS, RegionLabeller, region_psnr, region_ssim
from pig.metrics.ssim import ssim, ssim_map
from pig.metrics.weights import (INCEPTION_FILE, LPIPS_LINEAR_FILES, TORCHVISION_FILES, WeightsMissing, locate,
                                 lpips_package_weights)
from pig.progress import progress_bar
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


# The render stage passes on the note of the avatar's fit (pig.avatar.losses.fit_note: the LPIPS term of Eq. 15
# left out or not the paper's) in timing.json; renders of an older render stage lack it.
UNRECORDED_FIT_NOTE = "fit's LPIPS term unknown (renders written before the render stage recorded it, re-run render)"


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


REGION_KEYS = [f"{metric}_{region}" for metric in ("psnr", "ssim") for region in ("garment", "body", "background")]


def _mean_of_present(values: pd.Series) -> float:
    """Mean over the images where the value exists (a region can be absent from a view); NaN when none has it."""
    present = values.dropna()
    return float(present.mean()) if len(present) else math.nan


def evaluate_level(capture, split: str, level_dir: Path, cfg: EvaluateConfig, lpips_net, inception, device,
                   fid_note: str = "", labeller: RegionLabeller | None = None) -> tuple[pd.DataFrame, dict]:
    """Per-image metrics (DataFrame) and summary (dict) of one split at one LOD, over the split's views that
    have ground truth. Without `inception` the FID is NaN with `fid_note`. With a `labeller` (true meshes), also
    PSNR/SSIM per region (REGION_KEYS)."""
    # Batches never mix image sizes (DNA-Rendering's two camera groups differ).
    by_size: dict[tuple[int, int], list] = {}
    for c, f in capture.views(split):
        by_size.setdefault((capture.cameras[c].width, capture.cameras[c].height), []).append((c, f))
    batches = [pairs[i:i + cfg.batch_size] for pairs in by_size.values() for i in range(0, len(pairs), cfg.batch_size)]
    rows, fake_features, real_features = [], FeatureStatistics(), FeatureStatistics()
    reader = RenderReader(level_dir, {name: (cam.width, cam.height) for name, cam in capture.cameras.items()})

    def truth(view):
        mask = capture.mask(*view)
        return capture.image(*view) * mask[..., None], mask

    with ThreadPoolExecutor(cfg.encode_workers, thread_name_prefix="evaluate-decode") as pool:
        # Decoding (OpenCV, off the GIL) of the next batch overlaps the metrics of this one.
        def load(batch):
            return pool.map(lambda view: reader.image(*view), batch), pool.map(truth, batch)

        loaded = [load(batch) for batch in batches[:1]]
        for b, batch in enumerate(progress_bar(batches, desc=f"evaluate {split} {level_dir.name}", unit="batch")):
            if b + 1 < len(batches):
                loaded.append(load(batches[b + 1]))
            renders_iter, truths_iter = loaded.pop(0)
            truths, masks = zip(*truths_iter)
            renders, truths, masks = np.stack(list(renders_iter)), np.stack(truths), np.stack(masks)
            rows.extend(_score_batch(batch, renders, truths, masks, level_dir, lpips_net, inception, device,
                                     labeller, fake_features, real_features, protocol(cfg.protocol)))
    table = pd.DataFrame(rows)
    summary = {k: float(table[k].mean()) for k in ("psnr", "ssim", "lpips", "psnr_blank", "ssim_blank")}
    if labeller is not None:
        summary.update({key: _mean_of_present(table[key]) for key in REGION_KEYS})
    summary["images"] = len(table)
    fid = math.nan
    if inception is not None:
        fid, fid_note = fid_from_statistics(fake_features, real_features, cfg.fid_min_images)
    summary.update(fid=fid, fid_images=len(table), fid_min_images=cfg.fid_min_images, fid_note=fid_note)
    return table, summary


def _score_batch(batch, renders, truths, masks, level_dir, lpips_net, inception, device, labeller, fake_features,
                 real_features, rules: Protocol) -> list[dict]:
    """Per-image metric rows of one batch by the protocol's `rules`; FID features go into the running statistics."""
    rows = []
    if renders.shape != truths.shape:
        raise ValueError(f"{level_dir}: renders are {renders.shape[1:3]} but the capture's images are {truths.shape[1:3]}")
    x = torch.from_numpy(renders).permute(0, 3, 1, 2).to(device)
    y = torch.from_numpy(np.ascontiguousarray(truths, dtype=np.float32)).permute(0, 3, 1, 2).to(device)
    blank = torch.zeros_like(y)
    with torch.no_grad():
        similarity = ssim_map(x, y)
        # LPIPS and FID see the protocol's crop; PSNR, SSIM and the regions the full frame.
        xc, yc = (x, y) if not rules.crop else [crop_to_mask_box(t, torch.from_numpy(masks).to(device)) for t in (x, y)]
        values = {
            "psnr": psnr(x, y),
            "ssim": similarity.flatten(1).mean(1) if rules.ssim_window == "gaussian11" else ssim_uniform(x, y).float(),
            "lpips": lpips_net(xc, yc) if lpips_net is not None else torch.full((len(batch),), math.nan),
            "psnr_blank": psnr(blank, y),
            "ssim_blank": ssim(blank, y, reduction="none"),
        }
        if labeller is not None:
            labels = torch.from_numpy(np.stack([labeller(cam, frame) for cam, frame in batch])).to(device)
            region_values = {"psnr": region_psnr(x, y, labels), "ssim": region_ssim(similarity, labels)}
            for metric, per_region in region_values.items():
                for region, code in REGIONS.items():
                    values[f"{metric}_{region}"] = per_region[:, code]
        if inception is not None:
            fake_features.update(inception(xc).double().cpu().numpy())
            real_features.update(inception(yc).double().cpu().numpy())
    for i, (cam, frame) in enumerate(batch):
        rows.append({"camera": cam, "frame": frame, **{k: float(v[i]) for k, v in values.items()}})
    return rows


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
    claim_files(output_dir, [f"{split}_lod{level}{ext}" for level in levels for ext in (".csv", ".json")], "evaluate",
                (capture_dir, split_dir), overwrite)
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
        lambda: LPIPS(cfg.lpips_net, cfg.lpips_backbone_weights, cfg.lpips_linear_weights).to(device), "LPIPS")
    rules = protocol(cfg.protocol)
    inception, fid_note = _load_metric(lambda: InceptionFeatures(cfg.inception_weights, rules.fid_resize).to(device),
                                       "FID")
    weights = weights_note(cfg, lpips_net is not None, inception is not None)
    truth = TrueMeshes.load(capture_dir / GT_MESHES) if (capture_dir / GT_MESHES).is_file() else None
    labeller = None
    if truth is not None:
        truth.require_frames(capture.split[split]["frames"], f"split {split!r}")
        labeller = RegionLabeller(truth, capture.cameras)
        for level in levels:  # before any work: renders of an older render stage lack them
            SplatTrack.require(split_dir / f"lod{level}" / SPLATS)
    written = []
    for level in levels:
        level_dir = split_dir / f"lod{level}"
        table, summary = evaluate_level(capture, split, level_dir, cfg, lpips_net, inception, device, fid_note,
                                        labeller)
        if truth is not None:
            summary.update(ground_truth_geometry(_splat_track(level_dir, capture, split), truth, cfg.geometry_frames))
        timing = read_record(level_dir / "timing.json", "the render stage's timing record (splats, model_mb, fps, device)")
        timing.setdefault("fit_note", UNRECORDED_FIT_NOTE)
        summary.update(split=split, lod=level, lpips_net=cfg.lpips_net, lpips_note=lpips_note, protocol=cfg.protocol,
                       protocol_note=rules.note if cfg.protocol != "ours" else "", weights_note=weights,
                       **timing)
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
    return written


def _splat_track(level_dir: Path, capture, split: str) -> SplatTrack:
    """The render stage's splat track of one LOD, which must cover the split's frames."""
    track = SplatTrack.load(level_dir / SPLATS)
    frames = sorted(int(f) for f in capture.split[split]["frames"])
    if track.frames.tolist() != frames:
        raise CaptureError(f"{level_dir / SPLATS}: frames {track.frames.tolist()[:8]} are not the frames of split "
                           f"{split!r} ({frames[:8]}...); the renders are of another split or capture: rerun render")
    return track


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("evaluate", __doc__, "pig evaluate --capture results/synthetic/subject00/capture --renders "
                                               "results/synthetic/subject00/pig/renders/novel_view --split novel_view --output results/synthetic/subject00/pig/metrics")
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture directory")
    parser.add_argument("--renders", type=Path, required=True, help="renders/{split} directory of the render stage")
    parser.add_argument("--split", required=True, choices=["novel_view", "novel_pose", "train"],
                        help="the split the renders are of")
    parser.add_argument("--output", type=Path, required=True, help="metrics directory ({split}_lod{l}.csv/.json go here)")
    parser.add_argument("--lod", type=int, nargs="*", default=None, help="levels to evaluate (default: all rendered)")
    add_preset_argument(parser, "its evaluate section")
    add_device_argument(parser, None, "the preset's evaluate.device")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace files of the same names in an --output folder the evaluate stage did not write")
    args = parser.parse_args(argv)
    cfg = load_section(load_preset(args.preset), "evaluate", EvaluateConfig, {"device": args.device} if args.device else None)
    evaluate_split(args.capture, args.renders, args.split, args.output, cfg, args.lod, args.overwrite)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
