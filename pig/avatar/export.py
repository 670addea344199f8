"""Export of a fitted avatar as standard 3DGS point clouds (.ply): canonical, and per frame of a motion with
dense correspondences between the frames.

Each .ply is binary little-endian with one `vertex` element of float32 properties, in the layout of the
INRIA 3DGS code that its viewer, SuperSplat and gsplat's exporter read:
    x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..3(K-1)-1, opacity, scale_0..2, rot_0..3.
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

Poses: the canonical cloud is the avatar at rest, zero `full_pose` (all 55 joints) and zero translation,
decoded with training timestep 0's time embedding gamma(0) and expression and the fitted (refined) shape.
A motion frame's pose and translation drive the transport (Eqs. 2-3) while the nearest training timestep
by summed per-joint geodesic distance feeds gamma(t) (Eq. 6), as the render stage does for novel poses;
its expression is that timestep's, its shape the avatar's own (a motion's betas are not used).

Writes OUTPUT/canonical.ply and, with a motion, OUTPUT/frame_{i:06d}.ply for each selected motion frame i
and OUTPUT/correspondences.npz: `anchor_ids` (n,) int64, `frames` (F,) int64 motion frame indices,
`timesteps` (F,) int64 the training timesteps whose gamma(t) decoded them, `positions` (F, n, 3) float32
(row j is the xyz of anchor_ids[j] in frame_{frames[f]}.ply), `lod` (int64 scalar).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from pig.field.precondition import bake_preconditioning
from pig.stages._io import atomic_path
from pig.stages._outputs import build_dir, claim_dir

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


def write_splat_ply(path: str | Path, means, quats, scales, opacities, sh, what: str = "splats") -> None:
    """Write n splats (conventions of `splat_table`) as a binary little-endian 3DGS .ply, atomically."""
    table = splat_table(means, quats, scales, opacities, sh, what)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(table)}"]
    header += [f"property float {name}" for name in table.dtype.names] + ["end_header"]
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(table.tobytes())


def frame_selection(spec: str | None, count: int, source: str) -> np.ndarray:
    """Motion frame indices chosen by `spec` ("START:STOP[:STEP]", STOP excluded; None: all `count` frames) of
    the motion `source`, which has `count` frames."""
    if spec is None:
        return np.arange(count)
    match = re.fullmatch(r"\s*(\d+):(\d+)(?::(\d+))?\s*", spec)
    if match is None:
        raise ValueError(f"--frames {spec!r}: expected {FRAMES_FORM}")
    start, stop, step = int(match[1]), int(match[2]), int(match[3] or 1)
    if start >= stop or step < 1:
        raise ValueError(f"--frames {spec!r} selects no frame; expected {FRAMES_FORM}")
    if stop > count:
        raise ValueError(f"--frames {spec!r}: {source} has {count} frames (0..{count - 1}), so STOP may be at most "
                         f"{count}")
    return np.arange(start, stop, step)


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


def export_avatar(checkpoint: str | Path, output: str | Path, lod: int | None = None, poses=None, transl=None,
                  frames: str | None = None, motion_source: str | Path | None = None, device: str | torch.device = "cpu",
                  overwrite: bool = False) -> Path:
    """Write the export folder `output` (see the module docstring) of the avatar in `checkpoint` at level `lod`
    (default: the finest); with a motion, `poses` (N, 55, 3) and `transl` (N, 3) or else the motion file
    `motion_source` (read by pig.body.motion.read_motion, any of its layouts), also the frames `frames` selects
    ("START:STOP[:STEP]", default all). `output` may replace only an earlier export unless `overwrite`; nothing
    is written unless every check passes. Returns `output`."""
    from pig.avatar.checkpoint import load_avatar
    from pig.body.motion import read_motion

    checkpoint, output, source = Path(checkpoint), Path(output), str(motion_source or "the motion")
    if (poses is None) != (transl is None):
        raise ValueError("export: a motion needs both its poses and its translations")
    has_motion = poses is not None or motion_source is not None
    if not has_motion and frames is not None:
        raise ValueError(f"--frames {frames!r} selects frames of a motion; give one with --motion FILE")
    inputs = [checkpoint] + ([Path(motion_source)] if motion_source is not None else [])
    output = claim_dir(output, STAGE, inputs, overwrite)
    model = load_avatar(checkpoint, device)
    if poses is None and motion_source is not None:
        motion = read_motion(motion_source, hands_mean=model.body_model.hands_mean.cpu().numpy())
        poses, transl = motion.full_pose, motion.transl
    if poses is not None:
        poses, transl = _checked_motion(poses, transl, source)
        chosen = frame_selection(frames, len(poses), source)
    if lod is None:
        lod = model.num_levels - 1
    if not 0 <= lod < model.num_levels:
        raise ValueError(f"--lod {lod}: {checkpoint} has levels of detail 0..{model.num_levels - 1} "
                         f"({', '.join(map(str, model.level_sizes))} splats)")
    bake_preconditioning(model)  # the anchors' value once, not a solve per frame
    with build_dir(output, STAGE) as tmp:
        write_splat_ply(tmp / "canonical.ply", *posed_gaussians(model, 0, lod, np.zeros((55, 3)), np.zeros(3)),
                        what=f"{checkpoint}: canonical splats")
        if poses is not None:
            _export_motion(model, lod, poses, transl, chosen, tmp, f"{checkpoint}: splats of {source}")
    return output


def _export_motion(model, lod: int, poses: np.ndarray, transl: np.ndarray, chosen: np.ndarray, folder: Path,
                   what: str) -> None:
    """frame_{i:06d}.ply for each motion frame i in `chosen`, and correspondences.npz, into `folder`."""
    n = model.level_sizes[lod]
    positions = np.empty((len(chosen), n, 3), dtype=np.float32)
    timesteps = np.empty(len(chosen), dtype=np.int64)
    for row, frame in enumerate(chosen):
        timesteps[row] = model.nearest_timestep(torch.as_tensor(poses[frame]))
        gaussians = posed_gaussians(model, int(timesteps[row]), lod, poses[frame], transl[frame])
        write_splat_ply(folder / f"frame_{frame:06d}.ply", *gaussians, what=f"{what} frame {frame}")
        positions[row] = gaussians[0].cpu().numpy()
    with atomic_path(folder / "correspondences.npz") as path:
        np.savez(path, anchor_ids=np.arange(n, dtype=np.int64), frames=chosen.astype(np.int64), timesteps=timesteps,
                 positions=positions, lod=np.int64(lod))
