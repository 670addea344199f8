"""Preprocess stage: raw capture -> undistorted, masked, resized frames, cameras, SMPL-X parameters, splits, report.

Writes the directory `pig.data.capture.Capture.load` reads (FORMATS.md layouts in, interfaces' layout out)
into a work folder renamed at the end, after the projection sanity check passed; no paper equation. Training
views are JPEG (4:4:4) and held-out views PNG by default, masks 1-bit PNG (benchmarks/encoding.py measured the
choice). A killed or failed run resumes: a rerun with the same settings keeps the images already written.
A synthetic capture's true meshes (gt_meshes.npz beside the raw data) are checked and copied along unchanged.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import torch

from pig.body.model import BodyModel, BodyModelError
from pig.config import Bounds, ConfigError, load_preset, load_section, load_yaml, named_config
from pig.data.capture import MASK_SUFFIX
from pig.data.formats import FORMATS, capture_format, open_capture, reader_options
from pig.data.ground_truth import GT_MESHES, TrueMeshes
from pig.data.images import read_image
from pig.data.projection_check import Tolerance, View, check_projection
from pig.data.raw import CaptureError, RawCapture
from pig.data.rectify import MASK_THRESHOLD, Rectifier, output_size, scaled_intrinsics
from pig.data.splits import SplitConfig, make_split, require_views
from pig.names import safe_name
from pig.resources import host_cores
from pig.progress import progress_bar
from pig._cli import add_common_arguments, add_preset_argument, run_cli, stage_parser
from pig._io import atomic_path, write_json
from pig._outputs import OutputError, claim_dir, marked_stage, resumable_dir

RAW_BODY_MODEL = "body_model.npz"  # the synthetic capture ships its body model beside the data
HELD_OUT = ("novel_view", "novel_pose")


@dataclass
class PreprocessConfig:
    scale: Annotated[float, Bounds(gt=0)] = 1.0  # resize factor applied after undistortion
    # Cap on the longer output side in pixels (None: no cap); smaller images hold too few pixels to check.
    max_side: Annotated[int, Bounds(ge=16)] | None = None
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # RGB in [0, 1] outside the mask
    # Threads decoding, undistorting and encoding frames; None: one per usable core. Threads suffice: a worker
    # holds the GIL for under 3 % of its time, the rest is OpenCV, numpy and file I/O (benchmarks/preprocess.py).
    workers: int | None = None
    # Training views lossy, held-out views (the evaluation's ground truth) lossless: a 24 x 2500 THuman4 subject
    # is ~12 GB, against ~20 GB as all PNG (benchmarks/encoding.py). Masks are always 1-bit PNG.
    train_encoding: Literal["jpeg", "png"] = "jpeg"
    heldout_encoding: Literal["png", "jpeg"] = "png"
    jpeg_quality: int = 95  # 4:4:4 chroma; 42.8 dB inside the mask against the float result at 1330 x 1150
    png_compression: int = 1  # zlib level of the written PNGs (1: fast; 6 saves 10 % at twice the time)
    check_frames: Annotated[int, Bounds(ge=1)] = 3  # frames per camera sampled for the projection check
    # Tolerances of the check's IoU at the body's depth (pig/data/projection_check.py): body outside the mask
    # (calibration and fitting error) and mask outside the body (loose garments, hair). The synthetic capture's
    # skirt scores 0.905..0.956 with a symmetric 5 cm and 0.995..1.0 with 5 / 20 cm (benchmarks/NOTES.md).
    check_body_tolerance_m: float = 0.05
    check_garment_tolerance_m: float = 0.20
    min_iou: Annotated[float, Bounds(gt=0, le=1)] = 0.9  # every camera must reach this tolerant IoU
    mask_resize: Literal["area", "nearest"] = "area"  # mask resampling; "nearest" as DNA-Rendering peers do
    # Dataset name -> overrides of the keys above, e.g. dna: {scale: 0.5, mask_resize: nearest} (peers' protocol).
    datasets: dict[str, dict] = field(default_factory=dict)


def resolve_body_model(explicit: str | Path | None, raw_root: Path) -> Path:
    """The body model to use: the explicit path, else body_model.npz in the raw folder, else a clear error."""
    if explicit is not None:
        path = Path(explicit)
        if not path.exists():  # a FIFO or device is refused by the reader, named as such
            raise BodyModelError(f"body model {path} does not exist (expected an SMPL-X npz such as SMPLX_NEUTRAL.npz)")
        return path
    if (raw_root / RAW_BODY_MODEL).is_file():
        return raw_root / RAW_BODY_MODEL
    raise BodyModelError(
        f"no body model for {raw_root}: download SMPLX_NEUTRAL.npz (licensed, smpl-x.is.tue.mpg.de), put it e.g. at "
        "data/body_models/SMPLX_NEUTRAL.npz and set `body_model:` in the dataset YAML or pass --body-model; "
        f"a synthetic capture has {RAW_BODY_MODEL} in its folder")


def _sample_frames(frames: list[int], count: int) -> list[int]:
    """`count` frames evenly spaced over `frames` (all of them if fewer)."""
    picks = np.unique(np.round(np.linspace(0, len(frames) - 1, min(count, len(frames)))).astype(int))
    return [frames[i] for i in picks]


def _encoders(cfg: PreprocessConfig) -> dict[str, tuple[str, list[int]]]:
    """Encoding name -> (suffix, cv2.imencode parameters)."""
    return {"jpeg": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality,
                              cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]),
            "png": (".png", [cv2.IMWRITE_PNG_COMPRESSION, cfg.png_compression]),
            "mask": (MASK_SUFFIX, [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, cfg.png_compression])}


def _check_config(cfg: PreprocessConfig) -> np.ndarray:
    """The background as uint8 RGB; ConfigError for values OpenCV would reject or silently clamp."""
    background = np.round(np.clip(np.asarray(cfg.background, dtype=np.float64), 0, 1) * 255).astype(np.uint8)
    if background.shape != (3,):
        raise ConfigError(f"preprocess.background must be 3 numbers (RGB in [0, 1]), found {cfg.background}")
    if not 1 <= cfg.jpeg_quality <= 100:
        raise ConfigError(f"preprocess.jpeg_quality must be in 1..100, found {cfg.jpeg_quality}")
    if cfg.workers is not None and cfg.workers < 1:
        raise ConfigError(f"preprocess.workers must be at least 1 (or null: one per core), found {cfg.workers}")
    if not 0 <= cfg.png_compression <= 9:
        raise ConfigError(f"preprocess.png_compression must be a zlib level in 0..9, found {cfg.png_compression}")
    return background


def _write_encoded(path: Path, image: np.ndarray, suffix: str, params: list[int]) -> None:
    """Encode and write atomically: a killed run leaves a hidden temporary, never a cut-short image."""
    ok, data = cv2.imencode(suffix, image, params)
    if not ok:
        raise CaptureError(f"{path}: OpenCV could not encode the image")
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        handle.write(data)


def _written(work: Path, camera: str, names: dict[int, str]) -> set[int]:
    """Frames of `camera` whose image (named by `names`) and mask an earlier run already wrote into `work`;
    removes the temporaries killed writers left there (the caller holds the output's lock)."""
    present = {}
    for kind in ("images", "masks"):
        folder = work / kind / camera
        folder.mkdir(parents=True, exist_ok=True)
        present[kind] = set()
        for entry in os.scandir(folder):
            if entry.name.startswith("."):
                os.unlink(entry.path)
            else:
                present[kind].add(entry.name)
    return {f for f, name in names.items()
            if name in present["images"] and f"{f:08d}{MASK_SUFFIX}" in present["masks"]}


def _raw_manifest(source: Path) -> str:
    """SHA-256 of the path, size and modification time of every file of the raw capture (a file or a folder):
    any raw file replaced or edited between a killed run and its rerun starts the work afresh. Stats only."""
    files = [source] if source.is_file() else sorted(
        Path(folder) / name for folder, _, names in os.walk(source) for name in names)
    digest = hashlib.sha256()
    for path in files:
        stat = path.stat()
        digest.update(f"{path} {stat.st_size} {stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def _settings(raw: RawCapture, cfg: PreprocessConfig, split: dict, pairs: list[tuple[str, int]]) -> dict:
    """Everything the written images depend on: a resumed run reuses them only when this is unchanged."""
    def camera(cam):
        entry = {"K": cam.K.tolist(), "dist": cam.dist.tolist(), "size": [cam.width, cam.height]}
        if cam.color_correction is not None:
            entry["color_correction"] = np.asarray(cam.color_correction).tolist()
        return entry

    keys = ("scale", "max_side", "background", "mask_resize", "train_encoding", "heldout_encoding", "jpeg_quality",
            "png_compression")
    source = Path(raw.source).resolve()
    return {"format": type(raw).__name__, "source": str(source), "raw_files": _raw_manifest(source),
            "config": {key: getattr(cfg, key) for key in keys},
            "cameras": {name: camera(cam) for name, cam in raw.cameras.items()}, "split": split,
            "views": hashlib.sha256(json.dumps(pairs).encode()).hexdigest()}


def preprocess_capture(raw: RawCapture, output: str | Path, cfg: PreprocessConfig, body_model: str | Path,
                       split_cfg: SplitConfig, subject: str, split_source: str = "split",
                       progress: bool = True, overwrite: bool = False, inputs: tuple[Path, ...] = ()) -> dict:
    """Write the preprocessed capture of `raw` to `output` (atomically, resuming an earlier run's unfinished work
    with the same settings) and return its report.

    `output` may replace only an earlier preprocessed capture unless `overwrite`; it never overlaps the raw
    capture, the body model or the other `inputs`."""
    start = time.perf_counter()
    # Camera ids name the folders written below (whichever reader gave them): each one path component.
    for camera in raw.cameras:
        safe_name(camera, "camera id", str(raw.source), CaptureError)
    safe_name(subject, "subject", split_source)
    output = claim_dir(output, "preprocess", (raw.source, body_model, *inputs), overwrite)
    if not overwrite:
        _check_same_capture(output, raw, subject)
    background = _check_config(cfg)
    encoders = _encoders(cfg)
    body_model = Path(body_model)
    cameras = list(raw.cameras)
    split = make_split(cameras, raw.frames, split_cfg, subject, split_source)
    require_views(split, raw.has_frame, split_source, raw.source)
    needed = {(c, f) for part in split.values() for c in part["cameras"] for f in part["frames"]}
    held_out = {(c, f) for name in HELD_OUT for c in split[name]["cameras"] for f in split[name]["frames"]}
    pairs = [(c, f) for c in cameras for f in raw.frames if (c, f) in needed and raw.has_frame(c, f)]
    frames = sorted({f for part in split.values() for f in part["frames"]})
    model = BodyModel.from_file(body_model, dtype=torch.float64)

    sizes = {c: output_size(cam.width, cam.height, cfg.scale, cfg.max_side) for c, cam in raw.cameras.items()}
    views = {c: View(scaled_intrinsics(cam.K, sizes[c][0] / cam.width, sizes[c][1] / cam.height), cam.R, cam.T,
                     *sizes[c]) for c, cam in raw.cameras.items()}
    by_camera = {c: [f for cc, f in pairs if cc == c] for c in cameras}
    checked = {c: _sample_frames(fs, cfg.check_frames) for c, fs in by_camera.items() if fs}
    # Pose the body for the check first: a body model that does not fit the parameters fails before any writing.
    check_ids = sorted({f for fs in checked.values() for f in fs})
    with torch.no_grad():
        sel = raw.params.select([raw.frames.index(f) for f in check_ids])
        posed = model(torch.from_numpy(sel.full_pose), torch.from_numpy(sel.betas),
                      torch.from_numpy(sel.expression), torch.from_numpy(sel.transl)).vertices.numpy()
    vertices = dict(zip(check_ids, posed))

    def encoding(cam: str, frame: int) -> str:
        return cfg.heldout_encoding if (cam, frame) in held_out else cfg.train_encoding

    with resumable_dir(output, "preprocess", _settings(raw, cfg, split, pairs)) as work:
        def write(rectify: Rectifier, frame: int) -> tuple[int, np.ndarray] | None:
            cam = rectify.camera.name
            image, mask = rectify(raw.read_image(cam, frame), raw.read_mask(cam, frame), background)
            suffix, params = encoders[encoding(cam, frame)]
            _write_encoded(work / "images" / cam / f"{frame:08d}{suffix}", cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                           suffix, params)
            # The mask last: a frame counts as written (`_written`) once both files are there.
            _write_encoded(work / "masks" / cam / f"{frame:08d}{MASK_SUFFIX}", mask.astype(np.uint8) * 255,
                           *encoders["mask"])
            return (frame, mask) if frame in checked[cam] else None

        names = {c: {f: f"{f:08d}{encoders[encoding(c, f)][0]}" for f in fs} for c, fs in by_camera.items()}
        done = {c: _written(work, c, names[c]) for c in cameras}
        check_masks: dict[str, dict[int, np.ndarray]] = {c: {} for c in checked}
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)  # parallel over images instead; OpenCV's own pool would oversubscribe the cores
        pool = ThreadPoolExecutor(cfg.workers or host_cores())
        resumed = sum(map(len, done.values()))
        bar = progress_bar(total=len(pairs), initial=resumed, desc="preprocess", unit="img", disable=not progress)
        images_start = time.perf_counter()
        try:
            # Camera by camera, so only one camera's undistortion maps are alive at a time. pool.map keeps the
            # check masks only: memory does not grow with the capture.
            for cam, cam_frames in by_camera.items():
                todo = [f for f in cam_frames if f not in done[cam]]
                if todo:
                    rectify = Rectifier(raw.cameras[cam], *sizes[cam], cfg.mask_resize)
                    for result in pool.map(lambda frame: write(rectify, frame), todo):
                        if result is not None:
                            check_masks[cam][result[0]] = result[1]
                        bar.update()
                for frame in checked.get(cam, ()):  # written by an earlier run: read back for the check
                    if frame in done[cam]:
                        path = work / "masks" / cam / f"{frame:08d}{MASK_SUFFIX}"
                        check_masks[cam][frame] = read_image(path, cv2.IMREAD_GRAYSCALE) > 127
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            cv2.setNumThreads(threads)
            bar.close()
        images_s = time.perf_counter() - images_start

        cameras_json = {c: {"K": v.K.tolist(), "R": v.R.tolist(), "T": v.T.tolist(), "width": v.width,
                            "height": v.height} for c, v in views.items()}
        write_json(work / "cameras.json", cameras_json)
        row = {f: i for i, f in enumerate(raw.frames)}
        params = raw.params.select([row[f] for f in frames])
        params.save(work / "smplx.npz", frame_ids=frames)
        write_json(work / "split.json", split)
        shutil.copyfile(body_model, work / "body_model.npz")
        truth = Path(raw.source) / GT_MESHES
        if truth.is_file():  # a synthetic capture's true meshes, for the evaluate stage's ground-truth metrics
            TrueMeshes.load(truth).require_frames(frames, f"the capture's splits ({split_source})")
            shutil.copyfile(truth, work / GT_MESHES)

        check_start = time.perf_counter()
        _require_person(raw, checked, check_masks)
        check = check_projection({c: views[c] for c in checked}, checked,
                                 {c: [check_masks[c][f] for f in fs] for c, fs in checked.items()}, vertices,
                                 model.faces.numpy(), Tolerance(cfg.check_body_tolerance_m,
                                                                cfg.check_garment_tolerance_m), cfg.min_iou)
        report = {
            "format": type(raw).__name__,
            "source": str(raw.source),
            "subject": subject,
            "body_model": str(body_model),
            "config": asdict(cfg),
            "cameras": len(cameras),
            "frames": len(frames),
            "images": len(pairs),
            "images_resumed": resumed,
            "missing": len(needed) - len(pairs),
            "megabytes": {kind: round(_folder_bytes(work / kind) / 1e6, 3) for kind in ("images", "masks")},
            "background": background.tolist(),
            "projection_check": check,
            "seconds": round(time.perf_counter() - start, 3),
            "seconds_images": round(images_s, 3),
            "seconds_check": round(time.perf_counter() - check_start, 3),
        }
        write_json(work / "report.json", report)  # a non-finite IoU or radius is written as null
    return report


def _require_person(raw: RawCapture, checked: dict[str, list[int]], masks: dict[str, dict[int, np.ndarray]]) -> None:
    """CaptureError naming the masks when a camera's masks show no person in any checked frame: the projection
    check would blame the calibration."""
    empty = {c: fs for c, fs in checked.items() if not any(masks[c][f].any() for f in fs)}
    if empty:
        listed = "; ".join(f"camera {c}, frames {fs}" for c, fs in empty.items())
        raise CaptureError(f"{raw.source}: the masks are empty (all black, no pixel above {MASK_THRESHOLD}) in every "
                           f"frame checked for {len(empty)} of {len(checked)} cameras ({listed}); masks mark the person "
                           "with 255: check the mask files of these cameras")


def _check_same_capture(output: Path, raw: RawCapture, subject: str) -> None:
    """Refuse to replace an earlier preprocessed capture of another raw capture or subject (its report.json says
    which); a rerun on the same raw capture may replace it. Writes nothing."""
    if marked_stage(output) != "preprocess":
        return
    try:
        report = json.loads((output / "report.json").read_text())
        held, held_subject = Path(report["source"]), report["subject"]
    except (OSError, ValueError, KeyError, TypeError):  # unfinished or older: nothing says whose capture it is
        return
    if held.resolve() != Path(raw.source).resolve() or held_subject != subject:
        raise OutputError(f"{output}: holds the preprocessed capture of {held} (subject {held_subject!r}), not of "
                          f"{raw.source} (subject {subject!r}); choose another --output, or pass --overwrite to "
                          "replace it")


def _folder_bytes(folder: Path) -> int:
    return sum(entry.stat().st_size for sub in os.scandir(folder) for entry in os.scandir(sub.path))


def _dataset(value: str | None) -> dict:
    """The dataset YAML (a name under config/datasets/ or a path) with `_path` set; {} when not given."""
    if value is None:
        return {}
    path = Path(value)
    if path.suffix not in (".yaml", ".yml"):
        path = named_config("datasets", value)
    data = load_yaml(path)
    data["_path"] = str(path)
    return data


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("preprocess", __doc__, "pig preprocess --input results/synthetic/data/subject00 "
                                                 "--output results/synthetic/subject00/capture --preset test")
    parser.add_argument("--format", choices=sorted(FORMATS), default=None,
                        help="capture format (default: the dataset's `format`, else thuman4)")
    parser.add_argument("--input", required=True, type=Path, help="raw subject folder (e.g. data/thuman4/subject00)")
    parser.add_argument("--output", required=True, type=Path, help="preprocessed capture folder to write")
    add_preset_argument(parser, "its preprocess section")
    parser.add_argument("--dataset", default=None,
                        help="dataset YAML or name under config/datasets/ (its `split:` and `reader:` sections and "
                             "`body_model`)")
    parser.add_argument("--subject", default=None, help="subject name for per-subject split rules (default: input folder name)")
    parser.add_argument("--body-model", default=None, type=Path,
                        help="SMPL-X model npz (default: the dataset's body_model, else body_model.npz in --input)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --output folder that is not an earlier preprocessed capture")
    parser.add_argument("--no-progress", dest="quiet", action="store_true", help=argparse.SUPPRESS)  # the old --quiet
    add_common_arguments(parser)
    args = parser.parse_args(argv)
    preset = load_preset(args.preset)
    dataset = _dataset(args.dataset)
    per_dataset = ((preset.get("preprocess") or {}).get("datasets") or {}).get(dataset.get("name"))
    cfg = load_section(preset, "preprocess", PreprocessConfig, overrides=per_dataset)
    split_cfg = load_section(dataset, "split", SplitConfig)
    split_source = f"{dataset.get('_path', 'default split')}: section 'split'"
    fmt = args.format or dataset.get("format") or "thuman4"
    capture_format(fmt).required_files(args.input)  # a missing root says where the data goes, before anything else
    body_model = resolve_body_model(args.body_model or dataset.get("body_model"), args.input)
    options = {"body_model": body_model} if capture_format(fmt).needs_body_model else {}
    options.update(reader_options(fmt, dataset.get("reader"), f"{dataset.get('_path', '--dataset')}"))
    raw = open_capture(fmt, args.input, **options)
    report = preprocess_capture(raw, args.output, cfg, body_model, split_cfg, args.subject or args.input.name,
                                split_source, progress=not args.quiet, overwrite=args.overwrite,
                                inputs=(args.input,))
    worst = min(report["projection_check"]["cameras"].items(), key=lambda item: item[1]["iou"])
    print(f"preprocess: wrote {report['images']} images of {report['cameras']} cameras to {args.output} "
          f"in {report['seconds']:.1f} s; lowest projection IoU {worst[1]['iou']:.3f} ({worst[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
