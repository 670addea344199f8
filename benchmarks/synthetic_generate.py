"""Time the synthetic capture generator: stand-in model, scene, one frame (cold vs cached rays), whole presets.

    python benchmarks/synthetic_generate.py [--presets test cpu-demo]

Prints one table; ratios are taken within this process so they survive noisy shared cores.
"""
from __future__ import annotations

import argparse
import dataclasses
import resource
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from pig.body.standin import make_standin_arrays
from pig.config import load_preset, load_section
from pig.data.synthetic import SyntheticConfig, build_scene, generate_capture
from pig.data.synthetic import render as synthetic_render
from pig.data.synthetic.workers import RenderTimeline
from pig.data.synthetic.render import render_frame


def cpu_seconds() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


PARTS = ("scene", "rays", "intersect", "shade", "compose", "write")


def timeline_summary(timeline: RenderTimeline) -> dict[str, float]:
    """The render workers' timeline in numbers: seconds from `timeline.started` (the parent starting the workers),
    CPU-free waits included; parts in worker-seconds summed over the tasks."""
    wall = timeline.ended - timeline.started
    ready = {r["pid"]: r["ready"] - timeline.started for r in timeline.tasks}
    first = defaultdict(lambda: float("inf"))
    last = defaultdict(float)
    for r in timeline.tasks:
        first[r["pid"]] = min(first[r["pid"]], r["start"] - timeline.started)
        last[r["pid"]] = max(last[r["pid"]], r["end"] - timeline.started)
    busy = sum(r["end"] - r["start"] for r in timeline.tasks)
    parts = {name: sum(r["parts"].get(name, 0.0) for r in timeline.tasks) for name in PARTS}
    summary = {
        "workers": timeline.workers, "workers_used": len(ready), "tasks": len(timeline.tasks),
        "views": sum(r["views"] for r in timeline.tasks), "wall_s": wall,
        "ready_first_s": min(ready.values()), "ready_median_s": statistics.median(ready.values()),
        "ready_last_s": max(ready.values()), "first_task_last_s": max(first.values()),
        "idle_tail_s": wall - min(last.values()),  # from the first worker to run out of tasks to the end
        "busy_share": busy / (timeline.workers * wall), "task_s_mean": busy / len(timeline.tasks),
        "task_s_max": max(r["end"] - r["start"] for r in timeline.tasks),
        "rays_computed": sum(r["parts"].get("rays_computed", 0) for r in timeline.tasks),
        "rays_cached": sum(r["parts"].get("rays_cached", 0) for r in timeline.tasks),
    }
    summary.update({f"{name}_s": seconds for name, seconds in parts.items()})
    summary["other_s"] = busy - sum(parts.values())
    return summary


def timeline_table(summary: dict[str, float]) -> str:
    """`timeline_summary` as a two-column table, worker-seconds per part with their share of the tasks' time."""
    busy = summary["task_s_mean"] * summary["tasks"]
    rows = [f"| {key} | {value:.3g} |" if isinstance(value, float) else f"| {key} | {value} |"
            for key, value in summary.items() if not key.endswith("_s") or key[:-2] not in PARTS + ("other",)]
    rows += [f"| {name} worker-s | {summary[name + '_s']:.1f} ({100 * summary[name + '_s'] / busy:.0f} %) |"
             for name in PARTS + ("other",)]
    return "\n".join(["| render workers | |", "|---|---|", *rows])


def timed(fn):
    wall, cpu = time.perf_counter(), cpu_seconds()
    result = fn()
    return result, time.perf_counter() - wall, cpu_seconds() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["test", "cpu-demo"])
    args = parser.parse_args()
    rows = []
    _, wall, cpu = timed(lambda: make_standin_arrays(0))
    rows.append(("-", "stand-in model (make_standin_arrays)", wall, cpu, ""))
    for name in args.presets:
        cfg = load_section(load_preset(name), "synthetic", SyntheticConfig)
        scene, wall, cpu = timed(lambda: build_scene(cfg))
        rows.append((name, "build_scene (stand-in cached)", wall, cpu, ""))
        synthetic_render._RAYS.clear()
        frame = lambda: list(render_frame(scene.appearance, scene.body_vertices[0], scene.garment_vertices[0],  # noqa: E731
                                          scene.cameras, cfg.supersample))
        _, cold, cold_cpu = timed(frame)
        _, warm, warm_cpu = timed(frame)
        rows.append((name, f"render 1 frame x {cfg.cameras} cams, rays computed", cold, cold_cpu, ""))
        rows.append((name, f"render 1 frame x {cfg.cameras} cams, rays cached", warm, warm_cpu,
                     f"cached/computed CPU {warm_cpu / cold_cpu:.2f}"))
        totals = {}
        for workers in (1, 2):
            with tempfile.TemporaryDirectory() as tmp:
                run = dataclasses.replace(cfg, workers=workers)
                _, wall, cpu = timed(lambda: generate_capture(Path(tmp) / "subject", run, progress=False))
            totals[workers] = wall
            note = "" if workers == 1 else f"wall 2 workers / 1 worker {wall / totals[1]:.2f}"
            rows.append((name, f"generate_capture, {workers} worker(s), {cfg.frames} frames", wall, cpu, note))
    print(f"| {'preset':8} | {'step':52} | {'wall s':>7} | {'cpu s':>7} | note |")
    print(f"|{'-' * 10}|{'-' * 54}|{'-' * 9}|{'-' * 9}|------|")
    for profile, step, wall, cpu, note in rows:
        print(f"| {profile:8} | {step:52} | {wall:7.2f} | {cpu:7.2f} | {note} |")


if __name__ == "__main__":
    main()
