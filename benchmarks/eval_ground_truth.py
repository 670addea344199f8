"""The ground-truth metrics of a budget fit's evaluation (issue 38): where their host time goes, and the evaluation
as `fit_gpu.py --budget --finest-only --evaluate-iterate` runs it, old code against new, on the CPU.

Builds (once per `--workdir`) a synthetic subject of the `paper` preset at its full size (1330 x 1150; `--cameras` x
`--frames`, default 24 x 4: novel view 2 cameras x 3 frames, novel pose 24 cameras x 1 frame), an avatar of the
paper's 100k anchors fitted for one iteration (its splats are where the fit starts them, which is what the geometry
metrics' cost depends on) and its renders of both splits at the finest LOD.

Then, in this process: the parts of the region labels and the geometry metrics (`breakdown`): each camera's pixel
rays, a view's labels cast over the whole frame (as before) and over the box of the projected vertices (now), and
the geometry metrics of one split's splat track; then the ground-truth metrics' host work of a fit's two
evaluations (its weight average, then its last iterate; `host_work`), both splits each, by the modules of
`--old-code` (a checkout of the commit before: labels one view after another, cast anew each evaluation) and by
this checkout's (labels on `--label-workers` threads with the process's label cache); labels and geometry must be
equal. `--stages` also runs the evaluate stage of both splits twice in one process per checkout, each in a process
of its own (on the CPU its PSNR/SSIM, which a GPU computes, dominate; the summaries' values must agree, largest
difference printed); `--render` times the render stage on novel view at every LOD and at the finest alone.

    git worktree add /tmp/old-code 26bda42
    python benchmarks/eval_ground_truth.py --workdir /tmp/evgt --old-code /tmp/old-code --render
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from pig.config import derive_preset, load_preset

ROOT = Path(__file__).resolve().parent.parent
SPLITS = ("novel_view", "novel_pose")


def cpu_preset(workdir: Path) -> Path:
    """The paper preset with a one-iteration CPU fit (1 view, 1 timestep, nothing compiled, no LPIPS term) and a CPU
    evaluation (the CPU compositor, 1 timing frame)."""
    return derive_preset(workdir / "preset.yaml", "paper",
                         fit=dict(iterations=1, views=1, timesteps=1, weight_lpips=0.0, eval_every=1000, eval_frames=1,
                                  checkpoint_minutes=0.0, precision="float32", compile=False, compile_posing=False,
                                  fused_adam=False, lpips_compile=False, loader_workers=2),
                         precond=dict(knn_solver="factorized", cg_compile=False, cg_graphs=False),
                         evaluate=dict(timing_frames=1, device="cpu"),
                         rasterizer=dict(backend="cpu"))


def build(workdir: Path, cameras: int, frames: int, workers: int) -> tuple[Path, Path, Path]:
    """(capture, preset, renders folder) of the subject, its one-iteration avatar and finest-LOD renders."""
    from pig.avatar.training import fit
    from pig.data.synthetic import SyntheticConfig, generate_capture
    from pig.stages.preprocess import main as preprocess
    from pig.stages.render import main as render

    capture, preset, renders = workdir / "capture", cpu_preset(workdir), workdir / "renders"
    if not (capture / "report.json").is_file():
        synthetic = {**load_preset("paper")["synthetic"], "cameras": cameras, "frames": frames, "supersample": 1,
                     "workers": workers}
        raw = generate_capture(workdir / "raw", SyntheticConfig(**synthetic), progress=False)
        preprocess(["--input", str(raw), "--output", str(capture), "--preset", "paper", "--format", "thuman4",
                    "--body-model", str(raw / "body_model.npz"), "--no-progress"])
    checkpoint = workdir / "fit" / "avatar.pt"
    if not checkpoint.is_file():
        fit(capture, workdir / "fit", str(preset), progress_s=1e9)
    for split in SPLITS:
        if not (renders / split / "manifest.json").is_file():
            render(["--checkpoint", str(checkpoint), "--capture", str(capture), "--split", split, "--output",
                    str(renders / split), "--preset", str(preset), "--lod", "-1", "--quiet"])
    return capture, preset, renders


def breakdown(capture_dir: Path, renders: Path, geometry_frames: int) -> None:
    """Seconds of each part of the ground-truth metrics, one thread, in this process."""
    from pig.data.capture import Capture
    from pig.data.ground_truth import GT_MESHES, SplatTrack, TrueMeshes
    from pig.metrics.geometry import ground_truth_geometry
    from pig.metrics.regions import camera_rays, covered_box, mesh_caster, region_labels

    capture = Capture.load(capture_dir, cache_mb=0)
    truth = TrueMeshes.load(capture_dir / GT_MESHES)
    views = capture.views("novel_pose")[:8]
    rows = []
    start = time.perf_counter()
    rays = {camera: camera_rays(capture.cameras[camera]) for camera, _ in views}
    rows.append(("pixel rays of a camera (once per camera)", (time.perf_counter() - start) / len(rays)))
    casters = {frame: mesh_caster(truth.surfaces(frame)) for _, frame in views}
    full, box, share = 0.0, 0.0, []
    for camera, frame in views:
        surfaces, cam = truth.surfaces(frame), capture.cameras[camera]
        start = time.perf_counter()
        whole = whole_frame_labels(surfaces, cam, casters[frame], rays[camera])
        full += time.perf_counter() - start
        start = time.perf_counter()
        labels = region_labels(surfaces, cam, casters[frame], rays[camera])
        box += time.perf_counter() - start
        if not np.array_equal(labels, whole):
            raise AssertionError(f"{camera} frame {frame}: the box's labels differ from the whole frame's")
        rows_, cols_ = covered_box(surfaces, cam)
        share.append((rows_.stop - rows_.start) * (cols_.stop - cols_.start) / (cam.width * cam.height))
    rows += [("labels of a view, every pixel's ray cast (before)", full / len(views)),
             ("labels of a view, the box's rays cast (now)", box / len(views))]
    for split in SPLITS:
        track = SplatTrack.load(renders / split / f"lod{max_level(renders / split)}" / "splats.npz")
        start = time.perf_counter()
        ground_truth_geometry(track, truth, geometry_frames)
        rows.append((f"geometry metrics of {split} ({len(track.frames)} frames, {track.centres.shape[1]} splats)",
                     time.perf_counter() - start))
    camera = capture.cameras[views[0][0]]
    print(f"\nwhere the ground-truth metrics' host time goes: {len(views)} novel-pose views at {camera.width} x "
          f"{camera.height}, labels on one thread (box: {100 * np.mean(share):.1f} % of the frame on average), the "
          "geometry's KD-tree on every core")
    print(f"{'part':66s} {'s':>7s}")
    for name, seconds in rows:
        print(f"{name:66s} {seconds:7.3f}")


def old_modules(code: Path):
    """pig.metrics.regions, .surface and .geometry of the checkout `code`, loaded beside this checkout's."""
    import importlib.util

    loaded = {}
    saved = sys.modules.get("pig.metrics.surface")
    try:
        for name in ("surface", "regions", "geometry"):
            spec = importlib.util.spec_from_file_location(f"old_{name}", code / "pig" / "metrics" / f"{name}.py")
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            loaded[name] = module
            if name == "surface":  # the old geometry module imports the old surface module
                sys.modules["pig.metrics.surface"] = module
    finally:
        sys.modules["pig.metrics.surface"] = saved
    return loaded["regions"], loaded["geometry"]


def host_work(code: Path, capture_dir: Path, renders: Path, geometry_frames: int, workers: int) -> None:
    """The ground-truth metrics' host work of a budget fit's two evaluations (both splits each), before (the old
    checkout's labeller, one view after another on the scoring's thread, the geometry after the pass) and now (the
    labeller on `workers` threads with the process's label cache; the geometry with its KD-tree on every core), in
    this process; the labels and the geometry must agree."""
    from concurrent.futures import ThreadPoolExecutor

    from pig.data.capture import Capture
    from pig.data.ground_truth import GT_MESHES, SplatTrack, TrueMeshes
    from pig.metrics.geometry import ground_truth_geometry
    from pig.metrics.regions import LabelCache, RegionLabeller

    old_regions, old_geometry = old_modules(code)
    capture = Capture.load(capture_dir, cache_mb=0)
    truth = TrueMeshes.load(capture_dir / GT_MESHES)
    tracks = {split: SplatTrack.load(renders / split / f"lod{max_level(renders / split)}" / "splats.npz")
              for split in SPLITS}
    cache = LabelCache(1 << 30)
    rows = []
    for evaluation in ("average", "iterate"):
        for split in SPLITS:
            views = capture.views(split)
            start = time.perf_counter()
            labeller = old_regions.RegionLabeller(truth, capture.cameras)
            before = [labeller(*view) for view in views]
            before_s = time.perf_counter() - start
            start = time.perf_counter()
            labeller = RegionLabeller(truth, capture.cameras, cache)
            with ThreadPoolExecutor(workers) as pool:
                now = list(pool.map(lambda view: labeller(*view), views))
            now_s = time.perf_counter() - start
            if not all(np.array_equal(a, b) for a, b in zip(before, now)):
                raise AssertionError(f"{split}: the labels differ")
            rows.append((f"{evaluation}: {split} labels ({len(views)} views)", before_s, now_s))
            start = time.perf_counter()
            before = old_geometry.ground_truth_geometry(tracks[split], truth, geometry_frames)
            before_s = time.perf_counter() - start
            start = time.perf_counter()
            now = ground_truth_geometry(tracks[split], truth, geometry_frames)
            now_s = time.perf_counter() - start
            if before != now:
                raise AssertionError(f"{split}: the geometry metrics differ: {before} against {now}")
            rows.append((f"{evaluation}: {split} geometry", before_s, now_s))
    print(f"\nthe ground-truth metrics' host work of a budget fit's two evaluations, in one process: before (one "
          f"thread, labels cast anew) and now ({workers} label threads, the label cache; labels and geometry equal)")
    print(f"{'part':44s} {'before s':>9s} {'now s':>9s} {'ratio':>7s}")
    for name, before_s, now_s in rows:
        print(f"{name:44s} {before_s:9.2f} {now_s:9.2f} {now_s / before_s:7.3f}")
    before_s, now_s = sum(row[1] for row in rows), sum(row[2] for row in rows)
    print(f"{'all':44s} {before_s:9.2f} {now_s:9.2f} {now_s / before_s:7.3f}")


def whole_frame_labels(surfaces, camera, caster, rays) -> np.ndarray:
    """The labels as the code before issue 38 cast them: every pixel's ray."""
    from pig.metrics.regions import BACKGROUND, BODY, CHUNK, GARMENT

    origin, directions = rays
    directions = directions.reshape(-1, 3)
    triangle = np.empty(len(directions), dtype=np.int64)
    for start in range(0, len(directions), CHUNK):
        part = directions[start:start + CHUNK]
        triangle[start:start + CHUNK] = caster.intersects_first(np.broadcast_to(origin, part.shape), part)
    labels = np.where(triangle < 0, BACKGROUND, np.where(triangle < len(surfaces[0][1]), BODY, GARMENT))
    return labels.astype(np.uint8).reshape(camera.height, camera.width)


def max_level(split_dir: Path) -> int:
    return max(int(p.name[3:]) for p in split_dir.glob("lod*") if p.name[3:].isdigit())


# Run by each code version in its own process: both splits' evaluate stage, twice (a fit's two evaluations).
EVALUATIONS = """
import json, sys, time
from pathlib import Path
from pig.stages.evaluate import main as evaluate
capture, preset, renders, out = map(Path, sys.argv[1:5])
seconds = []
for evaluation in ("average", "iterate"):
    for split in ("novel_view", "novel_pose"):
        start = time.perf_counter()
        evaluate(["--capture", str(capture), "--renders", str(renders / split), "--split", split, "--output",
                  str(out / evaluation), "--preset", str(preset), "--overwrite", "--lod", sys.argv[5], "--quiet"])
        seconds.append([evaluation, split, time.perf_counter() - start])
print("SECONDS " + json.dumps(seconds))
"""


def evaluations(code: Path, capture: Path, preset: Path, renders: Path, out: Path, level: int) -> tuple[list, dict]:
    """([evaluation, split, seconds] of each evaluate call, {(evaluation, split): summary}) of `code`'s checkout."""
    env = {**os.environ, "PYTHONPATH": str(code)}
    result = subprocess.run([sys.executable, "-c", EVALUATIONS, str(capture), str(preset), str(renders), str(out),
                             str(level)], env=env, capture_output=True, text=True, cwd=code)
    if result.returncode:
        raise RuntimeError(f"evaluate under {code} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    seconds = json.loads(result.stdout.split("SECONDS ")[-1])
    summaries = {(evaluation, split): json.loads((out / evaluation / f"{split}_lod{level}.json").read_text())
                 for evaluation in ("average", "iterate") for split in SPLITS}
    return seconds, summaries


def largest_difference(old: dict, new: dict) -> tuple[float, str]:
    worst, where = 0.0, ""
    for key, summary in old.items():
        for name, value in summary.items():
            if isinstance(value, float) and name not in ("seconds_per_frame", "fps") and np.isfinite(value):
                difference = abs(new[key][name] - value)
                if difference >= worst:
                    worst, where = difference, f"{key[1]} {name}"
    return worst, where


def render_seconds(capture: Path, preset: Path, workdir: Path) -> list[tuple[str, float]]:
    from pig.stages.render import main as render

    rows = []
    for name, lods in (("every LOD", []), ("finest alone (--lod -1)", ["--lod", "-1"])):
        start = time.perf_counter()
        render(["--checkpoint", str(workdir / "fit" / "avatar.pt"), "--capture", str(capture), "--split",
                "novel_view", "--output", str(workdir / "render_timed"), "--preset", str(preset), "--overwrite",
                "--quiet", *lods])
        rows.append((name, time.perf_counter() - start))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/eval_ground_truth"))
    parser.add_argument("--old-code", type=Path, required=True, help="a checkout of the code to compare against")
    parser.add_argument("--cameras", type=int, default=24)
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2, help="processes generating the capture")
    parser.add_argument("--render", action="store_true", help="also time the render stage on novel view")
    parser.add_argument("--stages", action="store_true",
                        help="also time the evaluate stage of each checkout (on the CPU its PSNR/SSIM dominate)")
    parser.add_argument("--label-workers", type=int, default=os.cpu_count(), help="label threads of `now`")
    args = parser.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    capture, preset, renders = build(args.workdir, args.cameras, args.frames, args.workers)
    level = max_level(renders / "novel_view")
    views = {split: len(json.loads((renders / split / "manifest.json").read_text())["frames"])
             * len(json.loads((renders / split / "manifest.json").read_text())["cameras"]) for split in SPLITS}
    geometry_frames = load_preset("paper")["evaluate"].get("geometry_frames", 4)
    breakdown(capture, renders, geometry_frames)
    host_work(args.old_code.resolve(), capture, renders, geometry_frames, args.label_workers)
    if args.stages:
        stages(args, capture, preset, renders, level, views)
    if args.render:
        rows = render_seconds(capture, preset, args.workdir)
        print(f"\nthe render stage on novel view ({views['novel_view']} views), CPU compositor")
        for name, seconds in rows:
            print(f"{name:26s} {seconds:8.2f} s  ratio {seconds / rows[0][1]:.3f}")
    return 0


def stages(args, capture: Path, preset: Path, renders: Path, level: int, views: dict) -> None:
    timed = {}
    for name, code in (("before", args.old_code.resolve()), ("now", ROOT)):
        timed[name] = evaluations(code, capture, preset, renders, args.workdir / f"metrics_{name}", level)
    print(f"\nthe evaluate stage, both splits twice in one process (a budget fit's two evaluations), finest LOD, "
          f"{views['novel_view']} novel-view and {views['novel_pose']} novel-pose views")
    print(f"{'evaluation':10s} {'split':12s} {'before s':>9s} {'now s':>9s} {'ratio':>7s}")
    for (evaluation, split, before), (_, _, now) in zip(timed["before"][0], timed["now"][0]):
        print(f"{evaluation:10s} {split:12s} {before:9.2f} {now:9.2f} {now / before:7.3f}")
    before, now = (sum(row[2] for row in timed[name][0]) for name in ("before", "now"))
    print(f"{'all':23s} {before:9.2f} {now:9.2f} {now / before:7.3f}")
    worst, where = largest_difference(timed["before"][1], timed["now"][1])
    print(f"largest difference of a summary's metric, before against now: {worst:.3g} ({where})")


if __name__ == "__main__":
    raise SystemExit(main())
