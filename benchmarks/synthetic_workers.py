"""The synthetic generator's render workers with and without their one-BLAS-thread limit
(pig.data.synthetic.workers.WORKER_THREAD_LIMITS), alternated in one process: wall and CPU seconds (the parent's
and the workers') of one capture at the paper's image size; or, with --timeline, one capture and where its workers'
time went (pig.data.synthetic.workers.RenderTimeline: start-up, busy share, seconds per part, rays computed).

    python benchmarks/synthetic_workers.py [--cameras 4 --frames 4 --workers 2 --repeats 2 --supersample 2]
        [--timeline]

Without the limit OpenBLAS starts a thread per core in every worker; the CPU seconds show what idle threads spin.
On a host with many cores and several workers that is most of the generation (benchmarks/NOTES.md).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import pig.data.synthetic.capture as capture
import pig.data.synthetic.workers as render_workers
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.data.synthetic.render import RAY_CACHE_BYTES
from synthetic_generate import cpu_seconds, timeline_summary, timeline_table


def earlier_tasks(cfg: SyntheticConfig) -> list[tuple[list[int], list[int]]]:
    """The split before the cost model (capture._tasks until 2026-11): one frame block (~4 items a worker) by the
    largest camera group whose rays fit the cache, so that a worker recomputes rays in nearly every item."""
    group = max(1, min(cfg.cameras, RAY_CACHE_BYTES // (cfg.width * cfg.height * cfg.supersample**2 * 12)))
    camera_groups = [list(range(c, min(c + group, cfg.cameras))) for c in range(0, cfg.cameras, group)]
    step = max(1, round(cfg.frames * len(camera_groups) / (4 * cfg.workers)))
    frame_groups = [list(range(f, min(f + step, cfg.frames))) for f in range(0, cfg.frames, step)]
    return [(frames, cams) for frames in frame_groups for cams in camera_groups]


def timelines(cfg: SyntheticConfig, repeats: int) -> None:
    """The earlier split and the cost model's alternated: a row each, then the last capture's whole timeline."""
    views = cfg.cameras * cfg.frames
    print(f"{views} views at {cfg.width} x {cfg.height} (supersample {cfg.supersample}), {cfg.workers} workers")
    print("| tasks | wall s | CPU s | items | rays computed | workers ready by s | busy share | idle tail s |")
    print("|---|---|---|---|---|---|---|---|")
    model = capture._tasks
    for _ in range(repeats):
        for label, split in (("earlier split", earlier_tasks), ("cost model (capture._tasks)", model)):
            capture._tasks = split
            timeline = render_workers.RenderTimeline()
            with tempfile.TemporaryDirectory() as folder:
                wall, cpu = time.perf_counter(), cpu_seconds()
                generate_capture(Path(folder) / "raw", cfg, progress=False, timeline=timeline)
                wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
            s = timeline_summary(timeline)
            print(f"| {label} | {wall:.1f} | {cpu:.1f} | {s['tasks']} | {s['rays_computed']} | {s['ready_last_s']:.1f} "
                  f"| {s['busy_share']:.2f} | {s['idle_tail_s']:.1f} |", flush=True)
    capture._tasks = model
    print(timeline_table(s))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--supersample", type=int, default=2, help="benchmarks/fit_gpu.py's subject has 1")
    parser.add_argument("--timeline", action="store_true", help="one capture (with the limit) and its timeline")
    args = parser.parse_args()
    cfg = SyntheticConfig(cameras=args.cameras, frames=args.frames, width=1330, height=1150,
                          supersample=args.supersample, workers=args.workers)
    views = args.cameras * args.frames
    if args.timeline:
        timelines(cfg, args.repeats)
        return
    limits = dict(render_workers.WORKER_THREAD_LIMITS)
    print(f"{views} views at 1330 x 1150 (supersample {args.supersample}), {args.workers} workers")
    print("| workers' BLAS threads | wall s | CPU s (parent + workers) | CPU s a view |\n|---|---|---|---|")
    for _ in range(args.repeats):
        for label, limit in (("a thread per core (no limit)", {}), ("one (WORKER_THREAD_LIMITS)", limits)):
            render_workers.WORKER_THREAD_LIMITS = limit
            with tempfile.TemporaryDirectory() as folder:
                wall, cpu = time.perf_counter(), cpu_seconds()
                generate_capture(Path(folder) / "raw", cfg, progress=False)
                wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
            print(f"| {label} | {wall:.1f} | {cpu:.1f} | {cpu / views:.2f} |", flush=True)
    render_workers.WORKER_THREAD_LIMITS = limits


if __name__ == "__main__":
    main()
