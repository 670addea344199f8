"""Pose-driven frame rate per LOD: pose in, image out, through the model (old path) and pig.avatar.driver.

Times, as the median of --repeats frames after one warm-up, each frame with a new pose (a training pose
plus noise, so the nearest timestep changes):
- old: model.nearest_timestep + model.gaussians (grid at all anchors, refiner, body, transport, decoders) + raster;
- fast: AvatarDriver.gaussians with its per-pose caches cleared (nearest timestep and decoders run) + raster;
- fast, same timestep: a new pose near an already decoded timestep (the decoders are skipped);
- the fast frame's parts, each synchronised: nearest timestep, body, transport, decoders, assembly, raster;
- raster alone: the rasterizer on pre-computed splats of the same frames (for "same timestep": of those frames);
- real time: AvatarDriver(frame_graph=True).posed_frame (every timestep decoded once per LOD; on CUDA the frame
  is one compiled CUDA graph: pose -> nearest timestep -> body -> transport -> gather -> splats) + raster, against
  raster alone on its splats (the three timed in turn for each pose, so that clock drift weighs on each alike),
  and its image's mean absolute difference from the old path's (second table).
The device is synchronised around every timed call. Without --checkpoint the avatar is built from the
preset's sizes without a fit (the stand-in body, --timesteps random training poses): its decoders are
untrained, so the splats are random-ish and only the timings mean anything.

    python benchmarks/render_fps.py --device cuda                          # paper sizes, 1330 x 1150
    python benchmarks/render_fps.py --device cuda --checkpoint avatar.pt --precision bf16
    python benchmarks/render_fps.py --device cpu --anchors 4000 --width 160 --height 140 --repeats 3
    python benchmarks/render_fps.py --device cuda --precision bf16 --profile-frame 20   # + where a frame's time goes
    python benchmarks/render_fps.py --device cuda --precision bf16 --real-time-only --floor  # + the raster's settings
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from pig.avatar.config import AvatarConfig
from pig.avatar.driver import AvatarDriver
from pig.body.params import SmplxParams
from pig.config import load_preset, load_section
from pig.field.latent_grid import FieldConfig
from pig.field.precondition import PrecondConfig
from pig.render.api import render_gaussians
from pig.field.precondition import bake_preconditioning


def build_unfitted(profile: str, anchors: int | None, timesteps: int, seed: int = 0):
    """An avatar of the preset's sizes on the stand-in body, not fitted."""
    from pig.avatar.build import build_avatar
    from pig.body.standin import write_standin

    sections = load_preset(profile)
    cfg = load_section(sections, "avatar", AvatarConfig)
    if anchors:
        cfg = replace(cfg, num_anchors=anchors)
    rng = np.random.default_rng(seed)
    params = SmplxParams(rng.normal(scale=0.2, size=(timesteps, 55, 3)), np.zeros(10), np.zeros((timesteps, 10)),
                         np.zeros((timesteps, 3)))
    with tempfile.TemporaryDirectory() as tmp:
        write_standin(Path(tmp) / "body_model.npz")
        body = (Path(tmp) / "body_model.npz").read_bytes()
    spec = dict(avatar=asdict(cfg), field=asdict(load_section(sections, "field", FieldConfig)),
                precond=asdict(load_section(sections, "precond", PrecondConfig)), body_model_npz=body,
                params=asdict(params), frame_ids=list(range(timesteps)), variant="pig")
    torch.manual_seed(seed)
    return build_avatar(spec)


def framing_camera(model, width: int, height: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """A camera 3 m in front of the first training pose's body (+z, y up), the body filling 80% of the height."""
    with torch.no_grad():
        vertices = AvatarDriver(model).body(0)[0].float().cpu()
    centre = (vertices.max(0).values + vertices.min(0).values) / 2
    extent = float((vertices.max(0).values - vertices.min(0).values)[:2].max())
    distance = 3.0
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    viewmat[:3, 3] = -viewmat[:3, :3] @ centre + torch.tensor([0.0, 0.0, distance])
    focal = 0.8 * height * distance / extent
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return viewmat[None].to(device), K[None].to(device)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def median_ms(run, count: int, device: torch.device) -> float:
    """Median wall time [ms] of run(i) for i = 1..count, after run(0) as warm-up."""
    return interleaved_median_ms([run], count, device)[0]


def interleaved_median_ms(runs, count: int, device: torch.device) -> list[float]:
    """Median wall time [ms] of each run(i), the runs taken in turn for each i = 1..count (after i = 0 as
    warm-up), so that a drift of the clocks over the measurement weighs on all of them alike."""
    times = [[] for _ in runs]
    for i in range(count + 1):
        for run, kept in zip(runs, times):
            sync(device)
            start = time.perf_counter()
            run(i)
            sync(device)
            if i:
                kept.append(time.perf_counter() - start)
    return [1e3 * statistics.median(t) for t in times]


PARTS = ("nearest", "body", "transport", "decoders", "assemble", "raster")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cuda")
    parser.add_argument("--checkpoint", type=Path, help="avatar.pt of the fit stage (default: build without a fit)")
    parser.add_argument("--preset", default="paper", help="preset whose avatar, field and precond sizes to build")
    parser.add_argument("--anchors", type=int, help="number of anchors (default: the preset's)")
    parser.add_argument("--timesteps", type=int, default=100, help="training timesteps of a built avatar")
    parser.add_argument("--width", type=int, default=1330)
    parser.add_argument("--height", type=int, default=1150)
    parser.add_argument("--repeats", type=int, default=20, help="timed frames per measurement (median)")
    parser.add_argument("--precision", choices=["float32", "tf32", "bf16"], default="float32",
                        help="decoder MLPs: float32, TF32 matmuls (CUDA) or bf16 autocast")
    parser.add_argument("--threads", type=int, help="torch CPU threads")
    parser.add_argument("--real-time-only", action="store_true", help="only the real-time table (and --profile-frame)")
    parser.add_argument("--profile-frame", type=int, default=0, metavar="N",
                        help="after the real-time table: N frames of each LOD under torch.profiler, the graph's kernels "
                             "and the eager frame's operators by device time")
    parser.add_argument("--op-rows", type=int, default=15, help="rows of each --profile-frame table")
    parser.add_argument("--floor", action="store_true",
                        help="after the real-time table: gsplat's raster of the same splats under other settings "
                             "(packed, tile size, RGB only, opacity culling), CUDA only")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("--device cuda: no CUDA device (use --device cpu with small --anchors, --width, --height)", file=sys.stderr)
        return 2

    if args.checkpoint:
        from pig.avatar.checkpoint import load_avatar

        model, source = load_avatar(args.checkpoint), f"checkpoint {args.checkpoint}"
    else:
        model = build_unfitted(args.preset, args.anchors, args.timesteps)
        source = f"preset {args.preset}, not fitted (untrained decoders: random-ish splats, timings only)"
    bake_preconditioning(model)  # as the render stage does: no anchor or grid solve on either path
    model = model.to(device).eval()
    if args.precision == "tf32":
        torch.backends.cuda.matmul.allow_tf32 = True
    model.decoder.set_precision("bf16" if args.precision == "bf16" else "float32")
    viewmat, K = framing_camera(model, args.width, args.height, device)
    background = torch.zeros(3, device=device)

    def raster(splats):
        return render_gaussians(*splats, viewmat, K, args.width, args.height, background).color

    rng = np.random.default_rng(1)
    train = model.pose_init.cpu().double().numpy()
    picks = rng.integers(0, model.num_timesteps, args.repeats + 1)
    poses = [train[t] + rng.normal(scale=0.05, size=(55, 3)) for t in picks]
    transl = model.transl[0].cpu().double().numpy()
    rows = [SmplxParams(p[None], model.betas_init.cpu().numpy(), model.expression[:1].cpu().numpy(), transl[None]) for p in poses]

    print(f"{source}; {model.level_sizes[-1]} anchors, {model.num_levels} levels, SH {model.cfg.sh_degree}, decoders "
          f"{model.cfg.hidden_layers}x{model.cfg.hidden_width}, {model.num_timesteps} training timesteps; {args.width} x "
          f"{args.height}; {args.device} ({torch.cuda.get_device_name(device) if device.type == 'cuda' else f'{torch.get_num_threads()} threads'}); "
          f"decoders {args.precision}; median of {args.repeats} frames [ms]")
    if args.real_time_only:
        with torch.no_grad():
            driver = real_time_table(model, poses, rows, transl, raster, args.repeats, device)
            if args.profile_frame:
                profile_frames(driver, poses, transl, args.profile_frame, args.op_rows, device)
            if args.floor and device.type == "cuda":
                floor_table(driver, poses, transl, (viewmat, K, args.width, args.height), args.repeats, device)
        return 0
    header = (f"| LOD | splats | old | fast | fast FPS | {' | '.join(PARTS)} | raster alone | fast / raster | "
              f"same-t fast | same-t / raster | old / fast |")
    print(header + "\n|" + "---|" * (header.count("|") - 1))
    driver = AvatarDriver(model)
    with torch.no_grad():
        for lod in range(model.num_levels):
            def old(i):
                t = model.nearest_timestep(poses[i])
                raster([s.float() for s in model.gaussians(t, lod, rows[i])])

            def fast(i):
                driver.forget_poses()
                raster([s.float() for s in driver.gaussians(lod, poses[i], transl)])

            old_ms = median_ms(old, args.repeats, device)
            driver.gaussians(lod, poses[0], transl)  # the per-LOD work, once
            fast_ms = median_ms(fast, args.repeats, device)
            same_t = model.nearest_timestep(poses[0])
            same_ms = median_ms(lambda i: raster([s.float() for s in driver.gaussians(lod, poses[i], transl, same_t)]),
                                args.repeats, device)

            parts = {name: [] for name in PARTS}
            frame_splats = []  # each frame's splats: the raster's cost depends on them (untrained decoders: on t)
            for i in range(args.repeats + 1):
                driver.forget_poses()
                marks = []

                def mark():
                    sync(device)
                    marks.append(time.perf_counter())

                mark()
                t = driver.nearest_timestep(poses[i])
                mark()
                vertices = driver.body(t, poses[i], transl)
                mark()
                centres, rotation = driver.transport(lod, vertices)
                mark()
                decoded = driver.decoded(lod, t)
                mark()
                g = driver.splats(centres, rotation, decoded)
                splats = [x[0].float() for x in (g.means, g.quats, g.scales, g.opacities, g.sh)]
                mark()
                raster(splats)
                mark()
                frame_splats.append(splats)
                if i:
                    for name, a, b in zip(PARTS, marks, marks[1:]):
                        parts[name].append(1e3 * (b - a))
            alone_ms = median_ms(lambda i: raster(frame_splats[i]), args.repeats, device)
            same_splats = [[s.float() for s in driver.gaussians(lod, p, transl, same_t)] for p in poses]
            same_alone_ms = median_ms(lambda i: raster(same_splats[i]), args.repeats, device)
            del frame_splats, same_splats
            cells = " | ".join(f"{statistics.median(parts[name]):.2f}" for name in PARTS)
            print(f"| {lod} | {model.level_sizes[lod]} | {old_ms:.2f} | {fast_ms:.2f} | {1e3 / fast_ms:.1f} | {cells} | "
                  f"{alone_ms:.2f} | {fast_ms / alone_ms:.2f} | {same_ms:.2f} | {same_ms / same_alone_ms:.2f} | "
                  f"{old_ms / fast_ms:.2f} |", flush=True)
        driver = real_time_table(model, poses, rows, transl, raster, args.repeats, device)
        if args.profile_frame:
            profile_frames(driver, poses, transl, args.profile_frame, args.op_rows, device)
    return 0


def profile_frames(driver: AvatarDriver, poses, transl, count: int, rows: int, device: torch.device) -> None:
    """Where a real-time frame's device time goes, per LOD: the captured graph's kernels (as replayed), then the
    same frame function run eagerly, whose operator names say which part of the frame a cost belongs to."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    sort = "cuda_time_total" if device.type == "cuda" else "cpu_time_total"
    for lod in range(driver.model.num_levels):
        if not driver.frame_graph_fits(lod):
            continue
        query = [driver._pose(p) for p in poses[:count]]
        translation = driver._transl(transl)
        for label, run in (("graph replay", lambda i: driver.posed_frame(lod, poses[i], transl)),
                           ("eager frame", lambda i: driver._frame(lod, query[i], translation))):
            run(0)
            sync(device)
            with profile(activities=activities) as prof:
                for i in range(count):
                    run(i)
                sync(device)
            events = prof.key_averages()
            kernels = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
            kernel_us = sum(e.device_time_total for e in kernels) / count
            launched = sum(e.count for e in kernels) / count
            print(f"\nLOD {lod} {label}, {count} frames: {launched:.0f} kernels and {kernel_us / 1e3:.3f} ms of kernel time "
                  f"per frame")
            print(events.table(sort_by=sort, row_limit=rows, max_name_column_width=60))


FLOOR_VARIANTS = {  # name: (gsplat.rasterization keywords over the render stage's, drop splats below 1/255 opacity)
    "as rendered (unpacked, tile 16, RGB+ED)": ({}, False),
    "packed": ({"packed": True}, False),
    "tile 8": ({"tile_size": 8}, False),
    "tile 32": ({"tile_size": 32}, False),
    "RGB only": ({"render_mode": "RGB"}, False),
    "opacity >= 1/255 only": ({}, True),
}


def floor_table(driver: AvatarDriver, poses, transl, camera, repeats: int, device: torch.device) -> None:
    """Where the raster floor itself can drop: gsplat on each LOD's real-time splats under the settings of
    FLOOR_VARIANTS, timed in turn per pose, with each image's mean absolute difference from the render stage's."""
    from gsplat import rasterization

    from pig.render.projection import EPS2D, FAR_PLANE, NEAR_PLANE

    viewmat, K, width, height = camera
    # No `backgrounds`: the benchmark's is black, which adds nothing, and gsplat 1.5.3's packed path rejects one.
    base = dict(near_plane=NEAR_PLANE, far_plane=FAR_PLANE, eps2d=EPS2D, packed=False, render_mode="RGB+ED",
                rasterize_mode="classic")

    def raster(splats, options, cull):
        means, quats, scales, opacities, sh = splats
        if cull:  # selected outside the timed call would hide its cost; inside it costs a host sync
            keep = opacities >= 1 / 255
            means, quats, scales, opacities, sh = (x[keep] for x in splats)
        degree = round(sh.shape[1] ** 0.5) - 1
        image, _, _ = rasterization(means, quats, scales, opacities, sh, viewmat, K, width, height,
                                    sh_degree=degree, **{**base, **options})
        return image[0, ..., :3]

    print(f"\nRaster floor: gsplat on the real-time frame's splats, median of {repeats} frames [ms]; ratio and image "
          f"MAD against the render stage's settings")
    names = list(FLOOR_VARIANTS)
    header = "| LOD | splats | kept at 1/255 | " + " | ".join(names) + " |"
    print(header + "\n|" + "---|" * (header.count("|") - 1))
    for lod in range(driver.model.num_levels):
        if not driver.frame_graph_fits(lod):
            continue
        kept = [[x.clone() for x in driver.posed_frame(lod, p, transl)[0]] for p in poses]
        runs = [lambda i, v=FLOOR_VARIANTS[name]: raster(kept[i], *v) for name in names]
        times = interleaved_median_ms(runs, repeats, device)
        reference = raster(kept[0], *FLOOR_VARIANTS[names[0]])
        cells = []
        for name, ms in zip(names, times):
            mad = float((raster(kept[0], *FLOOR_VARIANTS[name]) - reference).abs().mean())
            cells.append(f"{ms:.3f} ({ms / times[0]:.2f}x, {mad:.1e})")
        fraction = float((kept[0][3] >= 1 / 255).float().mean())
        print(f"| {lod} | {driver.model.level_sizes[lod]} | {fraction:.3f} | " + " | ".join(cells) + " |", flush=True)
        del kept


def real_time_table(model, poses, rows, transl, raster, repeats: int, device: torch.device) -> AvatarDriver:
    """The real-time path per LOD: frame time, raster alone on its splats, image parity with the old path."""
    print(f"\nReal-time path (AvatarDriver frame_graph=True), median of {repeats} frames [ms]; set-up = decoding every "
          f"timestep at the LOD + compiling + capturing, once")
    header = "| LOD | splats | frame | FPS | pose -> splats | raster alone | frame / raster alone | image MAD vs old | set-up s |"
    print(header + "\n|" + "---|" * (header.count("|") - 1))
    driver = AvatarDriver(model, frame_graph=True)
    for lod in range(model.num_levels):
        if not driver.frame_graph_fits(lod):
            print(f"| {lod} | {model.level_sizes[lod]} | decoded timesteps take {driver.decoded_all_bytes(lod) / 2**30:.1f} GiB, "
                  f"over the budget |")
            continue
        sync(device)
        start = time.perf_counter()
        driver.posed_frame(lod, poses[0], transl)
        sync(device)
        setup_s = time.perf_counter() - start
        kept = [[x.clone() for x in driver.posed_frame(lod, p, transl)[0]] for p in poses]
        frame_ms, splats_ms, alone_ms = interleaved_median_ms(
            [lambda i: raster(driver.posed_frame(lod, poses[i], transl)[0]), lambda i: driver.posed_frame(lod, poses[i], transl),
             lambda i: raster(kept[i])], repeats, device)
        differences = []
        for i in range(min(repeats + 1, 5)):
            t = model.nearest_timestep(poses[i])
            reference = raster([s.float() for s in model.gaussians(t, lod, rows[i])])
            differences.append(float((raster(kept[i]) - reference).abs().mean()))
        del kept
        print(f"| {lod} | {model.level_sizes[lod]} | {frame_ms:.3f} | {1e3 / frame_ms:.0f} | {splats_ms:.3f} | "
              f"{alone_ms:.3f} | {frame_ms / alone_ms:.2f} | {max(differences):.2e} | {setup_s:.1f} |", flush=True)
    return driver


if __name__ == "__main__":
    sys.exit(main())
