"""GPU benchmark of the fit stage at the paper's sizes: milliseconds per iteration, data wait, peak GPU memory, where the time goes.

Generates a synthetic capture at the paper preset's image size (fewer frames, so it finishes in
minutes), preprocesses it, runs `pig.avatar.training.fit` (the fit stage) with the `paper` preset (100k anchors, 4 views x 5
timesteps, 5 x 512 decoders) once per `--variant` on that same capture, in this process, and prints
one table row per variant with its ratio to the first, and the time each iteration waited for its training
views (train_log.csv's data_wait_ms: decoding, staging and the copy to the GPU that prefetching did not hide).
Run on the GPU machine:

    bash .gpu/device-setup.sh && export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text && \
        python3 benchmarks/fit_gpu.py --iterations 60 --profile-phases 10 \
            --variant factorized:precond.knn_solver=factorized --variant cg:precond.knn_solver=cg \
            --variant no_prefetch:fit.prefetch=0

A variant is `NAME:section.key=value,...` (values in YAML) over the preset, e.g. the speed levers
`fit.precision=bf16`, `fit.compile=true` (pig/avatar/training.py). A NAME among the preset's `variants:`
(`template_bound:`, `no_precond:`, ...) fits that method variant, with any overrides on top. `--warm-compile N`
first runs an untimed N-iteration fit of each variant before it, so that its compilation (cached on disk and in the
process) is done before its timed window.

`--budget B` (fixed-budget mode): each variant fits for B training seconds (`fit.time_budget_s`: wall time less
held-out evaluations, checkpoint writes and compilation, pig.avatar.training_clock; the learning-rate schedule's
progress is the time fraction), then renders and evaluates novel view and novel
pose at every LOD with the render and evaluate stages, and prints their PSNR and SSIM per LOD, and at the finest
LOD the ground-truth metrics (regions, geometry, drift) where the evaluate stage computed them. With a weight
average (fit.average_decay), `--evaluate-iterate` evaluates the fit's last iterate as well (pig.avatar.training
writes it beside the average): one fit gives the variant with and without the average.
`--eval-every N` keeps the fit's held-out evaluations every N iterations and prints the held-out PSNR of every
variant at each of them with its difference to the first variant's (the parity check of two paths);
`--plot PATH` draws those curves. After the timed iterations, `--profile-phases N`
runs N more with the device synchronised around each part of an iteration (`fit(phase=...)`) and
around the model's submodules outside compiled regions (with `fit.compile_posing` the body model runs inside the
compiled posing: no model.body row, its time is in `model`), and prints median ms per part; `--profile-ops N`
runs N more under torch.profiler and prints the operators that take the most device time.
"""
from __future__ import annotations

import argparse
import csv
import gc
import gzip
import math
import re
import shutil
import statistics
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

import torch
import yaml
from torch._dynamo.utils import counters

from pig.config import load_preset
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.data.synthetic.workers import RenderTimeline
from pig._io import write_json
from pig.avatar.training import ITERATE_FILE, fit
from pig.stages.preprocess import main as preprocess
from synthetic_generate import timeline_summary, timeline_table

# Submodules of the avatar timed inside the "model" phase (the outermost one when they nest).
MODULES = {"LatentGrid": "model.grid", "PreconditionedTensor": "model.anchor_solve", "BodyModel": "model.body",
           "AnchorDecoder": "model.decoders", "BodyRefiner": "model.refiner"}


def parse_variant(text: str) -> tuple[str, dict]:
    """`NAME:section.key=value,...` -> (name, {section: {key: value}}); a value may be a YAML list, `[8,16,24]`."""
    name, _, body = text.partition(":")
    overrides: dict[str, dict] = defaultdict(dict)
    for item in filter(None, re.split(r",(?![^\[]*\])", body)):  # no split inside a list's brackets
        key, _, value = item.partition("=")
        section, _, field = key.strip().partition(".")
        overrides[section][field] = yaml.safe_load(value)
    return name, dict(overrides)


def load_compile_cache(path: Path) -> bool:
    """torch.compile's artifacts of an earlier process (same torch, same GPU architecture) into the local caches."""
    if not path.is_file():
        return False
    torch.compiler.load_cache_artifacts(gzip.decompress(path.read_bytes()))
    return True


def save_compile_cache(path: Path) -> None:
    """What this process compiled or loaded so far (torch.compiler.save_cache_artifacts), gzipped."""
    saved = torch.compiler.save_cache_artifacts()
    if saved is not None:
        temporary = path.with_name(path.name + ".partial")
        temporary.write_bytes(gzip.compress(saved[0], compresslevel=6))
        temporary.replace(path)


class PhaseTimer:
    """Wall time of fit phases and avatar submodules with the device synchronised at each boundary, while `active`
    (`synchronize`: the CUDA device's by default; a no-op on the CPU)."""

    def __init__(self, synchronize: Callable[[], None] = torch.cuda.synchronize):
        self.synchronize = synchronize
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
        self.synchronize()
        t0 = time.perf_counter()
        yield
        self.synchronize()
        self.current[name] += time.perf_counter() - t0

    def _timed(self, module) -> bool:
        """Whether `module`'s call is timed. Never inside a compiled region (the compiled posing calls BodyModel):
        traced there, the hooks' clock read (time.perf_counter, a builtin Dynamo cannot trace) broke the graph, and
        `active`, guarded, recompiled every compiled graph when profiling began (benchmarks/NOTES.md, "run29's graph
        break was the step timer's"). Dynamo reads is_compiling() as True while it traces: nothing after it is
        traced or guarded."""
        return not torch.compiler.is_compiling() and self.active and type(module).__name__ in MODULES

    def _pre(self, module, args):
        if self._timed(module):
            self.depth += 1
            if self.depth == 1:
                self.synchronize()
                self._starts.append(time.perf_counter())

    def _post(self, module, args, output):
        if self._timed(module):
            if self.depth == 1:
                self.synchronize()
                self.current[MODULES[type(module).__name__]] += time.perf_counter() - self._starts.pop()
            self.depth -= 1

    def end_iteration(self) -> None:
        if self.active:
            self.iterations.append(dict(self.current))
        self.current = defaultdict(float)

    def totals_s(self) -> dict[str, float]:
        """Seconds per phase summed over the recorded iterations."""
        return {k: sum(it.get(k, 0.0) for it in self.iterations) for k in {k for it in self.iterations for k in it}}

    def medians_ms(self) -> dict[str, float]:
        names = sorted({k for it in self.iterations for k in it})
        return {k: 1000 * statistics.median(it.get(k, 0.0) for it in self.iterations) for k in names}

    def close(self) -> None:
        for hook in self._hooks:
            hook.remove()


def variant_preset(profile: dict, name: str, overrides: dict) -> dict:
    """`profile` with `overrides` ({section: {key: value}}) over its sections and over variant `name`'s own entry, so
    that they win where the variant sets the same key (no_precond sets precond.optimizer: an override of it must not
    be undone by the variant)."""
    varied = yaml.safe_load(yaml.safe_dump(profile))
    entry = (varied.get("variants") or {}).get(name)
    for section, values in overrides.items():
        varied.setdefault(section, {}).update(values)
        if entry is not None and section in entry:
            entry[section].update(values)
    return varied


def run_variant(args, name: str, overrides: dict, profile: dict, capture: Path, folder: str | None = None) -> dict:
    """Fit variant `name` (a preset variant, else `pig`) with `overrides`; outputs under `folder` (default: `name`)."""
    varied = variant_preset(profile, name, overrides)
    total = args.iterations + args.profile_phases + args.profile_ops
    # Same preset, run length cut; no held-out evaluation or checkpoint inside the timing.
    varied["fit"].update(iterations=total, eval_every=args.eval_every or 10**9, checkpoint_minutes=10**6)
    if args.budget:
        varied["fit"].update(iterations=10**7, time_budget_s=args.budget)
    folder = folder or name
    path = args.workdir / f"profile_{folder}.yaml"
    path.write_text(yaml.safe_dump(varied))
    variant = name if name in (profile.get("variants") or {}) else "pig"
    out_dir = args.workdir / f"fit_{folder}"
    shutil.rmtree(out_dir, ignore_errors=True)

    marks: dict[int, float] = {}
    timer = PhaseTimer() if args.profile_phases else None
    ops = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA])
    phase_start = args.iterations
    ops_start = args.iterations + args.profile_phases

    graphs = {"start": counters["stats"]["unique_graphs"]}

    def tick(iteration: int) -> None:
        # The device is waited for only where the timed window starts and ends, so that the host may run ahead.
        if iteration in (args.warmup, args.iterations):
            torch.cuda.synchronize()
            marks[iteration] = time.perf_counter()
            graphs[iteration] = counters["stats"]["unique_graphs"]
        if args.compile_cache is not None and iteration == args.iterations:
            save_compile_cache(args.compile_cache)  # every LOD's graphs exist by now; the run may not reach its end
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
    t0 = time.perf_counter()
    try:
        fit(capture, out_dir, str(path), variant=variant, device="cuda", on_iteration=tick,
            **({"phase": timer} if timer else {}))
    finally:
        if timer is not None:
            timer.close()
    timed = args.iterations - args.warmup
    ms = 1000 * (marks[args.iterations] - marks[args.warmup]) / timed
    # The data wait of the same iterations (rows of the train log, each a mean over its logging window).
    with open(out_dir / "train_log.csv", newline="") as file:
        waits = [float(row["data_wait_ms"]) for row in csv.DictReader(file)
                 if args.warmup < int(row["iteration"]) <= args.iterations] or [math.nan]
    result = {
        "name": name, "variant": variant, "overrides": overrides, "iterations_timed": timed, "ms_per_iteration": ms,
        "wait_ms_median": statistics.median(waits), "wait_ms_mean": statistics.mean(waits),
        "wait_share": statistics.mean(waits) / ms,
        "peak_gib": torch.cuda.max_memory_allocated() / 2**30, "fit_total_s": time.perf_counter() - t0,
        "log": str(out_dir / "train_log.csv"),
        # Graphs torch.compile built before the timed window, and inside it (recompilations: want 0).
        "graphs_warmup": graphs[args.warmup] - graphs["start"], "graphs_timed": graphs[args.iterations] - graphs[args.warmup],
    }
    if timer is not None:
        result["phases_ms"] = timer.medians_ms()
    if args.budget:
        result["budget"] = evaluate_budget_run(args, name, out_dir, path, capture)
        if args.evaluate_iterate and (out_dir / ITERATE_FILE).exists():  # a weight average's last iterate, after it
            result["budget_iterate"] = evaluate_budget_run(args, f"{name}_iterate", out_dir, path, capture,
                                                           ITERATE_FILE)
    if args.eval_every:
        with open(out_dir / "train_log.csv", newline="") as file:
            rows = [row for row in csv.DictReader(file) if row["heldout_psnr"]]
        result["heldout"] = {int(row["iteration"]): float(row["heldout_psnr"]) for row in rows}
        # With a weight average (fit.average_decay) "heldout" is the average's; these are the iterate's where they differ.
        result["heldout_iterate"] = {int(row["iteration"]): float(row["heldout_psnr_iterate"]) for row in rows
                                     if row.get("heldout_psnr_iterate")}
        result["heldout_by_time"] = [(float(row["train_s"]), float(row["heldout_psnr"])) for row in rows]
    if args.profile_ops:
        table = ops.key_averages().table(sort_by="device_time_total", row_limit=args.op_rows, max_name_column_width=70)
        result["ops_table"] = table
    return result


# The evaluate stage's ground-truth metrics (synthetic captures only), as the budget table prints them.
GROUND_TRUTH_KEYS = ("psnr_garment", "ssim_garment", "psnr_body", "ssim_body", "psnr_background", "accuracy_mm_garment",
                     "completeness_mm_garment", "accuracy_mm_body", "completeness_mm_body", "drift_mm", "drift_mm_last")


def evaluate_budget_run(args, name: str, fit_dir: Path, profile_path: Path, capture: Path,
                        checkpoint: str = "avatar.pt") -> dict:
    """Render and evaluate `checkpoint`'s novel view and novel pose at every LOD (`--finest-only`: the finest alone,
    rendered alone); {split: {lod: {psnr, ssim, images}}} + iterations. Called twice in one process (the weight
    average, then the last iterate), the second evaluation reuses the first's region labels (pig.stages.evaluate)."""
    from pig.stages.evaluate import main as evaluate, render_levels
    from pig.stages.render import main as render
    from pig._io import read_record

    with open(fit_dir / "train_log.csv", newline="") as file:
        last = list(csv.DictReader(file))[-1]
    out: dict = {"iterations": int(last["iteration"]), "wall_s": float(last["wall_s"]), "train_s": float(last["train_s"]),
                 "compile_s": float(last["compile_s"])}
    t0 = time.perf_counter()
    for split in ("novel_view", "novel_pose"):
        renders = args.workdir / f"renders_{name}" / split
        metrics = args.workdir / f"metrics_{name}"
        render(["--checkpoint", str(fit_dir / checkpoint), "--capture", str(capture), "--split", split, "--output", str(renders),
                "--preset", str(profile_path), "--overwrite", *(["--lod", "-1"] if args.finest_only else [])])
        finest = ["--lod", str(max(render_levels(renders)))] if args.finest_only else []  # the one rendered
        evaluate(["--capture", str(capture), "--renders", str(renders), "--split", split, "--output", str(metrics),
                  "--preset", str(profile_path), "--overwrite", *finest])
        out[split] = {}
        for record in sorted(metrics.glob(f"{split}_lod*.json")):
            summary = read_record(record, "evaluate summary")
            out[split][int(summary["lod"])] = {k: summary[k] for k in ("psnr", "ssim", "lpips", "images", *GROUND_TRUTH_KEYS)
                                               if k in summary}
    out["evaluate_s"] = time.perf_counter() - t0
    return out


def plot_heldout(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        steps = sorted(r["heldout"])
        axes[0].plot(steps, [r["heldout"][s] for s in steps], marker="o", label=r["name"])
        axes[1].plot(*zip(*r["heldout_by_time"]), marker="o", label=r["name"])
    axes[0].set_xlabel("iteration")
    axes[1].set_xlabel("training time, held-out evaluations left out [s]")
    for ax in axes:
        ax.set_ylabel("held-out novel-view PSNR [dB] (finest LOD)")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/pig_fit_bench"))
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--frames", type=int, default=10, help="captured frames (the paper preset has 120)")
    parser.add_argument("--seed", type=int, default=None, help="the synthetic subject's seed (default: the preset's)")
    parser.add_argument("--cameras", type=int, default=None, help="captured cameras (default: the preset's)")
    parser.add_argument("--reuse-capture", action="store_true", help="keep an existing capture in --workdir")
    parser.add_argument("--iterations", type=int, default=60, help="timed iterations, warm-up included")
    parser.add_argument("--warmup", type=int, default=5, help="iterations left out of the timing (compilation happens there)")
    parser.add_argument("--supersample", type=int, default=1)
    parser.add_argument("--workers", type=int, default=None,
                        help="processes generating the capture (default: the preset's; a 32-core host halves it with 32)")
    parser.add_argument("--variant", action="append", default=[], help="NAME:section.key=value,... (repeatable)")
    parser.add_argument("--profile-phases", type=int, default=0, help="iterations timed per phase after the timed ones")
    parser.add_argument("--profile-ops", type=int, default=0, help="iterations under torch.profiler after those")
    parser.add_argument("--op-rows", type=int, default=30)
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument("--budget", type=float, default=None, help="fixed-budget mode: seconds of training per variant")
    parser.add_argument("--eval-every", type=int, default=None, help="held-out evaluation every N iterations (parity)")
    parser.add_argument("--plot", type=Path, default=None, help="with --eval-every: plot of the held-out PSNR curves")
    parser.add_argument("--finest-only", action="store_true", help="budget mode: evaluate the finest LOD only")
    parser.add_argument("--evaluate-iterate", action="store_true",
                        help="budget mode, with a weight average (fit.average_decay): evaluate the fit's last iterate "
                             f"({ITERATE_FILE}) too, after the average (its JSON key: budget_iterate)")
    parser.add_argument("--warm-compile", type=int, default=0, help="untimed fit of N iterations before the variants")
    parser.add_argument("--capture-only", action="store_true", help="generate and preprocess the capture, then stop")
    parser.add_argument("--compile-cache", type=Path, default=None,
                        help="torch.compile's artifacts: loaded from this file first if it exists, written to it "
                             "once the first variant's timed window ends (another machine skips most compilation)")
    args = parser.parse_args(argv)
    if not (args.capture_only or torch.cuda.is_available()):  # the subject alone needs no GPU
        print("fit_gpu: no CUDA device", file=sys.stderr)
        return 1
    profile = load_preset(args.preset)
    profile.pop("_path")
    syn_cfg = {**profile.get("synthetic", {}), "frames": args.frames, "supersample": args.supersample}
    if args.seed is not None:
        syn_cfg["seed"] = args.seed
    if args.cameras is not None:
        syn_cfg["cameras"] = args.cameras
    if args.workers is not None:
        syn_cfg["workers"] = args.workers
    syn = SyntheticConfig(**syn_cfg)
    capture = args.workdir / "capture"
    stamps = {}
    if not (args.reuse_capture and capture.exists()):
        shutil.rmtree(args.workdir, ignore_errors=True)
        t0 = time.perf_counter()
        timeline = RenderTimeline()
        raw = generate_capture(args.workdir / "raw", syn, progress=False, timeline=timeline)
        stamps["generate_s"] = time.perf_counter() - t0
        workers = timeline_summary(timeline)  # where generate_s went: worker start-up, busy share, parts
        print(f"generate: {stamps['generate_s']:.1f} s\n{timeline_table(workers)}", flush=True)
        stamps.update({f"generate_{key}": float(workers[key]) for key in
                       ("ready_last_s", "first_task_last_s", "idle_tail_s", "busy_share", "rays_computed")})
        t0 = time.perf_counter()
        preprocess(["--input", str(raw), "--output", str(capture), "--preset", args.preset,
                    "--format", "thuman4", "--body-model", str(raw / "body_model.npz"), "--no-progress"])
        stamps["preprocess_s"] = time.perf_counter() - t0

    if args.capture_only:
        print(f"capture in {capture}: {stamps or 'kept'}")
        return 0
    if args.compile_cache is not None:
        stamps["compile_cache_loaded"] = float(load_compile_cache(args.compile_cache))
    variants = [parse_variant(v) for v in args.variant] or [("profile", {})]
    warm = argparse.Namespace(**{**vars(args), "iterations": max(args.warm_compile, 2), "warmup": 1, "profile_phases": 0,
                                 "profile_ops": 0, "budget": None, "eval_every": None})
    results = []
    for name, overrides in variants:  # a line per variant as it ends, in case the run is cut short
        if args.warm_compile:  # the variant's own graphs: each variant compiles different code
            stamps[f"warm_compile_{name}_s"] = run_variant(warm, name, overrides, profile, capture,
                                                           folder=f"warm_{name}")["fit_total_s"]
        results.append(run_variant(args, name, overrides, profile, capture))
        r = results[-1]
        print(f"variant {r['name']}: {r['ms_per_iteration']:.1f} ms/it, peak {r['peak_gib']:.2f} GiB, fit {r['fit_total_s']:.0f} s, "
              f"graphs compiled {r['graphs_warmup']} in the warm-up and {r['graphs_timed']} in the timed window"
              + (f", budget {r['budget']}" if "budget" in r else ""), flush=True)

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
    base = results[0]["ms_per_iteration"]
    print("\n| variant | overrides | ms/it | vs first | data wait ms median | mean | share | peak GiB | timed |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        over = ", ".join(f"{s}.{k}={v}" for s, kv in r["overrides"].items() for k, v in kv.items())
        print(f"| {r['name']} | {over or '-'} | {r['ms_per_iteration']:.1f} | {r['ms_per_iteration'] / base:.3f} "
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
    if args.budget:
        levels = sorted({lod for r in results for lod in r["budget"]["novel_view"]})
        cell = lambda b, split, l: f"{b[split][l]['psnr']:.2f} / {b[split][l]['ssim']:.4f}" if l in b[split] else "-"
        print(f"\nFixed budget {args.budget:.0f} s of training: PSNR dB / SSIM per LOD (0 = coarsest)")
        print("| variant | iterations | " + " | ".join(f"{split} lod{l}" for split in ("novel_view", "novel_pose") for l in levels) + " |")
        print("|---|---|" + "---|" * (2 * len(levels)))
        evaluated = [(r["name"], r["budget"]) for r in results] + [(f"{r['name']} (its last iterate)", r["budget_iterate"])
                                                                 for r in results if "budget_iterate" in r]
        for label, b in evaluated:
            cells = [cell(b, split, l) for split in ("novel_view", "novel_pose") for l in levels]
            print(f"| {label} | {b['iterations']} | " + " | ".join(cells) + " |")
        if any("psnr_garment" in b["novel_view"][max(b["novel_view"])] for _, b in evaluated):
            for split in ("novel_view", "novel_pose"):
                print(f"\nGround truth, {split}, finest LOD: PSNR dB / SSIM per region; geometry mm (accuracy: splats to "
                      "the true surface, completeness: the true surface to splats); correspondence drift mm")
                print("| variant | LOD | garment | body | background | garment acc / comp | body acc / comp | drift mean / last |")
                print("|---|---|---|---|---|---|---|---|")
                for label, b in evaluated:
                    lod = max(b[split])
                    m = b[split][lod]
                    print(f"| {label} | {lod} | {m['psnr_garment']:.2f} / {m['ssim_garment']:.4f} | "
                          f"{m['psnr_body']:.2f} / {m['ssim_body']:.4f} | {m['psnr_background']:.2f} | "
                          f"{m['accuracy_mm_garment']:.1f} / {m['completeness_mm_garment']:.1f} | "
                          f"{m['accuracy_mm_body']:.1f} / {m['completeness_mm_body']:.1f} | "
                          f"{m.get('drift_mm', math.nan):.1f} / {m.get('drift_mm_last', math.nan):.1f} |")
    if args.eval_every:
        steps = sorted(results[0]["heldout"])
        print("\nHeld-out novel-view PSNR (finest LOD) per evaluation; difference to " + results[0]["name"])
        print("| iteration | " + " | ".join(r["name"] for r in results) + " | " +
              " | ".join(f"{r['name']} - {results[0]['name']}" for r in results[1:]) + " |")
        print("|---|" + "---|" * (2 * len(results) - 1))
        for step in steps:
            values = [r["heldout"].get(step, float("nan")) for r in results]
            print(f"| {step} | " + " | ".join(f"{v:.3f}" for v in values) + " | " +
                  " | ".join(f"{v - values[0]:+.3f}" for v in values[1:]) + " |")
        print("\nHeld-out novel-view PSNR (finest LOD) against training time (held-out evaluations left out)")
        print("| variant | " + " | ".join(["train s / dB"] * max(len(r["heldout_by_time"]) for r in results)) + " |")
        print("|---|" + "---|" * max(len(r["heldout_by_time"]) for r in results))
        for r in results:
            print(f"| {r['name']} | " + " | ".join(f"{t:.0f} / {p:.2f}" for t, p in r["heldout_by_time"]) + " |")
        if args.plot is not None:
            plot_heldout(results, args.plot)
    for r in results:
        if "ops_table" in r:
            print(f"\nOperators by device time, variant {r['name']} ({args.profile_ops} iterations):\n{r['ops_table']}")
    if args.json is not None:
        write_json(args.json, {"stamps": stamps, "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
