"""Render stage: every test camera and frame of one split at every LOD, as PNG plus alpha/depth OpenEXR.

A capture with true meshes (synthetic, gt_meshes.npz) also gets each LOD's splat centres and opacities over the
split's frames (lod{l}/splats.npz) for the evaluate stage's geometry error and correspondence drift.

Novel poses follow the paper (Section 4.1): the nearest training timestep by summed per-joint geodesic
distance feeds gamma(t) (Eq. 6) while the query pose drives the transport (Eqs. 2-3). Frames go through
pig.avatar.driver, which evaluates the field and the refiner once per avatar. Also times the per-frame
work (nearest timestep, body, transport, decoders, rasterization) per LOD for the LOD table.
"""
from __future__ import annotations

import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pig.avatar.driver import AvatarDriver
from pig.config import load_preset, load_section, resolve_device
from pig.data.capture_record import RECORD, capture_record
from pig.data.exr import write_exr
from pig.data.ground_truth import GT_MESHES, SPLATS, SplatTrack
from pig.field.precondition import bake_preconditioning
from pig.progress import progress_bar
from pig.render.api import RasterizerConfig, render_gaussians
from pig._cli import add_common_arguments, add_device_argument, add_preset_argument, run_cli, stage_parser
from pig._io import write_json, write_png
from pig._outputs import build_dir, claim_dir
from pig.stages.evaluate import EvaluateConfig

BLACK = (0.0, 0.0, 0.0)  # evaluation background (paper protocol: black, ground truth masked)


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU {platform.machine()}, torch threads={torch.get_num_threads()}"


def model_megabytes(model: torch.nn.Module, num_anchors: int, level_size: int) -> float:
    """Memory of the avatar a renderer of one LOD holds: per-anchor tensors (leading dim = N) count
    only the level's anchors, everything else (grid, decoders, refiner, per-frame parameters) in full.
    The body model is excluded: it is the shared SMPL-X file, not part of the fitted avatar."""
    shared = {id(t) for t in [*model.body_model.parameters(), *model.body_model.buffers()]}
    tensors = {id(t): t for t in [*model.parameters(), *model.buffers()] if id(t) not in shared}.values()
    total = 0.0
    for tensor in tensors:
        share = level_size / num_anchors if tensor.dim() and tensor.shape[0] == num_anchors else 1.0
        total += tensor.numel() * tensor.element_size() * share
    return total / 2**20


@dataclass
class CameraGroup:
    """Cameras of one image size, rendered in one rasterizer call."""

    names: list[str]
    width: int
    height: int
    viewmats: torch.Tensor  # (C, 4, 4)
    Ks: torch.Tensor  # (C, 3, 3)


class SplitRenderer:
    """Renders the avatar at a capture frame: the training timestep for training frames, else the
    nearest training timestep with the capture's pose driving the transport."""

    def __init__(self, model, capture, cameras: list[str], device: torch.device, rasterizer: RasterizerConfig):
        self.model, self.capture, self.device, self.rasterizer = model, capture, device, rasterizer
        self.driver = AvatarDriver(model)
        # One rasterizer call per image size: DNA-Rendering's two camera groups differ in resolution.
        by_size: dict[tuple[int, int], list[str]] = {}
        for name in cameras:
            by_size.setdefault((capture.cameras[name].width, capture.cameras[name].height), []).append(name)
        self.groups = [
            CameraGroup(
                names, width, height,
                torch.as_tensor(np.stack([capture.cameras[c].viewmat() for c in names]), dtype=torch.float32, device=device),
                torch.as_tensor(np.stack([capture.cameras[c].K for c in names]), dtype=torch.float32, device=device),
            )
            for (width, height), names in by_size.items()
        ]
        self.row_of_frame = {int(f): i for i, f in enumerate(capture.frames)}

    def timestep_and_pose(self, frame: int):
        if frame in self.model.frame_ids:
            return self.model.timestep_of_frame(frame), None
        pose = self.capture.params.select([self.row_of_frame[frame]])
        return self.driver.nearest_timestep(pose.full_pose[0]), pose

    @torch.no_grad()
    def gaussians(self, frame: int, lod: int) -> list[torch.Tensor]:
        """(means, quats, scales, opacities, sh) of the avatar at a capture frame, float32."""
        timestep, pose = self.timestep_and_pose(frame)
        full_pose, transl = (None, None) if pose is None else (pose.full_pose[0], pose.transl[0])
        return [t.float() for t in self.driver.gaussians(lod, full_pose, transl, timestep)]

    @torch.no_grad()
    def render(self, frame: int, lod: int, first_view_only: bool = False, gaussians: list[torch.Tensor] | None = None):
        """Yields (camera name, RenderResult of that group, index in the group) for every camera; `gaussians` of
        `frame` and `lod` may be given when the caller already has them."""
        gaussians = gaussians if gaussians is not None else self.gaussians(frame, lod)
        for group in self.groups[:1] if first_view_only else self.groups:
            views = slice(0, 1) if first_view_only else slice(None)
            result = render_gaussians(
                *gaussians, group.viewmats[views], group.Ks[views], group.width, group.height,
                torch.tensor(BLACK, device=self.device), backend=self.rasterizer.backend, max_pairs=self.rasterizer.max_pairs,
            )
            for index, name in enumerate(group.names[views]):
                yield name, result, index

    def seconds_per_frame(self, frames: list[int], lod: int, count: int) -> float:
        """Mean wall time of the whole per-frame work for one view, after one warm-up frame.

        Each frame is timed as a new pose (nearest timestep and decoders included); the per-LOD work the
        driver keeps (grid features, refiner) is not per-frame work."""
        chosen = frames[: count + 1]
        times = []
        for i, frame in enumerate(chosen):
            self.driver.forget_poses()
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            start = time.perf_counter()
            for _, result, _ in self.render(frame, lod, first_view_only=True):
                result.color.sum().item()  # forces completion on any device
            if i > 0 or len(chosen) == 1:
                times.append(time.perf_counter() - start)
        return float(np.mean(times))


def render_split(checkpoint: Path, capture_dir: Path, split: str, output: Path, cfg: EvaluateConfig,
                 rasterizer: RasterizerConfig, overwrite: bool = False) -> None:
    """Write `output`/lod{l}/... atomically; `output` may replace only an earlier render unless `overwrite`."""
    from pig.avatar.checkpoint import load_avatar, loss_terms
    from pig.avatar.losses import fit_note
    from pig.data.capture import Capture

    output = claim_dir(output, "render", (checkpoint, capture_dir), overwrite)
    capture = Capture.load(capture_dir)
    if split not in capture.split:
        raise KeyError(f"{capture_dir}/split.json: no split {split!r}; found {sorted(capture.split)}")
    cameras, frames = capture.split[split]["cameras"], [int(f) for f in capture.split[split]["frames"]]
    device = resolve_device(cfg.device)
    model = load_avatar(checkpoint, device, capture).eval()  # refuses an avatar of another capture
    note = fit_note(loss_terms(checkpoint)["lpips"])  # passed on to the evaluate stage's summaries and the tables
    bake_preconditioning(model)
    renderer = SplitRenderer(model, capture, cameras, device, rasterizer)
    track_splats = (capture_dir / GT_MESHES).is_file()  # for the evaluate stage's geometry error and drift
    levels = range(model.num_levels)
    with build_dir(output, "render") as tmp, \
            progress_bar(total=len(levels) * len(frames), desc=f"render {split}", unit="frame") as bar:
        write_json(tmp / RECORD, capture_record(capture))  # the capture these renders are for (evaluate checks it)
        for lod in levels:
            level_dir = tmp / f"lod{lod}"
            centres, opacities = [], []
            for frame in frames:
                gaussians = renderer.gaussians(frame, lod)
                if track_splats:
                    centres.append(gaussians[0].cpu().numpy())
                    opacities.append(gaussians[3].cpu().numpy())
                for cam, result, c in renderer.render(frame, lod, gaussians=gaussians):
                    write_png(level_dir / cam / f"{frame:08d}.png", result.color[c].cpu().numpy())
                    write_exr(level_dir / cam / f"{frame:08d}.exr",
                              {"A": result.alpha[c, ..., 0].cpu().numpy(), "Z": result.depth[c, ..., 0].cpu().numpy()})
                bar.update()
            if track_splats:
                order = np.argsort(frames)
                SplatTrack(np.asarray(frames)[order], np.stack(centres)[order], np.stack(opacities)[order]).save(
                    level_dir / SPLATS)
            seconds = renderer.seconds_per_frame(frames, lod, cfg.timing_frames)
            write_json(level_dir / "timing.json", {
                "splats": model.level_sizes[lod],
                "model_mb": model_megabytes(model, model.level_sizes[-1], model.level_sizes[lod]),
                "seconds_per_frame": seconds,
                "fps": 1.0 / seconds,
                "device": device_name(device),
                "width": renderer.groups[0].width,
                "height": renderer.groups[0].height,
                "fit_note": note,
            })


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("render", __doc__, "pig render --checkpoint results/synthetic/subject00/pig/avatar.pt --capture results/synthetic/subject00/capture "
                                             "--split novel_view --output results/synthetic/subject00/pig/renders/novel_view")
    parser.add_argument("--checkpoint", type=Path, required=True, help="avatar.pt of the fit stage")
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture directory")
    parser.add_argument("--split", required=True, choices=["novel_view", "novel_pose", "train"],
                        help="the capture's split to render (split.json)")
    parser.add_argument("--output", type=Path, required=True, help="renders/{split} directory to write")
    add_preset_argument(parser, "its evaluate and rasterizer sections")
    add_device_argument(parser, None, "the preset's evaluate.device")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --output folder that is not an earlier render of a split")
    args = parser.parse_args(argv)
    preset = load_preset(args.preset)
    cfg = load_section(preset, "evaluate", EvaluateConfig, {"device": args.device} if args.device else None)
    rasterizer = load_section(preset, "rasterizer", RasterizerConfig)
    render_split(args.checkpoint, args.capture, args.split, args.output, cfg, rasterizer, args.overwrite)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
