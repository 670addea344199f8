"""The render stage's avatar frames on an unfitted avatar of a preset's sizes: each LOD's frame through the stage's
driver (`AvatarDriver(frame_graph=True, decoded_budget_bytes=0, compile_frames=False)`: on CUDA one CUDA graph
captured as launched, decoding its timestep) against the launched driver the stage used before, for training
timesteps (the novel-view split's frames) and for poses near them (novel pose), the two timed in turn on each frame
with the device synchronised around each (median), and the largest difference of their splats. No capture or fit is
needed, so it runs in a minute of a GPU hold.

    python benchmarks/stage_frames.py --device cuda --timesteps 1000 --frames 20
    python benchmarks/stage_frames.py --device cpu --anchors 4000 --timesteps 20 --frames 3
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from pig.avatar.driver import AvatarDriver
from pig.field.precondition import bake_preconditioning

sys.path.insert(0, str(Path(__file__).parent))
from render_fps import build_unfitted, interleaved_median_ms  # noqa: E402


def fresh(driver: AvatarDriver) -> AvatarDriver:
    driver.forget_poses()
    return driver


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cuda")
    parser.add_argument("--preset", default="paper", help="preset whose avatar, field and precond sizes to build")
    parser.add_argument("--anchors", type=int, help="number of anchors (default: the preset's)")
    parser.add_argument("--timesteps", type=int, default=1000, help="training timesteps (THuman4's half: 1000)")
    parser.add_argument("--frames", type=int, default=20, help="timed frames per LOD and kind (median)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("--device cuda: no CUDA device", file=sys.stderr)
        return 2
    torch.manual_seed(0)
    model = build_unfitted(args.preset, args.anchors, args.timesteps)
    bake_preconditioning(model)  # as the render stage does
    model = model.to(device).eval()
    stage = AvatarDriver(model, frame_graph=True, decoded_budget_bytes=0, compile_frames=False)
    launched = AvatarDriver(model)
    rng = np.random.default_rng(0)
    steps = rng.integers(0, model.num_timesteps, args.frames + 1).tolist()
    train = model.pose_init.cpu().double().numpy()
    poses = [train[t] + rng.normal(scale=0.05, size=(55, 3)) for t in steps]
    transl = rng.normal(scale=0.1, size=3)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    print(f"preset {args.preset}, not fitted; {model.level_sizes[-1]} anchors, {model.num_levels} levels, decoders "
          f"{model.cfg.hidden_layers}x{model.cfg.hidden_width}, {model.num_timesteps} timesteps; {name}; median of "
          f"{args.frames} frames [ms], the stage's driver and the launched one in turn")
    header = ("| LOD | splats | training: stage | launched | stage / launched | pose: stage | launched | "
              "stage / launched | max abs difference |")
    print(header + "\n|" + "---|" * (header.count("|") - 1))
    with torch.no_grad():
        for lod in range(model.num_levels):
            gap = 0.0
            for t, pose in zip(steps[:3], poses[:3]):  # the first call of each path also captures its graph
                pairs = [(stage.gaussians(lod, timestep=t), launched.gaussians(lod, timestep=t))]
                ours = [x.clone() for x in stage.gaussians(lod, pose, transl)]
                pairs.append((ours, launched.gaussians(lod, pose, transl)))
                gap = max(gap, max(float((a - b).abs().max()) for ours_, theirs in pairs for a, b in zip(ours_, theirs)))
            # Each launched frame decodes afresh, as a split's frames do (its cache of recent timesteps emptied).
            training = interleaved_median_ms([lambda i: stage.gaussians(lod, timestep=steps[i]),
                                              lambda i: fresh(launched).gaussians(lod, timestep=steps[i])],
                                             args.frames, device)
            posed = interleaved_median_ms([lambda i: stage.gaussians(lod, poses[i], transl),
                                           lambda i: fresh(launched).gaussians(lod, poses[i], transl)],
                                          args.frames, device)
            print(f"| {lod} | {model.level_sizes[lod]} | {training[0]:.2f} | {training[1]:.2f} | "
                  f"{training[0] / training[1]:.3f} | {posed[0]:.2f} | {posed[1]:.2f} | {posed[0] / posed[1]:.3f} | "
                  f"{gap:.2e} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
