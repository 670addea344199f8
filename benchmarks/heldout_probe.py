"""Cost of the fit's held-out evaluations on the default run: one full evaluation, one probe, one redraw of
train_log.png, each timed in this process on a fitted avatar, times how often the default run does each.

Schedules from the preset (pig.avatar.training.evaluations_due): `after` is the preset as it is; `before` the same
without probes and with the full evaluation every `--before-eval-every` iterations (900: the default run before
probes). Redraws: before probes, at every evaluated row and once more after the fit; now at the start, at full
evaluations and at probes at least REDRAW_S apart, counted for a fit of `--fit-seconds` at an even pace (the start's
and the end's draws are outside the fit's timed loop but inside its rule). Also the PSNR of each, to show what the
probe reads against the full evaluation.

    python benchmarks/heldout_probe.py --capture results/synthetic/subject00/capture \
        --avatar results/synthetic/subject00/pig/avatar.pt [--preset cpu-demo] [--repeats 5] [--threads 2] \
        [--fit-seconds 400]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from pig.avatar.batches import ViewSource
from pig.avatar.checkpoint import load_avatar
from pig.avatar.fit_config import FitConfig
from pig.avatar.probe import Probe
from pig.avatar.train_plot import plot_train_log
from pig.avatar.training import REDRAW_S, HeldOut, evaluations_due
from pig.config import load_preset, load_section
from pig.data.capture import Capture
from pig.render.api import RasterizerConfig


def timed(call, repeats: int) -> tuple[float, object]:
    """(median seconds of `repeats` calls after one warm-up call, the last result)."""
    result = call()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = call()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def schedule(cfg: FitConfig, fit_seconds: float, throttled: bool) -> tuple[int, int, int]:
    """(full evaluations, probes, redraws of train_log.png) over a whole fit with `cfg`, the start included."""
    due = [evaluations_due(cfg, i) for i in range(cfg.iterations + 1)]
    if not throttled:
        return sum(f for f, _ in due), sum(p for _, p in due), sum(f or p for f, p in due) + 1
    redraws, last = 0, -float("inf")
    for i, (full, probe) in enumerate(due):
        now = fit_seconds * i / cfg.iterations
        if full or (probe and now - last >= REDRAW_S):
            redraws, last = redraws + 1, now
    return sum(f for f, _ in due), sum(p for _, p in due), redraws


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, required=True)
    parser.add_argument("--avatar", type=Path, required=True)
    parser.add_argument("--preset", default="cpu-demo")
    parser.add_argument("--before-eval-every", type=int, default=900)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--fit-seconds", type=float, default=400.0, help="the fit's wall time, for the redraw count")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    preset = load_preset(args.preset)
    cfg = load_section(preset, "fit", FitConfig)
    raster = load_section(preset, "rasterizer", RasterizerConfig)
    before = replace(cfg, probe_every=0, eval_every=args.before_eval_every)
    capture = Capture.load(args.capture, cache_mb=0)
    model = load_avatar(args.avatar, capture=capture)
    # A log of the default run's length (one row an iteration), with the evaluated rows' PSNRs, to redraw.
    rows = [{"iteration": i, "wall_s": 0.25 * i, "train_s": 0.25 * i, "loss": 1 / (1 + i), "l1": 0.1 / (1 + i),
             "ssim": 0.5 / (1 + i), "lpips": "", "heldout_psnr": 20 + i / 900 if evaluations_due(cfg, i)[0] else "",
             "probe_psnr": 18 + i / 900 if evaluations_due(cfg, i)[1] else ""} for i in range(cfg.iterations + 1)]
    with ViewSource(capture, list(model.frame_ids), "cpu", cfg.view_cache, cfg.loader_workers) as source, \
            tempfile.TemporaryDirectory() as folder:
        held_out = HeldOut(capture, model, source, cfg.eval_frames, cfg.views)
        probe = Probe(capture, model, source, cfg.probe_views, cfg.probe_scale)
        full_s, full_psnr = timed(lambda: held_out.psnr(model, raster), args.repeats)
        probe_s, probe_psnr = timed(lambda: probe.psnr(model, raster), args.repeats)
        plot_s, _ = timed(lambda: plot_train_log(Path(folder) / "train_log.png", rows, "benchmark"), args.repeats)
    views = sum(len(cams) for _, cams in held_out.steps)
    print(f"{args.avatar}: {args.threads} threads, median of {args.repeats}; full evaluation: {views} whole frames "
          f"({len(held_out.steps)} frames), PSNR {full_psnr:.3f} dB; probe: {len(probe.pairs)} views {probe.pairs} at "
          f"1/{cfg.probe_scale} over their mask boxes, PSNR {probe_psnr:.3f} dB", file=sys.stderr)
    print("| schedule | full evaluations | probes | redraws | full s | probe s | redraw s | total s |\n"
          "|---|---|---|---|---|---|---|---|")
    for name, c, throttled in ((f"before (eval_every {before.eval_every}, no probes)", before, False),
                               (f"after (eval_every {cfg.eval_every}, probe_every {cfg.probe_every})", cfg, True)):
        full, probes, redraws = schedule(c, args.fit_seconds, throttled)
        total = full * full_s + probes * probe_s + redraws * plot_s
        print(f"| {name} | {full} | {probes} | {redraws} | {full_s:.3f} | {probe_s:.3f} | {plot_s:.3f} | {total:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
