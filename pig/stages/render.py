"""Render stage: every test camera and frame of one split at every LOD (or those of `--lod`), as 8-bit lossless
chunks per camera.

Storage (pig.data.render_store): one file per (LOD, camera, run of frames), encoded on worker threads, and a
manifest; capture.json records the capture the views were rendered for (pig.data.capture_record). `--every-view`
also writes each view as a PNG with alpha and depth in an OpenEXR. A killed run resumes: only the missing chunks
are rendered again.

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
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from pig.avatar.driver import AvatarDriver
from pig.config import load_preset, load_section, resolve_device
from pig.data.capture_record import RECORD, capture_record
from pig.data.exr import write_exr
from pig.data.ground_truth import GT_MESHES, SPLATS, SplatTrack
from pig.data.render_store import FORMAT, ChunkEncoder, chunk_path, write_manifest
from pig.field.precondition import bake_preconditioning
from pig.progress import progress_bar
from pig.render.api import RasterizerConfig, render_gaussians
from pig._cli import add_common_arguments, add_device_argument, add_preset_argument, run_cli, stage_parser
from pig._io import write_json, write_png
from pig._outputs import claim_dir, resumable_dir
from pig.stages.evaluate import EvaluateConfig, add_encode_workers_argument, evaluate_section

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
        # On CUDA each frame is one captured graph (decoders included) instead of hundreds of launches: in run42 a
        # novel-view frame (one view) took ~19 ms, mostly launching. Captured as launched (no compilation to wait
        # for), decoding each frame's timestep (no decoded cache of every timestep: a frame decodes its own once).
        cuda = device.type == "cuda"
        self.driver = AvatarDriver(model, frame_graph=cuda, decoded_budget_bytes=0, compile_frames=False)
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

    @torch.no_grad()
    def gaussians(self, frame: int, lod: int) -> list[torch.Tensor]:
        """(means, quats, scales, opacities, sh) of the avatar at a capture frame, float32. On CUDA they are a frame
        graph's outputs, overwritten by the next frame at this LOD: render them first."""
        if frame in self.model.frame_ids:
            splats = self.driver.gaussians(lod, timestep=self.model.timestep_of_frame(frame))
        else:  # the nearest training timestep to the capture's pose
            pose = self.capture.params.select([self.row_of_frame[frame]])
            splats = self.driver.gaussians(lod, pose.full_pose[0], pose.transl[0])
        return [t.float() for t in splats]

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


def load_renderer(checkpoint: Path, capture, cameras: list[str], device: torch.device,
                  rasterizer: RasterizerConfig) -> tuple[SplitRenderer, dict, str]:
    """(renderer of `cameras`, the fit's loss terms, the checkpoint's SHA-256) from one read of `checkpoint`: a fit
    renaming a new checkpoint into place meanwhile cannot pair the renders with the new one's hash. Refuses an
    avatar of another capture."""
    from pig.avatar.checkpoint import read_avatar

    model, terms, checkpoint_sha256 = read_avatar(checkpoint, device, capture)
    bake_preconditioning(model)
    return SplitRenderer(model, capture, cameras, device, rasterizer), terms, checkpoint_sha256


def _to_u8(color: torch.Tensor) -> np.ndarray:
    """(..., H, W, 3) float in [0, 1] -> uint8, rounded as `write_png` rounds (half to even), on the render's device.

    A CUDA render comes back through page-locked memory from torch's caching host allocator: a fresh pageable array
    a view cost 3.3 ms of page faults and staged copying on an H200 (run40), most of the render stage's device time.
    The returned array keeps its block in use until the last view of it (an encoder's) is gone."""
    quantised = (color.clamp(0, 1) * 255).round().to(torch.uint8)
    if quantised.device.type != "cuda":
        return quantised.cpu().numpy()
    return torch.empty(quantised.shape, dtype=torch.uint8, pin_memory=True).copy_(quantised).numpy()


def chosen_levels(lods: list[int] | None, num_levels: int, checkpoint: Path) -> list[int]:
    """The avatar's LOD indices `lods` asks for, ascending (negative ones count from the finest, -1); all when None."""
    if lods is None:
        return list(range(num_levels))
    wrong = [lod for lod in lods if not -num_levels <= lod < num_levels]
    if wrong or not lods:
        raise ValueError(f"--lod {' '.join(map(str, lods))}: {checkpoint} has levels 0..{num_levels - 1} (or -1 for "
                         f"the finest, -{num_levels} for the coarsest); give at least one")
    return sorted({lod % num_levels for lod in lods})


def render_split(checkpoint: Path, capture_dir: Path, split: str, output: Path, cfg: EvaluateConfig,
                 rasterizer: RasterizerConfig, overwrite: bool = False, every_view: bool | None = None,
                 lods: list[int] | None = None) -> None:
    """Write `output`/lod{l}/{camera}/ chunks (pig.data.render_store), `output`/manifest.json and the capture's
    record `output`/capture.json; `output` may
    replace only an earlier render unless `overwrite`.

    Views are rendered a run of `cfg.chunk_frames` frames at a time, each frame at every LOD and camera, encoded on
    `cfg.encode_workers` threads. A killed run leaves its finished chunks beside `output`; a rerun with the same
    checkpoint, capture and settings renders only the missing ones. `every_view` (default `cfg.every_view`) also
    writes every view as {frame:08d}.png with alpha and depth in {frame:08d}.exr. `lods` (default: every LOD) limits
    the LODs rendered (`chosen_levels`): the evaluate stage finds only those."""
    from pig.avatar.losses import fit_note
    from pig.data.capture import Capture

    every_view = cfg.every_view if every_view is None else every_view
    output = claim_dir(output, "render", (checkpoint, capture_dir), overwrite)
    capture = Capture.load(capture_dir)
    if split not in capture.split:
        raise KeyError(f"{capture_dir}/split.json: no split {split!r}; found {sorted(capture.split)}")
    cameras, frames = capture.split[split]["cameras"], [int(f) for f in capture.split[split]["frames"]]
    device = resolve_device(cfg.device)
    renderer, terms, checkpoint_sha256 = load_renderer(checkpoint, capture, cameras, device, rasterizer)
    model = renderer.model
    note = fit_note(terms["lpips"])  # passed on to the evaluate stage's summaries and the tables
    track_splats = (capture_dir / GT_MESHES).is_file()  # for the evaluate stage's geometry error and drift
    levels = chosen_levels(lods, model.num_levels, checkpoint)
    chunks = [frames[i:i + cfg.chunk_frames] for i in range(0, len(frames), cfg.chunk_frames)]
    # Everything the chunks depend on: a rerun with any of it changed starts afresh.
    settings = {"checkpoint_sha256": checkpoint_sha256, "capture": capture.fingerprint(), "split": split,
                "chunk_format": FORMAT, "codec": cfg.render_codec, "chunk_frames": cfg.chunk_frames,
                "every_view": every_view, "rasterizer": asdict(rasterizer), "device": str(device), "levels": levels}
    with resumable_dir(output, "render", settings) as work, \
            progress_bar(total=len(levels) * len(frames), desc=f"render {split}", unit="frame") as bar:
        write_json(work / RECORD, capture_record(capture))  # the capture these renders are for (evaluate checks it)
        encoder = ChunkEncoder(cfg.render_codec, cfg.encode_workers)
        try:
            for chunk in chunks:
                todo = [lod for lod in levels if not _chunk_done(work / f"lod{lod}", cameras, chunk, track_splats)]
                bar.update(len(chunk) * (len(levels) - len(todo)))
                tracks = {lod: ([], []) for lod in todo}
                for frame in chunk:  # each frame once: every LOD and camera of it
                    for lod in todo:
                        level_dir = work / f"lod{lod}"
                        gaussians = renderer.gaussians(frame, lod)
                        if track_splats:
                            tracks[lod][0].append(gaussians[0].cpu().numpy())
                            tracks[lod][1].append(gaussians[3].cpu().numpy())
                        for cam, result, c in renderer.render(frame, lod, gaussians=gaussians):
                            if c == 0:  # one conversion and copy a camera group, whose views are one tensor
                                images = _to_u8(result.color)
                            image = images[c]
                            encoder.add(chunk_path(level_dir, cam, chunk[0]), frame, image)
                            if every_view:
                                write_png(level_dir / cam / f"{frame:08d}.png", image)
                                write_exr(level_dir / cam / f"{frame:08d}.exr", {
                                    "A": result.alpha[c, ..., 0].cpu().numpy(), "Z": result.depth[c, ..., 0].cpu().numpy()})
                        bar.update()
                for lod in todo:
                    if track_splats:  # before the chunks: a chunk present means its piece of the track is too
                        SplatTrack(np.asarray(chunk), np.stack(tracks[lod][0]), np.stack(tracks[lod][1])).save(
                            _track_piece(work / f"lod{lod}", chunk[0]))
                    for cam in cameras:
                        encoder.finish_chunk(chunk_path(work / f"lod{lod}", cam, chunk[0]), cam, lod)
        finally:
            encoder.close()
        for lod in levels:
            level_dir = work / f"lod{lod}"
            if track_splats:
                _join_track(level_dir, frames, chunks)
            if (level_dir / "timing.json").is_file():
                continue
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
        write_manifest(work, {"split": split, "cameras": cameras, "frames": frames, "levels": levels,
                              "chunk_frames": cfg.chunk_frames, "codec": cfg.render_codec, "every_view": every_view,
                              "checkpoint_sha256": settings["checkpoint_sha256"]})


def _track_piece(level_dir: Path, first_frame: int) -> Path:
    return level_dir / f".splats-{first_frame:08d}.npz"


def _chunk_done(level_dir: Path, cameras: list[str], chunk: list[int], track_splats: bool) -> bool:
    """Whether an earlier run wrote every camera's chunk of these frames (and the track's piece, or the whole
    track) at this LOD. Chunks are written atomically: one present is complete."""
    if not all(chunk_path(level_dir, cam, chunk[0]).is_file() for cam in cameras):
        return False
    return not track_splats or _track_piece(level_dir, chunk[0]).is_file() or (level_dir / SPLATS).is_file()


def _join_track(level_dir: Path, frames: list[int], chunks: list[list[int]]) -> None:
    """lod{l}/splats.npz, ascending frames, from the pieces of the chunks (removed once it is written)."""
    if (level_dir / SPLATS).is_file():
        return
    pieces = [SplatTrack.load(_track_piece(level_dir, chunk[0])) for chunk in chunks]
    order = np.argsort(frames)
    SplatTrack(np.asarray(frames)[order], np.concatenate([p.centres for p in pieces])[order],
               np.concatenate([p.opacities for p in pieces])[order]).save(level_dir / SPLATS)
    for chunk in chunks:
        _track_piece(level_dir, chunk[0]).unlink()


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
    add_encode_workers_argument(parser, "encode the views")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --output folder that is not an earlier render of a split")
    parser.add_argument("--lod", type=int, nargs="+", default=None,
                        help="LODs to render (default: all; -1 is the finest): a finest-only evaluation renders one")
    parser.add_argument("--every-view", action="store_true", default=None,
                        help="also write every view as PNG with alpha and depth in OpenEXR (evaluate.every_view)")
    args = parser.parse_args(argv)
    preset = load_preset(args.preset)
    cfg = evaluate_section(preset, args)
    rasterizer = load_section(preset, "rasterizer", RasterizerConfig)
    render_split(args.checkpoint, args.capture, args.split, args.output, cfg, rasterizer, args.overwrite,
                 args.every_view, args.lod)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
