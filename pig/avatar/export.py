"""Export of a fitted avatar as standard 3DGS point clouds (.ply): canonical, and per frame of a motion with
dense correspondences between the frames.

Each .ply is binary little-endian with one `vertex` element of float32 properties, in the layout of the
INRIA 3DGS code that its viewer, SuperSplat and gsplat's exporter read:
    x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..3(K-1)-1, opacity, scale_0..2, rot_0..3,
and two header comments naming its up axis: `comment up_axis +y` (the signed coordinate axis nearest to it) and
`comment up X Y Z` (the unit vector). `format` "splat" (antimatter15's viewer) and "ply_compressed" (SuperSplat's
chunk-quantised PLY, `.compressed.ply`) are gsplat's exporter's compact forms instead: they sort the splats along a
Morton curve (and the compressed PLY drops splats under opacity 1/255), so their rows are not anchor ids; the
correspondences keep the anchor order. A .splat file has no header: its up axis is in the sidecar only.
From the renderer's conventions (pig.render.api):
- colour: our sh (n, K, 3), K = (d+1)^2, are coefficients of the same real SH basis as 3DGS's (gsplat's,
  which is the INRIA rasterizer's: Y_0^0 = SH_C0 = 0.28209479, Y_1^{-1} = -0.48860251 y, ...), evaluated on
  the direction from the camera centre to the splat, colour = max(sum_k Y_k sh_k + 0.5, 0) in both. So the
  coefficients are written unchanged: f_dc_c = sh[:, 0, c] (3DGS's colour of the DC term alone is
  SH_C0 * f_dc + 0.5, as ours), and f_rest channel-major, f_rest_{c (K-1) + k - 1} = sh[:, k, c] for k >= 1.
- opacity: the logit of our opacity in (0, 1) (3DGS applies a sigmoid), the opacity clipped to
  [2^-24, 1 - 2^-24] first so that a saturated 0 or 1 gets a finite logit (|logit| <= 16.7); the clipping
  is below float32 resolution near 1 and far below the 1/255 at which rasterizers drop a splat.
- scale_i: the log of our linear scales (3DGS applies exp), floored at the smallest normal float32.
- rot_0..3: our unit quaternion wxyz, re-normalised (3DGS's rot_0 is w too).
- x y z: splat centres in the capture's world frame.
Non-finite or degenerate splats are an error, not dropped: row i of every file is anchor i of the avatar,
whose anchors are ordered so that each level of detail is a prefix of the next.

Poses: the canonical cloud is the avatar at rest, zero body pose and zero translation, decoded with training
timestep 0's time embedding gamma(0) and expression and the fitted (refined) shape; its root orientation turns
the rest body's up (+y, SMPL-X's) to the coordinate axis nearest the capture's up, so it stands as the capture's
subject does (zero, the identity, for a y-up capture). A motion is first brought into the capture's frame exactly
as the animate stage does (`capture_motion`: the selected frames rotated to the capture's up axis, centred over
the capture's subject, the clip's lowest vertex on the capture's ground). A frame's pose and translation then
drive the transport (Eqs. 2-3) while the nearest training timestep by summed per-joint geodesic distance feeds
gamma(t) (Eq. 6), as the render stage does for novel poses; its expression is that timestep's, its shape the
avatar's own (a motion's betas are not used).

Writes OUTPUT/canonical.ply and, with a motion, OUTPUT/frame_{i:06d}.ply for each selected motion frame i
and OUTPUT/correspondences.npz: `anchor_ids` (n,) int64, `frames` (F,) int64 motion frame indices,
`timesteps` (F,) int64 the training timesteps whose gamma(t) decoded them, `positions` (F, n, 3) float32
(row j is the xyz of anchor_ids[j] in frame_{frames[f]}.ply), `lod` (int64 scalar). The sidecar
OUTPUT/export.json records each file's up axis, the capture's ground height along it and centre, the format
and the level (other suffixes than .ply with the compact formats).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from pig.body.motion import check_translations
from pig.field.precondition import bake_preconditioning
from pig._io import atomic_path, write_json
from pig._outputs import build_dir, claim_dir

STAGE = "export"
OPACITY_CLIP = 2.0**-24  # float32 spacing just below 1: 1 - 2^-24 is the largest float32 under 1
SCALE_FLOOR = float(np.finfo(np.float32).tiny)
FRAMES_FORM = "START:STOP[:STEP] with integers 0 <= START < STOP and STEP >= 1 (STOP excluded), e.g. 0:100:2"


def ply_properties(sh_degree: int) -> list[str]:
    """Names of the vertex properties, in file order, of a 3DGS .ply with SH up to `sh_degree`."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def splat_table(means, quats, scales, opacities, sh, what: str = "splats") -> np.ndarray:
    """The .ply vertex records (structured float32 array, fields `ply_properties`) of n splats in the renderer's
    conventions: means (n, 3), quats (n, 4) wxyz, scales (n, 3) linear, opacities (n,) in [0, 1], sh (n, K, 3).
    `what` names the splats in errors."""
    means, quats, scales, opacities, sh = (np.asarray(torch.as_tensor(a).detach().cpu().double())
                                           for a in (means, quats, scales, opacities, sh))
    n = means.shape[0]
    degree = round(np.sqrt(sh.shape[1])) - 1 if sh.ndim == 3 else 0
    shapes = {"means": (means.shape, (n, 3)), "quats": (quats.shape, (n, 4)), "scales": (scales.shape, (n, 3)),
              "opacities": (opacities.shape, (n,)), "sh": (sh.shape, (n, (degree + 1) ** 2, 3))}
    for name, (found, expected) in shapes.items():
        if found != expected:
            raise ValueError(f"{what}: {name} of shape {found}; expected {expected} for {n} splats "
                             "(sh: (n, (d+1)^2, 3))")
    norms = np.linalg.norm(quats, axis=1)
    finite = np.isfinite(np.concatenate([means, quats, scales, opacities[:, None], sh.reshape(n, -1)], axis=1)).all(1)
    bad = ~finite | ~(norms > 0) | (scales < 0).any(1) | (opacities < 0) | (opacities > 1)
    if bad.any():
        raise ValueError(f"{what}: {int(bad.sum())} of {n} splats are invalid (NaN or inf, a zero quaternion, a "
                         f"negative scale or an opacity outside [0, 1]), the first is splat {int(np.argmax(bad))}; "
                         "nothing was written")
    alpha = np.clip(opacities, OPACITY_CLIP, 1.0 - OPACITY_CLIP)
    columns = [means, np.zeros((n, 3)), sh[:, 0, :], sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1),
               np.log(alpha / (1.0 - alpha))[:, None], np.log(np.maximum(scales, SCALE_FLOOR)), quats / norms[:, None]]
    values = np.ascontiguousarray(np.concatenate(columns, axis=1), dtype="<f4")
    return values.view([(name, "<f4") for name in ply_properties(degree)])[:, 0]


def nearest_axis(up) -> str:
    """The signed coordinate axis ("+x", "-y", ...) nearest to the direction `up`."""
    up = np.asarray(up, dtype=np.float64)
    index = int(np.argmax(np.abs(up)))
    return ("+" if up[index] > 0 else "-") + "xyz"[index]


def up_comments(up) -> list[str]:
    """The PLY header comments that name a file's up axis (module docstring)."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return [f"comment up_axis {nearest_axis(up)}", "comment up " + " ".join(f"{v:.9f}" for v in up)]


def write_splat_ply(path: str | Path, means, quats, scales, opacities, sh, what: str = "splats", up=None) -> None:
    """Write n splats (conventions of `splat_table`) as a binary little-endian 3DGS .ply, atomically; with `up`
    (3,), the header names it (`up_comments`)."""
    table = splat_table(means, quats, scales, opacities, sh, what)
    header = ["ply", "format binary_little_endian 1.0", *(up_comments(up) if up is not None else []),
              f"element vertex {len(table)}"]
    header += [f"property float {name}" for name in table.dtype.names] + ["end_header"]
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(table.tobytes())


FORMATS = {"ply": ".ply", "splat": ".splat", "ply_compressed": ".compressed.ply"}  # format -> file suffix


def write_splats(path: str | Path, gaussians, fmt: str, up, what: str = "splats") -> None:
    """Write splats (`splat_table`'s conventions) in format `fmt` (FORMATS), atomically, with up axis `up`."""
    if fmt == "ply":
        write_splat_ply(path, *gaussians, what=what, up=up)
        return
    from gsplat.exporter import export_splats

    table = splat_table(*gaussians, what=what)  # the checks and the 3DGS activations (logit, log) of the .ply

    def column(*names: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([table[name] for name in names], axis=1))

    rest = [name for name in table.dtype.names if name.startswith("f_rest_")]
    sh_rest = column(*rest).reshape(len(table), 3, -1).transpose(1, 2) if rest else torch.zeros(len(table), 0, 3)
    # One torch thread: the exporter's work is small per-chunk operations, where more threads only spin-wait
    # (12x slower with 2 threads on the loaded 2-core machine, benchmarks/NOTES.md).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        data = export_splats(column("x", "y", "z"), column("scale_0", "scale_1", "scale_2"),
                             column("rot_0", "rot_1", "rot_2", "rot_3"), column("opacity")[:, 0],
                             column("f_dc_0", "f_dc_1", "f_dc_2")[:, None], sh_rest, format=fmt)
    finally:
        torch.set_num_threads(threads)
    if fmt == "ply_compressed":  # the comments go after the format line, as in our .ply
        magic, form, rest_of_file = data.split(b"\n", 2)
        data = b"\n".join([magic, form, *(line.encode("ascii") for line in up_comments(up)), rest_of_file])
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def parse_frames(spec: str | None) -> slice | None:
    """The slice of "START:STOP[:STEP]" (STOP excluded; None: None, every frame); ValueError on any other form."""
    if spec is None:
        return None
    match = re.fullmatch(r"\s*(\d+):(\d+)(?::(\d+))?\s*", spec)
    if match is None:
        raise ValueError(f"--frames {spec!r}: expected {FRAMES_FORM}")
    start, stop, step = int(match[1]), int(match[2]), int(match[3] or 1)
    if start >= stop or step < 1:
        raise ValueError(f"--frames {spec!r} selects no frame; expected {FRAMES_FORM}")
    return slice(start, stop, step)


def frame_selection(spec: str | None, count: int, source: str) -> np.ndarray:
    """Motion frame indices chosen by `spec` ("START:STOP[:STEP]", STOP excluded; None: all `count` frames) of
    the motion `source`, which has `count` frames."""
    frames = parse_frames(spec)
    if frames is None:
        return np.arange(count)
    if frames.stop > count:
        raise ValueError(f"--frames {spec!r}: {source} has {count} frames (0..{count - 1}), so STOP may be at most "
                         f"{count}")
    return np.arange(frames.start, frames.stop, frames.step)


def _checked_motion(poses, transl, source: str) -> tuple[np.ndarray, np.ndarray]:
    poses, transl = np.asarray(poses), np.asarray(transl)
    if poses.ndim != 3 or poses.shape[1:] != (55, 3) or len(poses) == 0:
        raise ValueError(f"{source}: full pose of shape {poses.shape}; expected (N, 55, 3) SMPL-X axis-angles, N >= 1")
    if transl.shape != (len(poses), 3):
        raise ValueError(f"{source}: translation of shape {transl.shape}; expected ({len(poses)}, 3), one per pose")
    for name, values in (("full pose", poses), ("translation", transl)):
        if not np.issubdtype(values.dtype, np.number) or np.issubdtype(values.dtype, np.complexfloating):
            raise ValueError(f"{source}: {name} of dtype {values.dtype}; expected real numbers")
        bad = ~np.isfinite(values.reshape(len(values), -1)).all(1)
        if bad.any():
            raise ValueError(f"{source}: {name} holds NaN or inf in {int(bad.sum())} frames, the first is frame "
                             f"{int(np.argmax(bad))}")
    check_translations(transl, source)
    return poses.astype(np.float64), transl.astype(np.float64)


@torch.no_grad()
def posed_gaussians(model, timestep: int, lod: int, full_pose, transl) -> tuple[torch.Tensor, ...]:
    """(means, quats, scales, opacities, sh) of level `lod` with `full_pose` (55, 3) and `transl` (3,) driving the
    transport and training timestep `timestep` feeding gamma(t)."""
    device = model.pose_init.device
    poses = torch.as_tensor(np.asarray(full_pose).reshape(1, 55, 3), device=device)
    translation = torch.as_tensor(np.asarray(transl).reshape(1, 3), device=device)
    g = model(torch.tensor([timestep]), lod, poses, translation)
    return g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0]


def capture_motion(motion, body_model, betas, capture: tuple, frames: str | None = None, fps: float | None = None,
                   up: str | None = None):
    """(clip, chosen): the Motion `motion` as the animate and export stages drive an avatar with it, and the indices
    of its source's frames that the clip's rows are (`Motion.source_frames`: a clip read with only some frames keeps
    the file's indices). The frames `frames` selects ("START:STOP[:STEP]", default all),
    resampled to `fps` (default: the clip's own rate; else `chosen` is None), brought into the capture's frame by
    pig.body.motion.align_motion with the avatar's `body_model` and refined shape `betas`; `capture` is
    pig.body.motion.capture_frame's (up, ground, centre) of the avatar, `up` (e.g. "+y") overrides its axis."""
    from pig.body.motion import align_motion

    if frames is not None:
        chosen = frame_selection(frames, motion.num_frames, motion.source)
        step = int(chosen[1] - chosen[0]) if len(chosen) > 1 else 1
        motion = motion.select(slice(int(chosen[0]), int(chosen[-1]) + 1, step))
    chosen = motion.source_frames
    if fps is not None:
        motion, chosen = motion.resample(fps), None
    return align_motion(motion, body_model, betas, *capture, up), chosen


def export_avatar(checkpoint: str | Path, output: str | Path, lod: int | None = None, poses=None, transl=None,
                  frames: str | None = None, motion_source: str | Path | None = None, device: str | torch.device = "cpu",
                  overwrite: bool = False, up: str | None = None, fmt: str = "ply") -> Path:
    """Write the export folder `output` (see the module docstring) of the avatar in `checkpoint` at level `lod`
    (default: the finest); with a motion, `poses` (N, 55, 3) and `transl` (N, 3) or else the motion file
    `motion_source` (read by pig.body.motion.read_motion, any of its layouts), also the frames `frames` selects
    ("START:STOP[:STEP]", default all), in the capture's frame (`up`, e.g. "+y", overrides its up axis). `fmt`:
    a key of FORMATS. `output` may replace only an earlier export unless `overwrite`; nothing is written unless
    every check passes. Returns `output`."""
    from pig.avatar.checkpoint import load_avatar
    from pig.avatar.driver import AvatarDriver
    from pig.body.motion import Motion, capture_frame, parse_axis, read_motion, rotation_between
    from pig.body.rotation import matrix_to_axis_angle

    checkpoint, output, source = Path(checkpoint), Path(output), str(motion_source or "the motion")
    if fmt not in FORMATS:
        raise ValueError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if up is not None:
        parse_axis(up)  # a bad axis is an error before anything is read
    if (poses is None) != (transl is None):
        raise ValueError("export: a motion needs both its poses and its translations")
    has_motion = poses is not None or motion_source is not None
    if not has_motion and frames is not None:
        raise ValueError(f"--frames {frames!r} selects frames of a motion; give one with --motion FILE")
    inputs = [checkpoint] + ([Path(motion_source)] if motion_source is not None else [])
    output = claim_dir(output, STAGE, inputs, overwrite)
    model = load_avatar(checkpoint, device)
    motion = None
    selection = frames
    if poses is None and motion_source is not None:  # only the frames asked for are read
        motion = read_motion(motion_source, hands_mean=model.body_model.hands_mean.cpu().numpy(),
                             frames=parse_frames(frames))
        selection = None
    elif poses is not None:
        motion = Motion(*_checked_motion(poses, transl, source), fps=30.0, source=source)  # fps unused: no resampling
    if lod is None:
        lod = model.num_levels - 1
    if not 0 <= lod < model.num_levels:
        raise ValueError(f"--lod {lod}: {checkpoint} has levels of detail 0..{model.num_levels - 1} "
                         f"({', '.join(map(str, model.level_sizes))} splats)")
    capture = capture_frame(model)
    capture_up, ground, centre = capture
    if up is not None:
        capture_up = parse_axis(up)
    # The rest body turned from SMPL-X's +y to the capture's nearest axis: the identity for a y-up capture.
    canonical_up = parse_axis(nearest_axis(capture_up))
    canonical_pose = np.zeros((55, 3))
    canonical_pose[0] = matrix_to_axis_angle(torch.from_numpy(rotation_between([0.0, 1.0, 0.0], canonical_up))).numpy()
    if motion is not None:
        motion, chosen = capture_motion(motion, model.body_model, AvatarDriver(model).refined()[0], capture,
                                        selection, up=up)
    bake_preconditioning(model)  # the anchors' value once, not a solve per frame
    suffix = FORMATS[fmt]
    record = {"format": fmt, "lod": lod, "splats": model.level_sizes[lod], "checkpoint": str(checkpoint),
              "motion": str(motion_source) if motion_source is not None else None,
              "up": capture_up, "up_axis": nearest_axis(capture_up), "ground": ground, "centre": centre,
              "files": {f"canonical{suffix}": {"pose": "rest", "up": canonical_up, "up_axis": nearest_axis(canonical_up)}}}
    with build_dir(output, STAGE) as tmp:
        write_splats(tmp / f"canonical{suffix}", posed_gaussians(model, 0, lod, canonical_pose, np.zeros(3)), fmt,
                     canonical_up, what=f"{checkpoint}: canonical splats")
        if motion is not None:
            record["files"].update(_export_motion(model, lod, motion, chosen, tmp, fmt, capture_up,
                                                  f"{checkpoint}: splats of {source}"))
        write_json(tmp / "export.json", record)
    return output


def _export_motion(model, lod: int, motion, chosen: np.ndarray, folder: Path, fmt: str, up: np.ndarray,
                   what: str) -> dict[str, dict]:
    """frame_{i:06d} files for each motion frame i in `chosen` (row r of the aligned clip `motion` is frame
    chosen[r]), and correspondences.npz, into `folder`; returns the sidecar's entries of the frame files."""
    n = model.level_sizes[lod]
    positions = np.empty((len(chosen), n, 3), dtype=np.float32)
    timesteps = np.empty(len(chosen), dtype=np.int64)
    files = {}
    for row, frame in enumerate(chosen):
        timesteps[row] = model.nearest_timestep(torch.as_tensor(motion.full_pose[row]))
        gaussians = posed_gaussians(model, int(timesteps[row]), lod, motion.full_pose[row], motion.transl[row])
        name = f"frame_{frame:06d}{FORMATS[fmt]}"
        write_splats(folder / name, gaussians, fmt, up, what=f"{what} frame {frame}")
        positions[row] = gaussians[0].cpu().numpy()
        files[name] = {"motion_frame": int(frame), "timestep": int(timesteps[row]), "up": up, "up_axis": nearest_axis(up)}
    with atomic_path(folder / "correspondences.npz") as path:
        np.savez(path, anchor_ids=np.arange(n, dtype=np.int64), frames=chosen.astype(np.int64), timesteps=timesteps,
                 positions=positions, lod=np.int64(lod))
    return files
