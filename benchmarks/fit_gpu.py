"""GPU benchmark of the fit stage at the paper's sizes: milliseconds per iteration, data wait, peak GPU memory, where the time goes.

Generates a synthetic capture at the paper profile's image size (fewer frames, so it finishes in
minutes), preprocesses it, runs `pig.stages.fit` with the `paper` profile (100k anchors, 4 views x 5
timesteps, 5 x 512 decoders) once per `--variant` on that same capture, in this process, and prints
one table row per variant with its ratio to the first, and the time each iteration waited for its training
views (train_log.csv's data_wait_ms: decoding, staging and the copy to the GPU that prefetching did not hide).
Run on the GPU machine:

    bash .gpu/device-setup.sh && export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text && \
        python3 benchmarks/fit_gpu.py --iterations 60 --profile-phases 10 \
            --variant factorized:precond.knn_solver=factorized --variant cg:precond.knn_solver=cg \
            --variant no_prefetch:fit.prefetch=0

A variant is `NAME:section.key=value,...` (values in YAML) over the profile; the key `torch.tf32`
lets float32 matmuls use TF32 during that fit. After the timed iterations, `--profile-phases N`
runs N more with the device synchronised around each part of an iteration (`fit(phase=...)`) and
around the model's submodules, and prints median ms per part; `--profile-ops N` runs N more under
torch.profiler and prints the operators that take the most device time.
"""
from __future__ import annotations

import argparse
import csv
import gc
import shutil
import statistics
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch
import yaml

from pig.config import load_profile
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.stages._io import write_json
from pig.stages.fit import fit
from pig.stages.preprocess import main as preprocess

# Submodules of the avatar timed inside the "model" phase (the outermost one when they nest).
MODULES = {"LatentGrid": "model.grid", "PreconditionedTensor": "model.anchor_solve", "BodyModel": "model.body",
           "AnchorDecoder": "model.decoders", "BodyRefiner": "model.refiner"}


def parse_variant(text: str) -> tuple[str, dict, bool]:
    """`NAME:section.key=value,...` -> (name, {section: {key: value}}, tf32)."""
    name, _, body = text.partition(":")
    overrides: dict[str, dict] = defaultdict(dict)
    tf32 = False
    for item in filter(None, body.split(",")):
        key, _, value = item.partition("=")
        section, _, field = key.strip().partition(".")
        if section == "torch" and field == "tf32":
            tf32 = bool(yaml.safe_load(value))
        else:
            overrides[section][field] = yaml.safe_load(value)
    return name, dict(overrides), tf32


class PhaseTimer:
    """Wall time of fit phases and avatar submodules with the device synchronised at each boundary, while `active`."""

    def __init__(self):
        self.active = False
        self.depth = 0
        self.iterations: list[dict[str, float]] = []
        self.current: dict[str, float] = defaultdict(float)
        self._starts: list[float] = []
        self._hooks = [torch.nn.modules.module.register_module_forward_pre_hook(self._pre),
                       torch.nn.modules.module.register_module_forward_hook(self._post)]

    @contextmanager
    def __call__(self, name: str):
        if not self.active:
            yield
            return
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        yield
        torch.cuda.synchronize()
        self.current[name] += time.perf_counter() - t0

    def _pre(self, module, args):
        if self.active and type(module).__name__ in MODULES:
            self.depth += 1
            if self.depth == 1:
                torch.cuda.synchronize()
                self._starts.append(time.perf_counter())

    def _post(self, module, args, output):
        if self.active and type(module).__name__ in MODULES:
            if self.depth == 1:
                torch.cuda.synchronize()
                self.current[MODULES[type(module).__name__]] += time.perf_counter() - self._starts.pop()
            self.depth -= 1

    def end_iteration(self) -> None:
        if self.active:
            self.iterations.append(dict(self.current))
        self.current = defaultdict(float)

    def medians_ms(self) -> dict[str, float]:
        names = sorted({k for it in self.iterations for k in it})
        return {k: 1000 * statistics.median(it.get(k, 0.0) for it in self.iterations) for k in names}

    def close(self) -> None:
        for hook in self._hooks:
            hook.remove()


def run_variant(args, name: str, overrides: dict, tf32: bool, profile: dict, capture: Path) -> dict:
    varied = yaml.safe_load(yaml.safe_dump(profile))
    for section, values in overrides.items():
        varied.setdefault(section, {}).update(values)
    total = args.iterations + args.profile_phases + args.profile_ops
    # Same profile, run length cut; no held-out evaluation or checkpoint inside the timing.
    varied["fit"].update(iterations=total, eval_every=10**9, checkpoint_minutes=10**6)
    path = args.workdir / f"profile_{name}.yaml"
    path.write_text(yaml.safe_dump(varied))
    out_dir = args.workdir / f"fit_{name}"
    shutil.rmtree(out_dir, ignore_errors=True)

    times: list[float] = []
    timer = PhaseTimer() if args.profile_phases else None
    ops = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA])
    phase_start = args.iterations
    ops_start = args.iterations + args.profile_phases

    def tick(iteration: int) -> None:
        torch.cuda.synchronize()
        if iteration <= args.iterations:
            times.append(time.perf_counter())
        if timer is not None:
            timer.end_iteration()
            timer.active = phase_start <= iteration < ops_start
        if args.profile_ops and iteration == ops_start:
            ops.start()
        if args.profile_ops and iteration == total:
            ops.stop()

    gc.collect()
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    tf32_before = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = tf32
    t0 = time.perf_counter()
    try:
        fit(capture, out_dir, str(path), device="cuda", on_iteration=tick, **({"phase": timer} if timer else {}))
    finally:
        torch.backends.cuda.matmul.allow_tf32 = tf32_before
        if timer is not None:
            timer.close()
    steps = [b - a for a, b in zip(times[args.warmup:], times[args.warmup + 1:])]
    # The data wait of the same iterations (the first timed step ends iteration warmup + 2).
    with open(out_dir / "train_log.csv", newline="") as file:
        waits = [float(row["data_wait_ms"]) for row in csv.DictReader(file)
                 if args.warmup + 2 <= int(row["iteration"]) <= args.iterations]
    result = {
        "name": name, "overrides": overrides, "tf32": tf32, "iterations_timed": len(steps),
        "ms_median": 1000 * statistics.median(steps), "ms_mean": 1000 * statistics.mean(steps),
        "wait_ms_median": statistics.median(waits), "wait_ms_mean": statistics.mean(waits),
        "wait_share": statistics.mean(waits) / (1000 * statistics.mean(steps)),
        "peak_gib": torch.cuda.max_memory_allocated() / 2**30, "fit_total_s": time.perf_counter() - t0,
        "log": str(out_dir / "train_log.csv"),
    }
    if timer is not None:
        result["phases_ms"] = timer.medians_ms()
    if args.profile_ops:
        table = ops.key_averages().table(sort_by="device_time_total", row_limit=args.op_rows, max_name_column_width=70)
        result["ops_table"] = table
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/pig_fit_bench"))
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--frames", type=int, default=10, help="captured frames (the paper profile has 120)")
    parser.add_argument("--cameras", type=int, default=None, help="captured cameras (default: the profile's)")
    parser.add_argument("--reuse-capture", action="store_true", help="keep an existing capture in --workdir")
    parser.add_argument("--iterations", type=int, default=60, help="timed iterations, warm-up included")
    parser.add_argument("--warmup", type=int, default=5, help="iterations left out of the timing")
    parser.add_argument("--supersample", type=int, default=1)
    parser.add_argument("--variant", action="append", default=[], help="NAME:section.key=value,... (repeatable)")
    parser.add_argument("--profile-phases", type=int, default=0, help="iterations timed per phase after the timed ones")
    parser.add_argument("--profile-ops", type=int, default=0, help="iterations under torch.profiler after those")
    parser.add_argument("--op-rows", type=int, default=30)
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("fit_gpu: no CUDA device", file=sys.stderr)
        return 1
    profile = load_profile(args.profile)
    profile.pop("_path")
    syn_cfg = {**profile.get("synthetic", {}), "frames": args.frames, "supersample": args.supersample}
    if args.cameras is not None:
        syn_cfg["cameras"] = args.cameras
    syn = SyntheticConfig(**syn_cfg)
    capture = args.workdir / "capture"
    stamps = {}
    if not (args.reuse_capture and capture.exists()):
        shutil.rmtree(args.workdir, ignore_errors=True)
        t0 = time.perf_counter()
        raw = generate_capture(args.workdir / "raw", syn, progress=False)
        stamps["generate_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        preprocess(["--input", str(raw), "--output", str(capture), "--profile", args.profile,
                    "--format", "thuman4", "--body-model", str(raw / "body_model.npz"), "--no-progress"])
        stamps["preprocess_s"] = time.perf_counter() - t0

    variants = [parse_variant(v) for v in args.variant] or [("profile", {}, False)]
    results = [run_variant(args, *v, profile, capture) for v in variants]

    header = [
        ("device", torch.cuda.get_device_name()),
        ("anchors / levels", f"{profile['avatar']['num_anchors']} / {profile['avatar']['levels']}"),
        ("views x timesteps", f"{profile['fit']['views']} x {profile['fit']['timesteps']}"),
        ("view cache / loader workers / prefetch",
         " / ".join(str(profile["fit"].get(k, "default")) for k in ("view_cache", "loader_workers", "prefetch"))),
        ("capture", f"{syn.cameras} cameras x {syn.frames} frames, {syn.width} x {syn.height}"),
        *((k, f"{v:.1f}") for k, v in stamps.items()),
    ]
    width = max(len(k) for k, _ in header)
    for key, value in header:
        print(f"{key:<{width}}  {value}")
    base = results[0]["ms_median"]
    print("\n| variant | overrides | ms/it median | mean | vs first | data wait ms median | mean | share | peak GiB | timed |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        over = ", ".join(f"{s}.{k}={v}" for s, kv in r["overrides"].items() for k, v in kv.items()) + (" tf32" if r["tf32"] else "")
        print(f"| {r['name']} | {over or '-'} | {r['ms_median']:.1f} | {r['ms_mean']:.1f} | {r['ms_median'] / base:.3f} "
              f"| {r['wait_ms_median']:.2f} | {r['wait_ms_mean']:.2f} | {100 * r['wait_share']:.1f} % "
              f"| {r['peak_gib']:.2f} | {r['iterations_timed']} |")
    if args.profile_phases:
        names = sorted({k for r in results for k in r["phases_ms"]})
        print(f"\nPer-phase ms (median of {args.profile_phases} synchronised iterations; model.* lie inside model)")
        print("| phase | " + " | ".join(r["name"] for r in results) + " |")
        print("|---|" + "---|" * len(results))
        for n in names:
            print(f"| {n} | " + " | ".join(f"{r['phases_ms'].get(n, 0.0):.1f}" for r in results) + " |")
        top = [n for n in names if not n.startswith("model.")]
        print("| sum of phases | " + " | ".join(f"{sum(r['phases_ms'].get(n, 0.0) for n in top):.1f}" for r in results) + " |")
    for r in results:
        if "ops_table" in r:
            print(f"\nOperators by device time, variant {r['name']} ({args.profile_ops} iterations):\n{r['ops_table']}")
    if args.json is not None:
        write_json(args.json, {"stamps": stamps, "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
