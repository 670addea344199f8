"""GPU benchmark of the fit stage at the paper's sizes: milliseconds per iteration and peak GPU memory.

Generates a synthetic capture at the paper profile's image size (fewer frames, so it finishes in
minutes), preprocesses it, runs N iterations of `pig.stages.fit` with the `paper` profile (100k
anchors, 4 views x 5 timesteps, 5 x 512 decoders) and prints a table. Run on the GPU machine:

    bash .gpu/device-setup.sh && export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text && \
        python3 benchmarks/fit_gpu.py --iterations 60
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import time
from pathlib import Path

import torch
import yaml

from pig.config import load_profile
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.stages.fit import fit
from pig.stages.preprocess import main as preprocess


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/pig_fit_bench"))
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--frames", type=int, default=10, help="captured frames (the paper profile has 120)")
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=5, help="iterations left out of the timing")
    parser.add_argument("--supersample", type=int, default=1)
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("fit_gpu: no CUDA device", file=sys.stderr)
        return 1
    shutil.rmtree(args.workdir, ignore_errors=True)
    profile = load_profile(args.profile)
    profile.pop("_path")
    syn = SyntheticConfig(**{**profile.get("synthetic", {}), "frames": args.frames, "supersample": args.supersample})
    stamps = {}
    t0 = time.perf_counter()
    raw = generate_capture(args.workdir / "raw", syn, progress=False)
    stamps["generate_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    preprocess(["--input", str(raw), "--output", str(args.workdir / "capture"), "--profile", args.profile,
                "--format", "thuman4", "--body-model", str(raw / "body_model.npz"), "--no-progress"])
    stamps["preprocess_s"] = time.perf_counter() - t0
    # Same profile, run length cut to N iterations; no held-out evaluation or checkpoint inside the timing.
    profile["fit"].update(iterations=args.iterations, eval_every=10**9, checkpoint_minutes=10**6)
    bench_profile = args.workdir / "profile.yaml"
    bench_profile.write_text(yaml.safe_dump(profile))

    times: list[float] = []

    def tick(iteration: int) -> None:
        torch.cuda.synchronize()
        times.append(time.perf_counter())

    torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    fit(args.workdir / "capture", args.workdir / "fit", str(bench_profile), device="cuda", on_iteration=tick)
    stamps["fit_total_s"] = time.perf_counter() - t0
    steps = [b - a for a, b in zip(times[args.warmup:], times[args.warmup + 1:])]
    rows = [
        ("device", torch.cuda.get_device_name()),
        ("anchors / levels", f"{profile['avatar']['num_anchors']} / {profile['avatar']['levels']}"),
        ("views x timesteps", f"{profile['fit']['views']} x {profile['fit']['timesteps']}"),
        ("image size", f"{syn.width} x {syn.height}"),
        ("iterations timed", len(steps)),
        ("ms / iteration (median)", f"{1000 * statistics.median(steps):.1f}"),
        ("ms / iteration (mean)", f"{1000 * statistics.mean(steps):.1f}"),
        ("peak GPU memory [GiB]", f"{torch.cuda.max_memory_allocated() / 2**30:.2f}"),
        *((k, f"{v:.1f}") for k, v in stamps.items()),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
