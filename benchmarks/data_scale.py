"""Memory and data wait of the fit as the capture grows: peak host RSS, peak GPU memory, data-wait ms per iteration.

Builds synthetic captures of C cameras x {50, 500, 2500} frames (`--frames`): the first is generated and
preprocessed (its preprocess throughput is printed), the longer ones repeat its preprocessed frames under
new frame ids (hard links, the SMPL-X rows tiled), so every (camera, frame) is a distinct file the fit must
read; only the disk's page cache sees repeats, which is not the process's memory. Each capture then gets
a fit of `--iterations` iterations with the given preset (default: `paper` on CUDA, i.e. 100k anchors,
4 views x 5 timesteps, 5 x 512 decoders) in a fresh process, which reports its own peaks.

    python benchmarks/data_scale.py --workdir /tmp/scale                          # CUDA: paper preset
    python benchmarks/data_scale.py --workdir /tmp/scale --preset cpu-demo --device cpu --iterations 5
    python benchmarks/data_scale.py --workdir /tmp/scale --paper-resolution      # + data wait at 1330 x 1150

`--paper-resolution` adds one run on a 1330 x 1150 capture (`--paper-frames` generated, tiled to
`--paper-tiled` frames) whose train log gives the data wait per iteration and its share of the iteration.
`--upscale S` generates every frame of it instead of tiling (`--paper-frames` is then ignored): the generator
ray-casts at 1/S of the size (S must divide 1330 and 1150, e.g. 5: 266 x 230) and preprocess resizes to full size,
so no two frames share pixels, at ~1/S^2 of the full-size generator's cost (`build_capture`; benchmarks/eval_scale.py
uses it for the protocol's distinct ground truth).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from pig.body.params import SmplxParams
from pig.config import derive_preset
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.stages.preprocess import main as preprocess


def build_capture(workdir: Path, cameras: int, frames: int, width: int, height: int, workers: int,
                  upscale: int = 1) -> tuple[Path, dict]:
    """Generate and preprocess a capture of `width` x `height` views; returns its folder and the preprocess
    throughput. With `upscale` s > 1 the generator ray-casts s x s times fewer pixels (`width` / s x `height` / s,
    which s must divide) and preprocess resizes them to full size (bilinear, masks thresholded, K scaled): every frame
    is its own pose's image (30 frames a second of motion), distinct from all others, at ~1/s^2 of the generator's
    cost (smoother than a full-size render, so its PNGs are smaller)."""
    if width % upscale or height % upscale:
        raise SystemExit(f"--upscale {upscale} must divide the size {width} x {height}")
    tag = f"{cameras}x{frames}_{width}" + (f"_up{upscale}" if upscale > 1 else "")
    raw, capture = workdir / f"raw_{tag}", workdir / f"capture_{tag}"
    if not (capture / "report.json").is_file():
        # Upscaled captures stand for THuman4's: 30 frames a second of motion, so neighbouring frames differ.
        timing = {"duration_s": frames / 30} if upscale > 1 else {}
        cfg = SyntheticConfig(cameras=cameras, frames=frames, width=width // upscale, height=height // upscale,
                              workers=workers, **timing)
        start = time.perf_counter()
        generate_capture(raw, cfg, overwrite=True, progress=False)
        print(f"generate {cameras} x {frames} at {cfg.width} x {cfg.height}: {time.perf_counter() - start:.1f} s",
              flush=True)
        profile = workdir / f"preprocess_{upscale}.yaml"
        profile.write_text(yaml.safe_dump({"preprocess": {"workers": workers, "scale": upscale}}))
        if preprocess(["--input", str(raw), "--output", str(capture), "--preset", str(profile), "--dataset", "synthetic",
                       "--no-progress", "--overwrite"]) != 0:
            raise SystemExit("preprocess failed")
    report = json.loads((capture / "report.json").read_text())
    images = report["images"]
    return capture, {"images": images, "seconds_images": report["seconds_images"],
                     "images_per_s": images / report["seconds_images"]}


def tile_capture(source: Path, target: Path, frames: int) -> Path:
    """A capture of `frames` frames whose frame f is the source's frame f mod n (hard links), split alike."""
    if (target / "report.json").is_file():
        return target
    shutil.rmtree(target, ignore_errors=True)
    params, ids = SmplxParams.load(source / "smplx.npz")
    ids = [int(f) for f in ids]
    rows = [i % len(ids) for i in range(frames)]
    for kind in ("images", "masks"):
        for cam_dir in sorted((source / kind).iterdir()):
            out = target / kind / cam_dir.name
            out.mkdir(parents=True)
            files = {int(p.name.split(".")[0]): p for p in cam_dir.iterdir() if p.name.split(".")[0].isdigit()}
            for new, row in enumerate(rows):
                if ids[row] in files:
                    old = files[ids[row]]
                    os.link(old, out / f"{new:08d}{''.join(old.suffixes)}")
    params.select(rows).save(target / "smplx.npz", frame_ids=list(range(frames)))
    split = json.loads((source / "split.json").read_text())
    for part in split.values():
        members = set(int(f) for f in part["frames"])
        part["frames"] = [new for new, row in enumerate(rows) if ids[row] in members]
    (target / "split.json").write_text(json.dumps(split))
    for name in ("cameras.json", "body_model.npz", "report.json"):
        shutil.copyfile(source / name, target / name)
    return target


def fit_profile(workdir: Path, profile: str, iterations: int, tag: str) -> Path:
    # No held-out evaluation or checkpoint inside the measured iterations.
    return derive_preset(workdir / f"profile_{tag}.yaml", profile,
                         fit={"iterations": iterations, "eval_every": 10**9, "checkpoint_minutes": 10**6})


def measure_fit(capture: Path, profile: Path, device: str, out: Path) -> dict:
    """Run the fit in a fresh process (its peak RSS is its own) and return what it reports."""
    shutil.rmtree(out, ignore_errors=True)
    command = [sys.executable, __file__, "--child", str(capture), str(profile), device, str(out)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"fit on {capture} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def child(capture: str, profile: str, device: str, out: str) -> None:
    import pandas as pd
    import torch

    from pig.avatar.training import fit

    fit(Path(capture), Path(out), profile, device=device)
    log = pd.read_csv(Path(out) / "train_log.csv")
    steps = log[log["iteration"] > 0]
    wall = steps["wall_s"].diff().dropna() * 1000  # ms per iteration, first one (warm-up) dropped
    waits = steps["data_wait_ms"].iloc[1:]
    result = {
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "peak_gpu_mib": torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else float("nan"),
        "ms_per_iteration": float(wall.median()),
        "data_wait_ms_median": float(waits.median()),
        "data_wait_ms_mean": float(waits.mean()),
        "data_wait_share": float(waits.sum() / wall.sum()),
        "iterations": int(steps["iteration"].max()),
    }
    print(json.dumps(result))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, required=True)
    parser.add_argument("--preset", default="paper", help="fit preset (name or YAML); iterations are cut")
    parser.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    parser.add_argument("--cameras", type=int, default=24)
    parser.add_argument("--frames", type=int, nargs="+", default=[50, 500, 2500])
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=112)
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="generate/preprocess processes")
    parser.add_argument("--paper-resolution", action="store_true", help="add the 1330 x 1150 data-wait run")
    parser.add_argument("--paper-frames", type=int, default=4, help="frames generated at 1330 x 1150")
    parser.add_argument("--paper-tiled", type=int, default=2000, help="frames of the tiled 1330 x 1150 capture")
    parser.add_argument("--paper-iterations", type=int, default=100)
    parser.add_argument("--upscale", type=int, default=1,
                        help="generate every 1330 x 1150 frame at 1/S of the size and upscale it (distinct frames)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)

    base, throughput = build_capture(args.workdir, args.cameras, min(args.frames), args.width, args.height, args.workers)
    print(f"preprocess: {throughput['images']} images at {args.width} x {args.height} in "
          f"{throughput['seconds_images']:.2f} s = {throughput['images_per_s']:.0f} images/s "
          f"({args.workers} workers)", flush=True)
    rows = []
    profile = fit_profile(args.workdir, args.preset, args.iterations, "scale")
    for frames in sorted(args.frames):
        capture = base if frames == min(args.frames) else tile_capture(base, args.workdir / f"tiled_{frames}", frames)
        result = measure_fit(capture, profile, args.device, args.workdir / f"fit_{frames}")
        rows.append({"capture": f"{args.cameras} x {frames} at {args.width} x {args.height}", **result})
        print(json.dumps(rows[-1]), flush=True)
    if args.paper_resolution:
        generated = args.paper_tiled if args.upscale > 1 else args.paper_frames
        paper, rate = build_capture(args.workdir, args.cameras, generated, 1330, 1150, args.workers, args.upscale)
        print(f"preprocess at 1330 x 1150: {rate['images_per_s']:.1f} images/s ({args.workers} workers)", flush=True)
        tiled = paper if args.upscale > 1 else tile_capture(paper, args.workdir / f"paper_tiled_{args.paper_tiled}",
                                                            args.paper_tiled)
        profile = fit_profile(args.workdir, args.preset, args.paper_iterations, "paper_resolution")
        result = measure_fit(tiled, profile, args.device, args.workdir / "fit_paper_resolution")
        made = f"all generated at 1/{args.upscale}" if args.upscale > 1 else f"{args.paper_frames} generated"
        rows.append({"capture": f"{args.cameras} x {args.paper_tiled} at 1330 x 1150 ({made})", **result})
        print(json.dumps(rows[-1]), flush=True)

    print(f"\n{'capture':<40} {'peak RSS MiB':>12} {'peak GPU MiB':>12} {'ms/it':>8} {'wait ms':>8} {'wait %':>7}")
    for row in rows:
        print(f"{row['capture']:<40} {row['peak_rss_mib']:>12.0f} {row['peak_gpu_mib']:>12.0f} "
              f"{row['ms_per_iteration']:>8.1f} {row['data_wait_ms_median']:>8.2f} {100 * row['data_wait_share']:>6.2f}%")
    first, last = rows[0], rows[len(args.frames) - 1]
    print(f"\nlargest / smallest capture: RSS {last['peak_rss_mib'] / first['peak_rss_mib']:.3f}, "
          f"GPU {last['peak_gpu_mib'] / first['peak_gpu_mib']:.3f}")
    if args.json:
        args.json.write_text(json.dumps({"throughput": throughput, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(*sys.argv[2:6])
    else:
        raise SystemExit(main())
