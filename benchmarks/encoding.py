"""On-disk encodings of preprocessed images and masks: bytes, decode time and fidelity at THuman4's 1330 x 1150.

    python benchmarks/encoding.py [--raw DIR] [--views 12] [--noise 2.0]

Generates a small synthetic capture at 1330 x 1150 into a temporary folder unless --raw names one (a THuman4-
layout subject), rectifies its views as the preprocess stage does (uint8) and, as the reference, in float32
from the same raw pixels, then encodes the uint8 result with each candidate and prints, per candidate: bytes
per image, single-thread decode and encode milliseconds, and the PSNR of the decoded image against the float
reference inside the mask. A second table repeats it with Gaussian noise of --noise levels added to the raw
pixels (sensor noise, which real photos carry and the rendered subject does not). Then masks, the size of a
full THuman4 subject (24 cameras x 2500 frames) under each storage plan, and the decode rate on threads.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from pig.config import load_preset, load_section, load_yaml
from pig.data.capture import Capture
from pig.data.formats import open_capture
from pig.data.rectify import Rectifier
from pig.data.splits import SplitConfig
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.stages.preprocess import PreprocessConfig, preprocess_capture

REPO = Path(__file__).resolve().parent.parent

JPEG_444 = [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
# name -> (extension, imwrite parameters)
IMAGE_CANDIDATES = {
    "png level 1": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1]),
    "png level 3": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 3]),
    "png level 6": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 6]),
    "webp lossless": (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]),
    "jpeg q90 4:4:4": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90, *JPEG_444]),
    "jpeg q95 4:4:4": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95, *JPEG_444]),
    "jpeg q98 4:4:4": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 98, *JPEG_444]),
    "jpeg q95 4:2:0": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]),
    "webp q90": (".webp", [cv2.IMWRITE_WEBP_QUALITY, 90]),
    "webp q98": (".webp", [cv2.IMWRITE_WEBP_QUALITY, 98]),
    "avif q90": (".avif", [cv2.IMWRITE_AVIF_QUALITY, 90, cv2.IMWRITE_AVIF_SPEED, 8]),
    "jpeg2000 lossless": (".jp2", []),
}
MASK_CANDIDATES = {
    "png 8-bit level 1": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1]),
    "png 8-bit level 6": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 6]),
    "png 1-bit level 1": (".png", [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 1]),
    "png 1-bit level 6": (".png", [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 6]),
}
# A full THuman4 subject (FORMATS.md): train = cams 0..22 x frames 0..1999, novel view = cam 23 x 0..1999,
# novel pose = all 24 cams x 2000..2499.
THUMAN4_VIEWS = {"train": 23 * 2000, "novel_view": 1 * 2000, "novel_pose": 24 * 500}
BUDGET_GB = 25.0


def rectified_views(raw_root: Path, count: int, noise: float, seed: int = 0):
    """Up to `count` views spread over cameras and frames: (uint8 preprocess output, float32 reference, mask)."""
    raw = open_capture("thuman4", raw_root)
    rng = np.random.default_rng(seed)
    pairs = [(c, f) for f in raw.frames for c in raw.cameras if raw.has_frame(c, f)]
    pairs = [pairs[i] for i in np.unique(np.linspace(0, len(pairs) - 1, count).round().astype(int))]
    background = np.zeros(3, np.uint8)
    for cam, frame in pairs:
        camera = raw.cameras[cam]
        rectify = Rectifier(camera, camera.width, camera.height)
        image = raw.read_image(cam, frame)
        if noise > 0:
            image = np.clip(np.round(image + rng.normal(0, noise, image.shape)), 0, 255).astype(np.uint8)
        matte = raw.read_mask(cam, frame)
        out, mask = rectify(image, matte, background)
        reference = image.astype(np.float32)
        if rectify._maps is not None:  # the stage's undistortion, in float: no fixed-point interpolation, no rounding
            reference = cv2.remap(reference, *rectify._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        reference[~mask] = 0
        yield cv2.cvtColor(out, cv2.COLOR_RGB2BGR), cv2.cvtColor(reference, cv2.COLOR_RGB2BGR), mask


def best_ms(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1000 * min(times)


def measure(views, candidates: dict, repeats: int, flags: int, is_mask: bool = False) -> dict[str, dict]:
    """name -> mean bytes, decode ms, encode ms and PSNR in the mask (pooled MSE) over `views`."""
    results = {}
    for name, (ext, params) in candidates.items():
        sizes, decode, encode, squared, pixels, exact = [], [], [], 0.0, 0, True
        for image, reference, mask in views:
            data = (mask.astype(np.uint8) * 255) if is_mask else image
            ok, encoded = cv2.imencode(ext, data, params)
            assert ok, name
            encode.append(best_ms(lambda: cv2.imencode(ext, data, params), repeats))
            decoded = cv2.imdecode(encoded, flags)
            decode.append(best_ms(lambda: cv2.imdecode(encoded, flags), repeats))
            sizes.append(encoded.size)
            if is_mask:
                exact &= bool(np.array_equal(decoded > 127, mask))
            else:
                error = decoded[mask].astype(np.float64) - reference[mask]
                squared += float(np.sum(error**2))
                pixels += error.size
        psnr = 10 * np.log10(255.0**2 / (squared / pixels)) if pixels else float("nan")
        results[name] = {"ext": ext, "bytes": float(np.mean(sizes)), "decode_ms": float(np.mean(decode)),
                         "encode_ms": float(np.mean(encode)), "psnr": psnr, "exact": exact}
    return results


def print_images(title: str, results: dict[str, dict]) -> None:
    print(f"\n{title}")
    print(f"| {'encoding':<18} | {'KB/image':>8} | {'decode ms':>9} | {'encode ms':>9} | {'PSNR dB (mask)':>14} |")
    print(f"|{'-' * 20}|{'-' * 10}|{'-' * 11}|{'-' * 11}|{'-' * 16}|")
    for name, r in results.items():
        print(f"| {name:<18} | {r['bytes'] / 1e3:>8.1f} | {r['decode_ms']:>9.2f} | {r['encode_ms']:>9.1f} | "
              f"{r['psnr']:>14.2f} |")


def decode_rate(encoded_views: list[tuple[np.ndarray, np.ndarray]], threads: int, seconds: float = 2.0) -> float:
    """Views (image + mask) decoded per second by `threads` threads, each decoding the list round robin."""
    def work(offset: int) -> int:
        done, end = 0, time.perf_counter() + seconds
        while time.perf_counter() < end:
            image, mask = encoded_views[(offset + done) % len(encoded_views)]
            cv2.imdecode(image, cv2.IMREAD_COLOR)
            cv2.imdecode(mask, cv2.IMREAD_GRAYSCALE)
            done += 1
        return done

    start = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        total = sum(pool.map(work, range(threads)))
    return total / (time.perf_counter() - start)


def capture_read_rates(raw_root: Path, out: Path, threads: list[int], seconds: float = 2.0) -> dict[int, float]:
    """Training views (JPEG image + 1-bit PNG mask, as the paper preset writes them) read per second through
    `Capture` with its cache off (file read, completeness check, decode, background restored), on `threads`."""
    profile = load_preset("paper")
    cfg = load_section(profile, "preprocess", PreprocessConfig)
    split = load_section(load_yaml(REPO / "config" / "datasets" / "synthetic.yaml"), "split", SplitConfig)
    preprocess_capture(open_capture("thuman4", raw_root), out, cfg, raw_root / "body_model.npz", split, "subject00",
                       progress=False)
    capture = Capture.load(out, cache_mb=0)
    views = capture.views("train")

    def work(offset: int) -> int:
        done, end = 0, time.perf_counter() + seconds
        while time.perf_counter() < end:
            camera, frame = views[(offset + done) % len(views)]
            capture._read("images", camera, frame)
            capture.mask(camera, frame)
            done += 1
        return done

    rates = {}
    for count in threads:
        start = time.perf_counter()
        with ThreadPoolExecutor(count) as pool:
            total = sum(pool.map(work, range(count)))
        rates[count] = total / (time.perf_counter() - start)
    return rates


def per_thread(rates: dict[int, float]) -> str:
    fewest = min(rates)
    return (", ".join(f"{t} thread(s) {r:6.0f}/s" for t, r in rates.items())
            + f"; 12 threads at {fewest} thread(s)' rate per thread: {12 * rates[fewest] / fewest:6.0f}/s")


def plan_gb(per_view: dict[str, float]) -> float:
    """Bytes of a full THuman4 subject with the per-split bytes per view (image + mask)."""
    return sum(THUMAN4_VIEWS[split] * per_view[split] for split in THUMAN4_VIEWS) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--raw", type=Path, default=None, help="raw THuman4-layout subject at 1330x1150")
    parser.add_argument("--views", type=int, default=12, help="views measured, spread over cameras and frames")
    parser.add_argument("--noise", type=float, default=2.0, help="sensor-noise std (levels of 255) of the 2nd table")
    parser.add_argument("--repeats", type=int, default=3, help="timings: best of this many")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="decode-rate thread counts")
    args = parser.parse_args()
    cv2.setNumThreads(1)  # single-thread codec timings; the stages parallelise over images instead
    with tempfile.TemporaryDirectory() as tmp:
        raw_root = args.raw
        if raw_root is None:
            cfg = SyntheticConfig(cameras=4, frames=3, width=1330, height=1150, workers=1)
            start = time.perf_counter()
            raw_root = generate_capture(Path(tmp) / "subject00", cfg, progress=False)
            print(f"generated {cfg.cameras} cameras x {cfg.frames} frames at 1330x1150 in "
                  f"{time.perf_counter() - start:.0f} s")
        clean = list(rectified_views(raw_root, args.views, 0.0))
        noisy = list(rectified_views(raw_root, args.views, args.noise))
        capture_rates = capture_read_rates(raw_root, Path(tmp) / "capture", args.threads)
    height, width = clean[0][0].shape[:2]
    coverage = np.mean([mask.mean() for _, _, mask in clean])
    print(f"{len(clean)} views of {width}x{height}, foreground {100 * coverage:.1f} % of the pixels; "
          f"cv2 {cv2.__version__}, 1 OpenCV thread, best of {args.repeats}")
    images = measure(clean, IMAGE_CANDIDATES, args.repeats, cv2.IMREAD_COLOR)
    print_images("Images, rendered subject (PSNR against the float rectification, inside the mask)", images)
    noisy_images = measure(noisy, IMAGE_CANDIDATES, args.repeats, cv2.IMREAD_COLOR)
    print_images(f"Images with sensor noise (std {args.noise} levels added to the raw pixels)", noisy_images)

    masks = measure(clean, MASK_CANDIDATES, args.repeats, cv2.IMREAD_GRAYSCALE, is_mask=True)
    print("\nMasks")
    print(f"| {'encoding':<18} | {'KB/mask':>8} | {'decode ms':>9} | {'encode ms':>9} | exact |")
    print(f"|{'-' * 20}|{'-' * 10}|{'-' * 11}|{'-' * 11}|-------|")
    for name, r in masks.items():
        print(f"| {name:<18} | {r['bytes'] / 1e3:>8.1f} | {r['decode_ms']:>9.2f} | {r['encode_ms']:>9.1f} | "
              f"{'yes' if r['exact'] else 'NO':>5} |")
    packed = [np.packbits(mask) for _, _, mask in clean]
    unpack = np.mean([best_ms(lambda: np.unpackbits(bits, count=mask.size).reshape(mask.shape), args.repeats)
                      for bits, (_, _, mask) in zip(packed, clean)])
    pack = np.mean([best_ms(lambda: np.packbits(mask), args.repeats) for _, _, mask in clean])
    print(f"| {'np.packbits, raw':<18} | {packed[0].size / 1e3:>8.1f} | {unpack:>9.2f} | {pack:>9.1f} | {'yes':>5} |")

    mask_bytes = masks["png 1-bit level 1"]["bytes"]
    print(f"\nFull THuman4 subject, {sum(THUMAN4_VIEWS.values())} views ({THUMAN4_VIEWS}), masks as png 1-bit "
          f"level 1 (as the stage writes them), budget {BUDGET_GB:.0f} GB; clean / noisy")
    plans = {
        "all png level 1": ("png level 1", "png level 1"),
        "all png level 6": ("png level 6", "png level 6"),
        "all webp lossless": ("webp lossless", "webp lossless"),
        "train jpeg q95, held-out png level 1": ("jpeg q95 4:4:4", "png level 1"),
        "train jpeg q95, held-out png level 6": ("jpeg q95 4:4:4", "png level 6"),
        "train jpeg q98, held-out png level 6": ("jpeg q98 4:4:4", "png level 6"),
        "all jpeg q95": ("jpeg q95 4:4:4", "jpeg q95 4:4:4"),
    }
    for plan, (train, held_out) in plans.items():
        sizes = []
        for table in (images, noisy_images):
            per_view = {"train": table[train]["bytes"] + mask_bytes}
            per_view["novel_view"] = per_view["novel_pose"] = table[held_out]["bytes"] + mask_bytes
            sizes.append(plan_gb(per_view))
        verdict = "fits" if max(sizes) <= BUDGET_GB else "too large"
        print(f"  {plan:<40} {sizes[0]:6.1f} GB / {sizes[1]:6.1f} GB  {verdict}")

    print("\nDecode rate, views (image + mask png 1-bit) per second on threads (this machine's "
          f"{len(os.sched_getaffinity(0))} cores)")
    for name in ("jpeg q95 4:4:4", "png level 1", "png level 6"):
        ext, params = IMAGE_CANDIDATES[name]
        mask_ext, mask_params = MASK_CANDIDATES["png 1-bit level 1"]
        encoded = [(cv2.imencode(ext, image, params)[1], cv2.imencode(mask_ext, mask.astype(np.uint8) * 255,
                                                                       mask_params)[1]) for image, _, mask in noisy]
        rates = {threads: decode_rate(encoded, threads) for threads in args.threads}
        print(f"  {name:<16} " + per_thread(rates))
    print("  through Capture (JPEG training view + mask, cache off, background restored): " + per_thread(capture_rates))


if __name__ == "__main__":
    main()
