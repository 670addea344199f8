"""Render and evaluate at the THuman4 protocol's scale: wall time, views/s, peak host/GPU memory, bytes per stage,
and where a render and an evaluate second go.

Builds a capture of THuman4's dimensions (24 cameras, 2000 training + 500 novel-pose frames, 1330 x 1150).
By default `--generated-frames` frames are generated and preprocessed, the others repeat their images by hard
links (as benchmarks/data_scale.py does) under SMPL-X poses that never repeat (seeded noise on the body joints), so
every frame is its own pose and nearest-timestep lookup, but the ground truth repeats. `--upscale S` instead
generates every frame at 1/S of the size and upscales it in preprocess (data_scale.build_capture): no two frames
share pixels, as the whole-protocol figure needs. The split is THuman4's: cam23 held out on the training frames
(novel view), all 24 cameras on the last 500 (novel pose), its views stored as lossless PNG as preprocess stores
held-out views; `--fraction` scales both frame counts. An avatar with one timestep per training frame is fitted
for `--iterations` iterations, then the render stage runs per split and the evaluate stage per split (every LOD in
one process, as the workflow runs it; `--evaluate-per-lod`: one process per LOD, as the workflow did before), each
as its own process with the workflow's command line, so old and new code (`--code`) run the same way. LPIPS-VGG
and FID use stand-in random weights written to the work folder's torch hub cache (real weights cost the same time).

`--breakdown-batches N` then times each part of an evaluate second alone, on N batches of novel-pose views with
the device synchronised around each (`breakdown`): decoding ground truth and renders (one thread), the
host-to-device copies (float32 from pageable memory as the old stage did, uint8 from page-locked as now), PSNR,
SSIM, LPIPS-VGG (pair, and the render side against cached ground-truth taps) and the FID network, in ms per view;
with `--lpips-precision` / `--fid-precision` / `--channels-last` (passed to the evaluate stage's preset too) also
the networks' rows in that arithmetic and the largest |LPIPS - LPIPS float32| over the same views. With
`--lpips-window` (evaluate.lpips_window, the stage's preset too) also the batch's nonzero boxes on the host, LPIPS
in the preset's arithmetic over the window they give (LPIPS.window), the window's share of the frame, and the
largest |windowed - whole-frame LPIPS| in that arithmetic.

`--render-breakdown N` times each part of a render second alone on N novel-pose frames (after one warm-up frame),
through the render stage's own calls in its order, the device synchronised around each (`render_breakdown`): the
avatar's pose and decode per frame and LOD, the rasterization of every camera of a frame (one call per image size,
as the stage batches them), the uint8 conversion and device-to-host copy of a camera group's views at once (the
stage's) and, as the baseline, of each view alone (`.cpu()` into a fresh array), each view's encoding on one thread
(evaluate.render_codec) and the chunk writes; in ms per view (a view: one camera at one frame and LOD) and, for the
per-frame parts, ms per frame at that LOD; then the stage's device and host (encoding) time per view and the
views/s bound they imply with evaluate.encode_workers encoding threads.

    python benchmarks/eval_scale.py --workdir /tmp/evscale                     # CUDA: paper preset, whole protocol
    python benchmarks/eval_scale.py --workdir /tmp/evscale --device cpu --preset cpu-demo --fraction 0.004 \\
        --width 333 --height 288 --iterations 20 --code /path/to/other/checkout --evaluate-per-lod
    python benchmarks/eval_scale.py --combine half_a.json half_b.json   # runs' stage tables summed (two halves)
"""
from __future__ import annotations

import argparse
import copy
import importlib
import json
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from data_scale import build_capture, tile_capture  # noqa: E402

from pig.body.params import SmplxParams  # noqa: E402
from pig.data.ground_truth import GT_MESHES  # noqa: E402
from pig.config import derive_preset, load_preset  # noqa: E402

CAMERAS, TRAIN_FRAMES, POSE_FRAMES = 24, 2000, 500  # config/datasets/thuman4.yaml
HELD_OUT = "cam23"


def protocol_capture(workdir: Path, fraction: float, width: int, height: int, generated: int, workers: int,
                     upscale: int = 1) -> Path:
    """The THuman4-sized capture (see the module docstring); built once per size."""
    train, pose = max(2, round(TRAIN_FRAMES * fraction)), max(1, round(POSE_FRAMES * fraction))
    if upscale > 1:  # every frame generated: distinct ground truth, distinct poses
        target, _ = build_capture(workdir, CAMERAS, train + pose, width, height, workers, upscale)
        (target / GT_MESHES).unlink(missing_ok=True)  # a real capture's evaluation: no true-mesh metrics
    else:
        target = workdir / f"capture_{train}+{pose}_{width}x{height}"
        if (target / "report.json").is_file():
            return target
        source, _ = build_capture(workdir, CAMERAS, generated, width, height, workers)
        tile_capture(source, target, train + pose)
        params, ids = SmplxParams.load(target / "smplx.npz")
        rng = np.random.default_rng(0)
        pose_noise = np.zeros_like(params.full_pose)
        pose_noise[:, 1:22] = rng.normal(0.0, 0.05, (len(ids), 21, 3))  # body joints: no two frames share a pose
        SmplxParams(params.full_pose + pose_noise, params.betas, params.expression, params.transl).save(
            target / "smplx.npz", frame_ids=ids)
    cameras = sorted(json.loads((target / "cameras.json").read_text()))
    if HELD_OUT not in cameras:
        raise SystemExit(f"{target}: expected cameras cam00..cam23, found {cameras}")
    split = {"train": {"cameras": [c for c in cameras if c != HELD_OUT], "frames": list(range(train))},
             "novel_view": {"cameras": [HELD_OUT], "frames": list(range(train))},
             "novel_pose": {"cameras": cameras, "frames": list(range(train, train + pose))}}
    (target / "split.json").write_text(json.dumps(split))
    heldout_as_png(target, workers)
    return target


def heldout_as_png(capture_dir: Path, workers: int) -> None:
    """Store the held-out views that preprocess wrote as JPEG (training views of the generator's own split) as
    lossless PNG of the same pixels, as preprocess stores held-out views: the evaluation decodes what it would."""
    from pig.data.capture import Capture

    capture = Capture.load(capture_dir, cache_mb=0)
    views = {view for name in ("novel_view", "novel_pose") for view in capture.views(name)}
    jpegs = [(cam, frame) for cam, frame in sorted(views) if (capture_dir / "images" / cam / f"{frame:08d}.jpg").is_file()]

    def convert(view):
        cam, frame = view
        image = capture.image_u8(cam, frame)  # the JPEG's pixels as the capture reads them
        path = capture_dir / "images" / cam / f"{frame:08d}"
        if not cv2.imwrite(f"{path}.png", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise SystemExit(f"{path}.png: could not be written")
        Path(f"{path}.jpg").unlink()

    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(convert, jpegs))
    if jpegs:
        print(f"{len(jpegs)} held-out views re-stored as PNG", flush=True)


def distinct_truths(capture_dir: Path, workers: int) -> tuple[int, int]:
    """(distinct, all) held-out ground-truth images, told apart by their PNG bytes (one encoder and level: equal
    pixels give equal bytes)."""
    import hashlib

    split = json.loads((capture_dir / "split.json").read_text())
    paths = [capture_dir / "images" / cam / f"{frame:08d}.png" for name in ("novel_view", "novel_pose")
             for cam in split[name]["cameras"] for frame in split[name]["frames"]]
    with ThreadPoolExecutor(workers) as pool:
        digests = list(pool.map(lambda path: hashlib.sha256(path.read_bytes()).digest(), paths))
    return len(set(digests)), len(digests)


def stand_in_weights(torch_home: Path) -> None:
    """Random LPIPS-VGG (VGG-16 features by torchvision's keys + lpips linear layers) and a TorchScript
    Inception stand-in in `torch_home`/hub/checkpoints under the published names."""
    from pig.metrics.lpips import backbone_features
    from pig.metrics.weights import INCEPTION_FILE, LPIPS_LINEAR_FILES, TORCHVISION_FILES

    folder = torch_home / "hub" / "checkpoints"
    folder.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    if not (folder / TORCHVISION_FILES["vgg"]).is_file():
        features = backbone_features("vgg")
        for layer in features:
            if isinstance(layer, torch.nn.Conv2d):
                torch.nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
        torch.save({f"features.{k}": v for k, v in features.state_dict().items()}, folder / TORCHVISION_FILES["vgg"])
        widths = [64, 128, 256, 512, 512]
        torch.save({f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) * 2 / c for k, c in enumerate(widths)},
                   folder / LPIPS_LINEAR_FILES["vgg"])
    if not (folder / INCEPTION_FILE).is_file():
        torch.jit.script(InceptionStandIn()).save(str(folder / INCEPTION_FILE))


class InceptionStandIn(torch.nn.Module):
    """Random convolutions of Inception-v3's cost (7.1 GFLOP at 299 x 299 against its 5.7) to 2048 pooled
    features, called as the StyleGAN/clean-fid file is (no torchvision on the machines)."""

    def __init__(self):
        super().__init__()
        widths, layers = [3, 32, 64, 192, 384, 768], []
        for k, (c_in, c_out) in enumerate(zip(widths, widths[1:])):
            layers += [torch.nn.Conv2d(c_in, c_out, 3, stride=1 if k == 1 else 2, padding=1), torch.nn.ReLU()]
        self.net = torch.nn.Sequential(*layers, torch.nn.Conv2d(768, 2048, 1), torch.nn.AdaptiveAvgPool2d(1))

    def forward(self, x: torch.Tensor, return_features: bool = False) -> torch.Tensor:
        return self.net(x / 127.5 - 1).flatten(1)


def write_preset(workdir: Path, preset: str, iterations: int, device: str, evaluate: dict) -> Path:
    return derive_preset(workdir / "eval_scale_preset.yaml", preset,
                         fit=dict(iterations=iterations, eval_every=10**9, checkpoint_minutes=10**6,
                                  weight_lpips=0.0),  # the fit only makes renders like a real fit's
                         evaluate=dict(lpips_net="vgg", device=device, **evaluate))


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def run_stage(module: str, args: list[str], env: dict, report: Path) -> dict:
    """Run one stage in a fresh process as the workflow does; its wall time, peak RSS and peak GPU memory."""
    report.unlink(missing_ok=True)
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, __file__, "--stage", module, str(report), *args], env=env)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{module} {' '.join(args)} failed (exit {os.waitstatus_to_exitcode(status)})")
    gpu = json.loads(report.read_text())["peak_gpu_mib"] if report.is_file() else float("nan")
    return {"wall_s": wall, "peak_rss_mib": usage.ru_maxrss / 1024, "peak_gpu_mib": gpu}


def stage_child(module: str, report: str, args: list[str]) -> int:
    from pig._cli import run_cli

    code = run_cli(importlib.import_module(module).main, args)
    peak = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else float("nan")
    Path(report).write_text(json.dumps({"peak_gpu_mib": peak}))
    return code


def codec_table(split_dir: Path, count: int) -> list[dict]:
    """Bytes per view, encode and decode ms per view (one thread) of each lossless codec on `count` rendered views
    of the finest LOD, read back from the render stage's storage."""
    from pig.data.images import decode_image
    from pig.data.render_store import CODECS, RenderReader, encode_image

    level = max(int(p.name[3:]) for p in split_dir.glob("lod*"))
    reader = RenderReader(split_dir / f"lod{level}")
    manifest = json.loads((split_dir / "manifest.json").read_text())
    views = [(cam, frame) for frame in manifest["frames"] for cam in manifest["cameras"]][:count]
    images = [reader.image_u8(cam, frame) for cam, frame in views]
    rows = []
    print(f"\n{len(images)} views of {split_dir.name} lod{level}, {images[0].shape[1]} x {images[0].shape[0]}, one thread")
    print(f"{'codec':<6} {'KB/view':>8} {'encode ms':>10} {'decode ms':>10}")
    for codec in CODECS:
        start = time.perf_counter()
        streams = [encode_image(image, codec) for image in images]
        encode = time.perf_counter() - start
        start = time.perf_counter()
        decoded = [decode_image(stream, codec) for stream in streams]
        decode = time.perf_counter() - start
        if not all(np.array_equal(d[..., ::-1], image) for d, image in zip(decoded, images)):
            raise SystemExit(f"{codec}: a view did not decode to the same pixels")
        row = {"codec": codec, "bytes_per_view": sum(s.size for s in streams) / len(images),
               "encode_ms": 1000 * encode / len(images), "decode_ms": 1000 * decode / len(images)}
        rows.append(row)
        print(f"{codec:<6} {row['bytes_per_view'] / 1024:>8.1f} {row['encode_ms']:>10.1f} {row['decode_ms']:>10.1f}")
    return rows


class PartTimer:
    """Times each call of `timed(name, work)` alone: the device synchronised before and after; `times[name]` holds
    the seconds of each call."""

    def __init__(self, device: torch.device):
        self.sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
        self.times: dict[str, list[float]] = {}

    def __call__(self, name: str, work):
        self.sync()
        start = time.perf_counter()
        result = work()
        self.sync()
        self.times.setdefault(name, []).append(time.perf_counter() - start)
        return result


def breakdown(capture_dir: Path, split_dir: Path, preset: Path, device: str, batches: int) -> list[dict]:
    """Milliseconds per view of each part of an evaluate second, each timed alone on `batches` batches (the preset's
    evaluate.batch_size) of the split's views, the device synchronised around each: decoding (one thread), the
    host-to-device copies, and each metric. Runs this checkout's metrics in this process (TORCH_HOME set)."""
    from pig.config import load_section
    from pig.data.capture import Capture
    from pig.data.render_store import RenderReader
    from pig.metrics.fid import InceptionFeatures
    from pig.metrics.lpips import LPIPS
    from pig.metrics.psnr import psnr
    from pig.metrics.ssim import ssim_map
    from pig.stages.evaluate import EvaluateConfig, nonzero_box, union_box, view_batches

    cfg = load_section(load_preset(str(preset)), "evaluate", EvaluateConfig)
    dev = torch.device(device)
    capture = Capture.load(capture_dir, cache_mb=0)
    level = max(int(p.name[3:]) for p in split_dir.glob("lod*"))
    reader = RenderReader(split_dir / f"lod{level}")
    lpips, inception = LPIPS(cfg.lpips_net).to(dev), InceptionFeatures().to(dev)
    # The preset's arithmetic, when it is not float32's: its rows beside the float32 ones, on the same views.
    lowered = (cfg.lpips_precision, cfg.fid_precision, cfg.channels_last) != ("float32", "float32", False)
    layout = ", channels-last" if cfg.channels_last else ""
    arithmetic, fid_row = f"{cfg.lpips_precision}{layout}", f"FID Inception ({cfg.fid_precision}{layout})"
    if lowered:
        lpips_low = LPIPS(cfg.lpips_net, precision=cfg.lpips_precision, channels_last=cfg.channels_last).to(dev)
        inception_low = InceptionFeatures(precision=cfg.fid_precision, channels_last=cfg.channels_last).to(dev)
    lpips_gap = window_gap = 0.0
    window_share: list[float] = []
    lpips_preset_net = lpips_low if lowered else lpips
    window_rows = (f"LPIPS-{cfg.lpips_net} truth taps over the window ({arithmetic})",
                   f"LPIPS-{cfg.lpips_net} render vs taps over the window ({arithmetic})")
    timed = PartTimer(dev)
    times = timed.times

    chosen = view_batches(capture, split_dir.name, cfg.batch_size)[:batches + 1]
    for b, views in enumerate(chosen):  # the first batch warms up (cuDNN's choice of algorithms), not counted
        truths = timed("decode ground truth (1 thread)", lambda: [capture.image_u8(*v) for v in views])
        masks = timed("decode masks (1 thread)", lambda: [capture.mask(*v) for v in views])
        renders = timed("decode renders (1 thread)", lambda: [reader.image_u8(*v) for v in views])
        as_float = timed("uint8 to float32 + mask on the host (old)", lambda: (
            np.stack(renders).astype(np.float32) / 255,
            np.stack([t.astype(np.float32) / 255 * m[..., None] for t, m in zip(truths, masks)])))
        timed("copy float32 pair, pageable (old)", lambda: [torch.from_numpy(a).to(dev) for a in as_float])
        pinned = [torch.from_numpy(np.stack(a)).pin_memory() if dev.type == "cuda" else torch.from_numpy(np.stack(a))
                  for a in (renders, truths, masks)]
        on_device = timed("copy uint8 render + truth + mask, pinned (new)",
                          lambda: [t.to(dev, non_blocking=True) for t in pinned])
        x = (on_device[0].float() / 255).permute(0, 3, 1, 2)
        y = (on_device[1].float() / 255 * on_device[2][..., None]).permute(0, 3, 1, 2)
        with torch.no_grad():
            timed("PSNR", lambda: psnr(x, y))
            timed("SSIM", lambda: ssim_map(x, y).flatten(1).mean(1))
            timed(f"LPIPS-{cfg.lpips_net} pair (old: per LOD)", lambda: lpips(x, y))
            reference = timed(f"LPIPS-{cfg.lpips_net} truth taps (new: once)", lambda: lpips.reference(y))
            whole = timed(f"LPIPS-{cfg.lpips_net} render vs taps (new: per LOD)", lambda: lpips.distance(x, reference))
            timed("FID Inception, one image set", lambda: inception(x))
            if lowered:
                low_reference = timed(f"LPIPS-{cfg.lpips_net} truth taps ({arithmetic})",
                                      lambda: lpips_low.reference(y))
                low = timed(f"LPIPS-{cfg.lpips_net} render vs taps ({arithmetic})",
                            lambda: lpips_low.distance(x, low_reference))
                timed(fid_row, lambda: inception_low(x))
                lpips_gap = max(lpips_gap, (low - whole).abs().max().item())
                whole = low  # the window is compared in the preset's arithmetic
                del low_reference
            if cfg.lpips_window:
                boxes = timed("nonzero boxes of masks + renders (1 thread)",
                              lambda: [nonzero_box(image) for image in (*masks, *renders)])
                rows_, cols_ = lpips_preset_net.window(union_box(boxes) or (0, 1, 0, 1), *x.shape[-2:])
                window_share.append((rows_.stop - rows_.start) * (cols_.stop - cols_.start) / x[0, 0].numel())
                window_reference = timed(window_rows[0], lambda: lpips_preset_net.reference(y[..., rows_, cols_]))
                windowed = timed(window_rows[1], lambda: lpips_preset_net.distance(
                    x[..., rows_, cols_], window_reference, frame=tuple(x.shape[-2:])))
                window_gap = max(window_gap, (windowed - whole).abs().max().item())
                del window_reference
        del reference
        if b == 0:
            times.clear()
    views = sum(len(v) for v in chosen[1:])
    ms = {name: 1000 * sum(values) / views for name, values in times.items()}
    rows = [{"part": name, "ms_per_view": value} for name, value in ms.items()]
    print(f"\nwhere an evaluate second goes: {views} views of {split_dir.name} lod{level}, batches of "
          f"{cfg.batch_size}, device {device}, each part alone")
    print(f"{'part':<66} {'ms/view':>9}")
    for row in rows:
        print(f"{row['part']:<66} {row['ms_per_view']:>9.2f}")
    # Per view score (one view at one LOD) at this split's LOD count L: the old jobs redid the ground truth's
    # share at every LOD; the pass does it once per view. Host work runs on evaluate.encode_workers threads.
    lods = len(list(split_dir.glob("lod*")))
    net = cfg.lpips_net
    if lowered:
        print(f"largest |LPIPS {arithmetic} - LPIPS float32| over these views: {lpips_gap:.2e} (issue 39: 1e-3)")
        rows.append({"part": f"max |LPIPS {arithmetic} - float32|", "lpips_difference": lpips_gap})
    if cfg.lpips_window:
        share = sum(window_share) / len(window_share)
        print(f"LPIPS window: {share:.1%} of the frame on average over {len(window_share)} batches; largest "
              f"|windowed - whole-frame LPIPS| ({arithmetic}): {window_gap:.2e}")
        rows.append({"part": "LPIPS window share of the frame", "share": share})
        rows.append({"part": f"max |LPIPS windowed - whole frame| ({arithmetic})", "lpips_difference": window_gap})
    truth_host = ms["decode ground truth (1 thread)"] + ms["decode masks (1 thread)"]
    old_host = truth_host + ms["decode renders (1 thread)"] + ms["uint8 to float32 + mask on the host (old)"]
    new_host = truth_host / lods + ms["decode renders (1 thread)"]
    metrics = ms["PSNR"] + ms["SSIM"]
    old_device = (ms["copy float32 pair, pageable (old)"] + metrics + ms[f"LPIPS-{net} pair (old: per LOD)"]
                  + 2 * ms["FID Inception, one image set"])
    new_device = (ms["copy uint8 render + truth + mask, pinned (new)"] + metrics
                  + ms[f"LPIPS-{net} render vs taps (new: per LOD)"] + ms[f"LPIPS-{net} truth taps (new: once)"] / lods
                  + (1 + 1 / lods) * ms["FID Inception, one image set"])
    paths = [("old", old_host, old_device), ("new", new_host, new_device)]
    lpips_f32 = ms[f"LPIPS-{net} render vs taps (new: per LOD)"] + ms[f"LPIPS-{net} truth taps (new: once)"] / lods
    if lowered:  # the same pass with the networks' rows in the preset's arithmetic
        lpips_preset = (ms[f"LPIPS-{net} render vs taps ({arithmetic})"]
                        + ms[f"LPIPS-{net} truth taps ({arithmetic})"] / lods)
        fid_change = (1 + 1 / lods) * (ms[fid_row] - ms["FID Inception, one image set"])
        paths.append((f"new in {arithmetic}", new_host, new_device - lpips_f32 + lpips_preset + fid_change))
    if cfg.lpips_window:  # the preset's pass with LPIPS over the window, the boxes found on the host
        lpips_whole = lpips_preset if lowered else lpips_f32
        lpips_window = ms[window_rows[1]] + ms[window_rows[0]] / lods
        name, _, device_whole = paths[-1]
        paths.append((f"{name} with the LPIPS window", new_host + ms["nonzero boxes of masks + renders (1 thread)"],
                      device_whole - lpips_whole + lpips_window))
    for name, host, on_device in paths:
        print(f"{name}, per view score at {lods} LODs: host {host:.2f} ms on one thread "
              f"({host / cfg.encode_workers:.2f} ms on {cfg.encode_workers}), device {on_device:.2f} ms")
        rows.append({"part": f"{name} per view score: host, one thread", "ms_per_view": host})
        rows.append({"part": f"{name} per view score: device", "ms_per_view": on_device})
    return rows


def render_breakdown(capture_dir: Path, checkpoint: Path, preset: Path, split: str, frames: int,
                     scratch: Path) -> tuple[list[dict], dict]:
    """Milliseconds per view of each part of a render second, each timed alone on `frames` frames of the split (after
    one warm-up frame), the device synchronised around each, through the render stage's own calls in its order
    (every LOD of a frame, then the next frame): the avatar's pose and decode per frame and LOD, the rasterization
    of every camera (one call per image size), the uint8 conversion and copy to the host of a group's views at once
    (the stage's) and of each view alone (the baseline, left out of the stage's sum), each view's encoding
    (evaluate.render_codec, one thread) and the chunks' writes (one per LOD and camera, of the timed frames, in a
    temporary folder under `scratch`). A view is one camera at one frame and LOD, as the stage's views/s counts.

    Returns the rows and, for checks, the last frame's views: {(lod, camera): (uint8 image, encoded stream)}."""
    import tempfile

    from pig.config import load_section, resolve_device
    from pig.data.capture import Capture
    from pig.data.render_store import chunk_path, encode_image, write_chunk
    from pig.render.api import RasterizerConfig
    from pig.stages.evaluate import EvaluateConfig
    from pig.stages.render import _to_u8, load_renderer

    data = load_preset(str(preset))
    cfg = load_section(data, "evaluate", EvaluateConfig)
    capture = Capture.load(capture_dir, cache_mb=0)
    cameras = capture.split[split]["cameras"]
    dev = resolve_device(cfg.device)
    renderer, _, _ = load_renderer(checkpoint, capture, cameras, dev, load_section(data, "rasterizer", RasterizerConfig))
    levels = list(range(renderer.model.num_levels))
    track_splats = (capture_dir / GT_MESHES).is_file()  # the stage then copies each frame's centres and opacities
    chosen = [int(f) for f in capture.split[split]["frames"]][:frames + 1]
    timed_frames = chosen[1:] or chosen  # the first warms up (gsplat's and the decoders' first calls)
    timed = PartTimer(dev)
    times = timed.times

    pose_row = {lod: f"pose + decode avatar, lod{lod}" for lod in levels}
    raster_row = {lod: f"rasterize {len(cameras)} cameras, lod{lod}" for lod in levels}
    track_row, copy_row = "splat track to host", "to uint8 + copy to host, per group"
    copy_each_row = "to uint8 + copy to host, per view (old)"
    encode_row, write_row = f"encode {cfg.render_codec} (1 thread)", f"chunk write ({len(timed_frames)} frames)"
    streams: dict[tuple[int, str], list[np.ndarray]] = {}
    last: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] = {}
    for i, frame in enumerate(chosen):
        for lod in levels:
            gaussians = timed(pose_row[lod], lambda: renderer.gaussians(frame, lod))
            if track_splats:
                timed(track_row, lambda: (gaussians[0].cpu().numpy(), gaussians[3].cpu().numpy()))
            views = timed(raster_row[lod], lambda: list(renderer.render(frame, lod, gaussians=gaussians)))
            for cam, result, c in views:
                if c == 0:
                    images = timed(copy_row, lambda: _to_u8(result.color))
                timed(copy_each_row, lambda: (result.color[c].clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy())
                image = images[c]
                stream = timed(encode_row, lambda: encode_image(image, cfg.render_codec))
                if frame in timed_frames:
                    streams.setdefault((lod, cam), []).append(stream)
                    last[(lod, cam)] = image, stream
            del views, gaussians, images
        if i == 0 and len(chosen) > 1:
            times.clear()
    with tempfile.TemporaryDirectory(dir=scratch, prefix=".render-breakdown-") as folder:
        for (lod, cam), encoded in streams.items():
            path = chunk_path(Path(folder) / f"lod{lod}", cam, timed_frames[0])
            path.parent.mkdir(parents=True, exist_ok=True)
            timed(write_row, lambda: write_chunk(path, timed_frames, encoded, cfg.render_codec, cam, lod))

    per_frame = {*pose_row.values(), *raster_row.values(), track_row}
    lods, n, c = len(levels), len(timed_frames), len(cameras)
    # Views each row was timed over: the per-LOD rows over their LOD's views, the others over every LOD's.
    views_of = {name: n * c * (1 if name in pose_row.values() or name in raster_row.values() else lods)
                for name in times}
    order = [*pose_row.values(), *raster_row.values(), track_row, copy_row, copy_each_row, encode_row, write_row]
    rows = []
    for name in [name for name in order if name in times]:
        values = times[name]
        row = {"part": name, "ms_per_view": 1000 * sum(values) / views_of[name]}
        if name in per_frame:
            row["ms_per_frame"] = 1000 * sum(values) / len(values)
        rows.append(row)
    device_ms = 1000 * sum(sum(v) for k, v in times.items()
                           if k not in (encode_row, write_row, copy_each_row)) / (n * c * lods)
    host_ms = 1000 * (sum(times[encode_row]) + sum(times[write_row])) / (n * c * lods)
    workers = cfg.encode_workers
    bound = 1000 / max(device_ms, host_ms / workers)
    print(f"\nwhere a render second goes: {n} frames of {split} x {c} cameras x {lods} LODs, device {dev}, "
          f"{capture.cameras[cameras[0]].width} x {capture.cameras[cameras[0]].height}, each part alone")
    print(f"{'part':<44} {'ms/view':>9} {'ms/frame':>9}")
    for row in rows:
        frame_ms = f"{row['ms_per_frame']:>9.2f}" if "ms_per_frame" in row else f"{'':>9}"
        print(f"{row['part']:<44} {row['ms_per_view']:>9.2f} {frame_ms}")
    print(f"render stage, per view: device {device_ms:.2f} ms, host {host_ms:.2f} ms on one thread "
          f"({host_ms / workers:.2f} ms on {workers} encode workers): at most {bound:.1f} views/s")
    rows += [{"part": "render stage per view: device", "ms_per_view": device_ms},
             {"part": "render stage per view: host, one thread", "ms_per_view": host_ms},
             {"part": f"render stage per view: host on {workers} encode workers", "ms_per_view": host_ms / workers},
             {"part": "render stage bound", "views_per_s": bound}]
    rows += frame_paths(renderer, capture, split, frames, dev)
    return rows, last


def frame_paths(renderer, capture, split: str, frames: int, dev: torch.device) -> list[dict]:
    """A frame's avatar at each LOD through the render stage's driver (on CUDA its captured frame graphs) against the
    launched driver the stage used before, on `frames` frames of `split` and, if it is another, as many of the
    novel-view split's (training frames, one camera each: most of a novel view's cost), each timed alone after one
    warm-up frame (the capture), and the largest difference of their splats."""
    from pig.avatar.driver import AvatarDriver

    model = renderer.model
    launched = copy.copy(renderer)  # the stage's own frame routing, with the launched driver
    launched.driver = AvatarDriver(model)
    kinds = {name: [int(f) for f in capture.split[name]["frames"]][:frames + 1]
             for name in dict.fromkeys([split, "novel_view"]) if name in capture.split}

    timed, rows, gap = PartTimer(dev), [], 0.0
    print(f"\na frame's avatar, the stage's driver against the launched one (old): ms a frame, mean of {frames} "
          f"frames after one warm-up")
    print(f"{'LOD':<4} " + " ".join(f"{kind + ': stage':>18} {'launched':>9} {'ratio':>6}" for kind in kinds))
    for lod in range(model.num_levels):
        cells = []
        for kind, picks in kinds.items():
            for i, frame in enumerate(picks):
                ours = [t.clone() for t in timed(f"{kind} {lod} stage {i > 0}", lambda: renderer.gaussians(frame, lod))]
                theirs = timed(f"{kind} {lod} launched {i > 0}", lambda: launched.gaussians(frame, lod))
                gap = max(gap, max(float((a - b).abs().max()) for a, b in zip(ours, theirs)))
            stage, old = (timed.times.get(f"{kind} {lod} {path} True", [float("nan")]) for path in ("stage", "launched"))
            stage_ms, old_ms = 1000 * float(np.mean(stage)), 1000 * float(np.mean(old))
            rows += [{"part": f"{kind} frame avatar, lod{lod}, stage", "ms_per_frame": stage_ms},
                     {"part": f"{kind} frame avatar, lod{lod}, launched (old)", "ms_per_frame": old_ms}]
            cells.append(f"{stage_ms:>18.2f} {old_ms:>9.2f} {stage_ms / old_ms:>6.3f}")
        print(f"{lod:<4} " + " ".join(cells))
    print(f"largest |splat attribute, stage - launched| over these frames: {gap:.2e}")
    rows.append({"part": "frame avatar: largest difference, stage - launched", "difference": gap})
    return rows


def print_stage_table(rows: list[dict]) -> None:
    """The per-stage table: views, wall time, views a second, peak host and GPU memory, bytes written."""
    print(f"{'stage':<14} {'split':<11} {'views':>7} {'wall s':>8} {'views/s':>8} {'RSS MiB':>8} {'GPU MiB':>8} "
          f"{'bytes':>12} {'B/view':>8}")
    for row in rows:
        print(f"{row['stage']:<14} {row['split']:<11} {row['views']:>7} {row['wall_s']:>8.1f} "
              f"{row['views'] / row['wall_s']:>8.1f} {row['peak_rss_mib']:>8.0f} {row['peak_gpu_mib']:>8.0f} "
              f"{row['bytes']:>12} {row['bytes'] / row['views']:>8.0f}")
    total = {key: sum(row[key] for row in rows) for key in ("wall_s", "bytes")}
    print(f"{'total':<14} {'':<11} {'':>7} {total['wall_s']:>8.1f} {'':>8} {'':>8} {'':>8} {total['bytes']:>12}")


def combined_rows(runs: list[list[dict]]) -> list[dict]:
    """Several runs' stage rows as one protocol's (e.g. its two halves at --fraction 0.5): per stage and split the
    views, wall seconds and bytes summed, the peak memories the largest; in the first run's order."""
    merged: dict[tuple[str, str], dict] = {}
    for rows in runs:
        for row in rows:
            key = (row["stage"], row["split"])
            if key not in merged:
                merged[key] = {k: row[k] for k in ("stage", "split", "views", "wall_s", "peak_rss_mib", "peak_gpu_mib",
                                                    "bytes")}
                continue
            into = merged[key]
            for k in ("views", "wall_s", "bytes"):
                into[k] += row[k]
            for k in ("peak_rss_mib", "peak_gpu_mib"):
                into[k] = max(into[k], row[k])
    return list(merged.values())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--combine", type=Path, nargs="+", metavar="JSON",
                        help="print the summed stage table of earlier runs' --json files, and nothing else")
    parser.add_argument("--workdir", type=Path)
    parser.add_argument("--fraction", type=float, default=1.0, help="share of THuman4's 2000 + 500 frames")
    parser.add_argument("--width", type=int, default=1330)
    parser.add_argument("--height", type=int, default=1150)
    parser.add_argument("--generated-frames", type=int, default=4, help="frames generated; the rest hard links")
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    parser.add_argument("--iterations", type=int, default=300, help="iterations of the brief fit")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="generate/preprocess processes")
    parser.add_argument("--code", type=Path, default=None,
                        help="checkout whose stages run (PYTHONPATH); default: the one this script imports")
    parser.add_argument("--splits", nargs="+", default=["novel_view", "novel_pose"])
    parser.add_argument("--tag", default="", help="name of this code's results folder (default: new/other)")
    parser.add_argument("--codec", choices=["png", "webp"], default=None, help="evaluate.render_codec (preset's)")
    parser.add_argument("--encode-workers", type=int, default=None, help="evaluate.encode_workers (preset's)")
    parser.add_argument("--batch-size", type=int, default=None, help="evaluate.batch_size (preset's)")
    parser.add_argument("--lpips-precision", choices=["float32", "float16", "bfloat16"], default=None,
                        help="evaluate.lpips_precision (preset's); the breakdown adds its rows beside float32's")
    parser.add_argument("--fid-precision", choices=["float32", "float16", "bfloat16"], default=None,
                        help="evaluate.fid_precision (preset's)")
    parser.add_argument("--channels-last", action="store_true", help="evaluate.channels_last: true")
    parser.add_argument("--lpips-window", action="store_true",
                        help="evaluate.lpips_window: true; the breakdown adds the window's rows")
    parser.add_argument("--codec-sample", type=int, default=0,
                        help="also time every codec on this many rendered novel-pose views (one thread)")
    parser.add_argument("--upscale", type=int, default=1,
                        help="generate every frame at 1/S of the size, upscaled (distinct ground truth)")
    parser.add_argument("--evaluate-per-lod", action="store_true",
                        help="one evaluate process per LOD (the workflow before one pass per split)")
    parser.add_argument("--breakdown-batches", type=int, default=0,
                        help="also time each part of an evaluate second alone on this many novel-pose batches")
    parser.add_argument("--render-breakdown", type=int, default=0,
                        help="also time each part of a render second alone on this many novel-pose frames")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    if args.combine:
        runs = [json.loads(path.read_text())["rows"] for path in args.combine]
        print(f"{len(runs)} runs combined: {', '.join(map(str, args.combine))}")
        print_stage_table(combined_rows(runs))
        return 0
    if args.workdir is None:
        parser.error("--workdir is required (unless --combine)")
    args.workdir.mkdir(parents=True, exist_ok=True)
    capture = protocol_capture(args.workdir, args.fraction, args.width, args.height, args.generated_frames,
                               args.workers, args.upscale)
    distinct, held_out = distinct_truths(capture, args.workers)
    print(f"distinct held-out ground-truth images: {distinct} of {held_out}", flush=True)
    torch_home = args.workdir / "torch_home"
    stand_in_weights(torch_home)
    env = {**os.environ, "TORCH_HOME": str(torch_home), "PYTHONPATH": os.pathsep.join(
        [str(args.code.resolve()) if args.code else str(Path(__file__).resolve().parents[1]),
         *filter(None, [os.environ.get("PYTHONPATH")])])}
    evaluate = {key: value for key, value in (("render_codec", args.codec), ("encode_workers", args.encode_workers),
                                              ("batch_size", args.batch_size),
                                              ("lpips_precision", args.lpips_precision),
                                              ("fid_precision", args.fid_precision),
                                              ("channels_last", args.channels_last or None),
                                              ("lpips_window", args.lpips_window or None)) if value is not None}
    preset = write_preset(args.workdir, args.preset, args.iterations, args.device, evaluate)
    variant = args.workdir / f"{capture.name}_{args.preset}_{args.iterations}" / "pig"
    if not (variant / "avatar.pt").is_file():
        fitted = run_stage("pig.stages.fit", ["--capture", str(capture), "--output", str(variant), "--preset",
                                              str(preset), "--device", args.device], env, args.workdir / "peak.json")
        print(f"fit ({args.iterations} iterations): {fitted['wall_s']:.1f} s", flush=True)
    results = variant.parent / (args.tag or ("other" if args.code else "new"))
    shutil.rmtree(results, ignore_errors=True)
    split = json.loads((capture / "split.json").read_text())
    rows = []
    for name in args.splits:
        views = len(split[name]["cameras"]) * len(split[name]["frames"])
        renders = results / "renders" / name
        row = run_stage("pig.stages.render", ["--checkpoint", str(variant / "avatar.pt"), "--capture", str(capture),
                                              "--split", name, "--output", str(renders), "--preset", str(preset)],
                        env, args.workdir / "peak.json")
        levels = sorted(int(p.name[3:]) for p in renders.glob("lod*"))
        rows.append({"stage": "render", "split": name, "views": views * len(levels), **row,
                     "bytes": folder_bytes(renders)})
        for group in ([[level] for level in levels] if args.evaluate_per_lod else [levels]):
            lods = [arg for level in group for arg in ("--lod", str(level))] if args.evaluate_per_lod else []
            row = run_stage("pig.stages.evaluate", ["--capture", str(capture), "--renders", str(renders), "--split",
                                                    name, *lods, "--output", str(results / "metrics"),
                                                    "--preset", str(preset)], env, args.workdir / "peak.json")
            summaries = [json.loads((results / "metrics" / f"{name}_lod{level}.json").read_text()) for level in group]
            record = results / "metrics" / f"{name}.json"  # the pass's record (absent from older code)
            waits = json.loads(record.read_text()) if record.is_file() and not args.evaluate_per_lod else {}
            rows.append({"stage": "evaluate " + (f"lod{group[0]}" if args.evaluate_per_lod else "all"), "split": name,
                         "views": views * len(group), **row,
                         "bytes": sum((results / "metrics" / f"{name}_lod{level}{ext}").stat().st_size
                                      for level in group for ext in (".csv", ".json"))
                                  + (record.stat().st_size if waits else 0),
                         "psnr": [s["psnr"] for s in summaries], "lpips": [s["lpips"] for s in summaries],
                         "fid": [s["fid"] for s in summaries], "decode_wait_s": waits.get("decode_wait_s"),
                         "device_wait_s": waits.get("device_wait_s")})
    print(f"\ncapture {capture.name}: {args.width} x {args.height}, code {env['PYTHONPATH'].split(os.pathsep)[0]}, "
          f"device {args.device}, preset {args.preset}")
    print_stage_table(rows)
    for row in rows:
        if row.get("decode_wait_s") is not None:
            print(f"{row['stage']} {row['split']}: waited {row['decode_wait_s']:.1f} s for decoding, "
                  f"{row['device_wait_s']:.1f} s for the device, of {row['wall_s']:.1f} s")
        if "psnr" in row:
            print(f"{row['stage']} {row['split']}: PSNR {', '.join(f'{v:.2f}' for v in row['psnr'])}; LPIPS "
                  f"{', '.join(f'{v:.4f}' for v in row['lpips'])}; FID {', '.join(f'{v:.3f}' for v in row['fid'])}")
    print(f"capture images (ground truth and training): {folder_bytes(capture / 'images')} bytes")
    codecs = codec_table(results / "renders" / "novel_pose", args.codec_sample) if args.codec_sample else []
    parts = []
    if args.breakdown_batches:
        os.environ["TORCH_HOME"] = str(torch_home)  # the stand-in weights
        parts = breakdown(capture, results / "renders" / "novel_pose", preset, args.device, args.breakdown_batches)
    render_parts = []
    if args.render_breakdown:
        render_parts, _ = render_breakdown(capture, variant / "avatar.pt", preset, "novel_pose", args.render_breakdown,
                                           results)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "codecs": codecs, "breakdown": parts,
                                         "render_breakdown": render_parts,
                                         "args": {k: str(v) for k, v in vars(args).items()}}, indent=1))
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 3 and sys.argv[1] == "--stage":
        raise SystemExit(stage_child(sys.argv[2], sys.argv[3], sys.argv[4:]))
    raise SystemExit(main())
