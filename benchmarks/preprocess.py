"""Preprocess stage time on the default (cpu-demo) synthetic capture: thread-pool sizes and output scales; with
--full-size, throughput at THuman4's 1330 x 1150 and an estimate for a full THuman4 subject.

    python benchmarks/preprocess.py [--raw DIR] [--preset cpu-demo]
    python benchmarks/preprocess.py --full-size [--raw-full DIR] [--workers 1 2] [--cores 16]

Generates the synthetic captures into a temporary folder unless --raw / --raw-full name them, then runs the
stage several times in this process and prints tables (images phase, projection check, total). --full-size
also times each step of one image on one thread (decode, undistort, composite, encode, write), profiles the
stage's worker thread for the share of its time Python holds the GIL (the bound on thread scaling), and
estimates 24 cameras x 2500 frames (46000 JPEG training views, 14000 PNG held-out views) on --cores cores.
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from pig.config import load_preset, load_section, load_yaml
from pig.data.formats import open_capture
from pig.data.rectify import MASK_THRESHOLD, Rectifier, composite
from pig.data.splits import SplitConfig
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig._io import atomic_path
from pig.stages.preprocess import PreprocessConfig, _encoders, preprocess_capture

REPO = Path(__file__).resolve().parent.parent
THUMAN4_VIEWS = {"train": 46000, "held_out": 14000}  # 23 x 2000 training, 1 x 2000 + 24 x 500 held out


def step_times(raw, cfg: PreprocessConfig, out: Path, views: int = 6, repeats: int = 3) -> dict[str, float]:
    """Milliseconds per image of each step on one thread (best of `repeats`, mean over `views` training views)."""
    encoders = _encoders(cfg)
    background = np.zeros(3, np.uint8)
    pairs = [(c, f) for c in raw.cameras for f in raw.frames][:views]
    times: dict[str, list[float]] = {}

    def timed(name, function):
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            result = function()
            best = min(best, time.perf_counter() - start)
        times.setdefault(name, []).append(1000 * best)
        return result

    cv2.setNumThreads(1)
    for cam, frame in pairs:
        camera = raw.cameras[cam]
        rectify = Rectifier(camera, camera.width, camera.height)
        image = timed("decode raw image", lambda: raw.read_image(cam, frame))
        matte = timed("decode raw mask", lambda: raw.read_mask(cam, frame))
        image, matte = timed("undistort (remap) image + mask", lambda: (
            cv2.remap(image, *rectify._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
            cv2.remap(matte, *rectify._maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)))
        mask = timed("threshold + composite", lambda: matte > MASK_THRESHOLD)
        image = timed("threshold + composite", lambda: composite(image, mask, background))
        bgr = timed("RGB -> BGR", lambda: cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        data = {kind: timed(f"encode {kind}", lambda kind=kind: cv2.imencode(encoders[kind][0], bgr if kind != "mask"
                                                                              else mask.astype(np.uint8) * 255,
                                                                              encoders[kind][1])[1])
                for kind in ("jpeg", "png", "mask")}

        def write(kind):
            with atomic_path(out / f"{cam}_{frame}_{kind}{encoders[kind][0]}") as tmp, open(tmp, "wb") as handle:
                handle.write(data[kind])
        for kind in ("jpeg", "mask"):
            timed("write files (atomic)", lambda kind=kind: write(kind))
    steps = {name: float(np.sum(values)) / len(pairs) for name, values in times.items()}
    return steps


def full_size(raw_root: Path, tmp: Path, workers: list[int], cores: int) -> None:
    dataset = load_yaml(REPO / "config" / "datasets" / "synthetic.yaml")
    split_cfg = load_section(dataset, "split", SplitConfig)
    raw = open_capture("thuman4", raw_root)
    base = load_section(load_preset("paper"), "preprocess", PreprocessConfig)
    rows = []
    for count in workers:
        cfg = PreprocessConfig(**{**base.__dict__, "workers": count})
        report = preprocess_capture(raw, tmp / f"full_{count}", cfg, raw_root / "body_model.npz", split_cfg,
                                    "subject00", progress=False)
        rows.append((count, report["images"], report["seconds_images"], report["megabytes"]))
    print(f"\n1330x1150 views, paper preset (train JPEG q{base.jpeg_quality} 4:4:4, held out PNG level "
          f"{base.png_compression}, masks 1-bit PNG), {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f}")
    print(f"| {'workers':>7} | {'images':>6} | {'images_s':>8} | {'img/s':>6} | {'MB images':>9} | {'MB masks':>8} |")
    print(f"|{'-' * 9}|{'-' * 8}|{'-' * 10}|{'-' * 8}|{'-' * 11}|{'-' * 10}|")
    for count, images, seconds, megabytes in rows:
        print(f"| {count:>7} | {images:>6} | {seconds:>8.2f} | {images / seconds:>6.2f} | "
              f"{megabytes['images']:>9.1f} | {megabytes['masks']:>8.2f} |")

    steps = step_times(raw, base, tmp)
    print("\nOne image on one thread, milliseconds (best of 3, mean over 6 views):")
    for name, ms in steps.items():
        print(f"  {name:<32} {ms:7.2f}")
    shared = sum(ms for name, ms in steps.items() if not name.startswith("encode"))
    train = shared + steps["encode jpeg"] + steps["encode mask"]
    held_out = shared + steps["encode png"] + steps["encode mask"]
    print(f"  sum, training view (JPEG)        {train:7.2f}")
    print(f"  sum, held-out view (PNG)         {held_out:7.2f}")
    if rows[0][0] == 1:
        written = tmp / f"full_{rows[0][0]}" / "images"
        count = {suffix: len(list(written.glob(f"*/*{suffix}"))) for suffix in (".jpg", ".png")}
        stage = 1000 * rows[0][2] / rows[0][1]
        steps_mean = (count[".jpg"] * train + count[".png"] * held_out) / rows[0][1]
        print(f"  stage, 1 worker, per image       {stage:7.2f}  ({count['.jpg']} JPEG + {count['.png']} PNG views; "
              f"the steps' mean {steps_mean:.2f}, so {stage - steps_mean:+.2f} ms outside them)")
    share, seconds = gil_share(raw, base, split_cfg, tmp / "profiled")
    print(f"\nPython holding the GIL (cProfile of the stage's worker thread, {seconds:.1f} s): at most "
          f"{100 * share:.1f} % of the workers' time; the rest is OpenCV, numpy and file I/O, which release it")
    total = THUMAN4_VIEWS["train"] * train + THUMAN4_VIEWS["held_out"] * held_out
    speedup = cores / (1 + (cores - 1) * share)  # Amdahl with the GIL-held share as the serial part
    print(f"24 x 2500 THuman4 subject: {total / 1000:.0f} core-seconds of image work at the per-core speed measured "
          f"here; on {cores} cores {total / 1000 / cores / 60:.1f} min with linear thread scaling, "
          f"{total / 1000 / speedup / 60:.1f} min ({speedup:.1f}x) with the GIL share above serialised")


# Built-in calls that release the GIL while they work (the rest of the worker's time is counted as holding it).
RELEASING = ("<imdecode>", "<imencode>", "<remap>", "<cvtColor>", "<copyTo>", "<merge>", "<resize>",
             "<method 'read' of '_io.BufferedReader' objects>", "<method 'write' of '_io.BufferedWriter' objects>",
             "<built-in method io.open>", "<built-in method posix.replace>", "<built-in method posix.unlink>",
             "<method 'astype' of 'numpy.ndarray' objects>", "<built-in method numpy.full>")
WAITING = ("<method 'acquire' of '_thread.lock' objects>", "<method 'get' of '_queue.SimpleQueue' objects>")


def gil_share(raw, cfg: PreprocessConfig, split_cfg: SplitConfig, out: Path) -> tuple[float, float]:
    """Upper bound on the share of a worker thread's busy time spent holding the GIL: everything but the calls in
    RELEASING (numpy operators inside Python functions count as holding it), from a 1-worker run under cProfile."""
    from pig.stages import preprocess

    profilers = []

    def profile_thread():
        profilers.append(cProfile.Profile())
        profilers[-1].enable()

    pool = preprocess.ThreadPoolExecutor
    preprocess.ThreadPoolExecutor = lambda workers: pool(workers, initializer=profile_thread)
    try:
        preprocess_capture(raw, out, replace(cfg, workers=1), raw.source / "body_model.npz", split_cfg, "subject00",
                           progress=False)
    finally:
        preprocess.ThreadPoolExecutor = pool
    held: dict[str, float] = {}
    busy = 0.0
    for profiler in profilers:
        for (file, line, name), (_, _, own, _, _) in pstats.Stats(profiler).stats.items():
            if file == "~" and name in WAITING:
                continue
            busy += own
            if not (file == "~" and name in RELEASING):
                key = name if file == "~" else f"{name} ({Path(file).name}:{line})"
                held[key] = held.get(key, 0.0) + own
    for name, own in sorted(held.items(), key=lambda item: -item[1])[:5]:
        print(f"  holding the GIL: {1000 * own:7.2f} ms in {name}")
    return sum(held.values()) / busy, busy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--raw", type=Path, default=None, help="existing raw synthetic subject folder")
    parser.add_argument("--preset", default="cpu-demo")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--full-size", action="store_true", help="only the 1330x1150 throughput and estimate")
    parser.add_argument("--raw-full", type=Path, default=None, help="existing raw subject at 1330x1150")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="thread counts of --full-size")
    parser.add_argument("--cores", type=int, default=16, help="cores of the estimate (the GPU machine's 16)")
    args = parser.parse_args()
    if args.full_size:
        with tempfile.TemporaryDirectory() as tmp:
            raw_root = args.raw_full
            if raw_root is None:
                cfg = SyntheticConfig(cameras=4, frames=6, width=1330, height=1150, workers=1)
                start = time.perf_counter()
                raw_root = generate_capture(Path(tmp) / "subject00", cfg, progress=False)
                print(f"generated {cfg.cameras} cameras x {cfg.frames} frames at 1330x1150 in "
                      f"{time.perf_counter() - start:.0f} s")
            full_size(raw_root, Path(tmp), args.workers, args.cores)
        return
    profile = load_preset(args.preset)
    dataset = load_yaml(REPO / "config" / "datasets" / "synthetic.yaml")
    split_cfg = load_section(dataset, "split", SplitConfig)
    with tempfile.TemporaryDirectory() as tmp:
        raw_root = args.raw
        if raw_root is None:
            start = time.perf_counter()
            raw_root = generate_capture(Path(tmp) / "subject00", load_section(profile, "synthetic", SyntheticConfig),
                                        progress=False)
            print(f"generated {raw_root} in {time.perf_counter() - start:.1f} s")
        raw = open_capture("thuman4", raw_root)
        base = load_section(profile, "preprocess", PreprocessConfig)
        rows = []
        for workers, scale in ((1, 1.0), (2, 1.0), (2, 0.5)):
            cfg = PreprocessConfig(**{**base.__dict__, "workers": workers, "scale": scale})
            for repeat in range(args.repeats):
                report = preprocess_capture(raw, Path(tmp) / f"out_{workers}_{scale}_{repeat}", cfg,
                                            raw_root / "body_model.npz", split_cfg, "subject00", progress=False)
                rows.append((workers, scale, report["images"], report["seconds_images"], report["seconds_check"],
                             report["seconds"]))
    print(f"{'workers':>7} {'scale':>5} {'images':>6} {'images_s':>8} {'img/s':>6} {'check_s':>7} {'total_s':>7}")
    for workers, scale, images, images_s, check_s, total_s in rows:
        print(f"{workers:>7} {scale:>5} {images:>6} {images_s:>8.2f} {images / images_s:>6.1f} {check_s:>7.2f} "
              f"{total_s:>7.2f}")
    best = {key: min(r[3] for r in rows if r[:2] == key) for key in ((1, 1.0), (2, 1.0))}
    print(f"images phase, 2 workers / 1 worker (best of {args.repeats}): {best[(2, 1.0)] / best[(1, 1.0)]:.2f}")


if __name__ == "__main__":
    main()
