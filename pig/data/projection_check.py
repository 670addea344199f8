"""Projection sanity check: per camera, IoU between the posed body model's projected silhouette and the masks.

Catches cameras and body parameters that disagree (above all camera-to-world calibration read as
world-to-camera) before any fitting; data preparation, no paper equation.

Score. The body silhouette B lies inside the clothed person's mask M up to calibration and fitting error,
while loose garments and hair extend M well beyond B. So the pass/fail score is a tolerant IoU with one
tolerance per direction: body pixels count as agreeing within r_b of the mask, mask pixels within r_g of
the body, r = max(MIN_RADIUS_PX, f * tolerance_m / max(z, MIN_DEPTH_M)), z the median depth of the body in
that camera (floored: nearer, as with a camera inside the subject, the radius would grow without bound and
cover the whole image, so that any calibration passed):
    IoU_tol = (|B u M| - |B \\ D_rb(M)| - |M \\ D_rg(B)|) / |B u M|,  D_r = dilation by a disc of radius r,
summed over the sampled frames. The plain IoU |B n M| / |B u M| is reported beside it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

NEAR = 0.01  # metres; triangles with a vertex closer than this to the camera plane are not drawn
MIN_RADIUS_PX = 1.5  # rasterisation and resampling put silhouette edges up to about a pixel apart
MIN_DEPTH_M = 1.0  # full-body capture cameras stand farther from the body than this
_SHIFT = 4  # sub-pixel bits for cv2.fillConvexPoly


class ProjectionCheckError(ValueError):
    """Cameras and body parameters disagree: the body does not project onto the masks."""


@dataclass
class View:
    """One camera of the preprocessed capture: pinhole K, world-to-camera R, T, image size."""

    K: np.ndarray
    R: np.ndarray
    T: np.ndarray
    width: int
    height: int


def project(points: np.ndarray, K: np.ndarray, R: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> pixels (N, 2) (centres at integer coordinates) and camera depth z (N,)."""
    cam = points @ R.T + T
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam @ K.T)[:, :2] / z[:, None]
    return uv, z


def silhouette(vertices: np.ndarray, faces: np.ndarray, view: View) -> np.ndarray:
    """(H, W) bool: pixels covered by the projected triangles (those entirely in front of the camera)."""
    uv, z = project(vertices, view.K, view.R, view.T)
    out = np.zeros((view.height, view.width), np.uint8)
    tris = uv[faces]
    keep = np.all(z[faces] > NEAR, axis=1)
    # Drop triangles entirely off to one side of the image; the rest fit in int32 after the shift.
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    keep &= (hi[:, 0] >= 0) & (hi[:, 1] >= 0) & (lo[:, 0] < view.width) & (lo[:, 1] < view.height)
    keep &= np.all(np.abs(tris) < 2 ** (30 - _SHIFT), axis=(1, 2))
    fixed = np.round(tris[keep] * (1 << _SHIFT)).astype(np.int32)
    for tri in fixed:
        cv2.fillConvexPoly(out, tri, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return out.astype(bool)


def _within(mask: np.ndarray, radius: float) -> np.ndarray:
    """Pixels within `radius` of a pixel of `mask` (its dilation by a disc)."""
    if not mask.any():
        return mask
    distance = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return distance <= radius


def overlap_counts(body: np.ndarray, mask: np.ndarray, body_radius: float, garment_radius: float) -> np.ndarray:
    """[|B n M|, |B u M|, tolerant agreement] pixel counts of one frame (see the module docstring)."""
    union = np.count_nonzero(body | mask)
    missed = (np.count_nonzero(body & ~_within(mask, body_radius))
              + np.count_nonzero(mask & ~_within(body, garment_radius)))
    return np.array([np.count_nonzero(body & mask), union, union - missed], dtype=np.float64)


@dataclass
class Tolerance:
    body_m: float = 0.05  # body outside the mask: calibration and fitting error
    garment_m: float = 0.20  # mask outside the body: loose garments, hair


def camera_score(view: View, vertices: list[np.ndarray], masks: list[np.ndarray], faces: np.ndarray,
                 tolerance: Tolerance) -> dict[str, float]:
    """Plain and tolerant IoU of one camera over frames (vertices[i] posed for masks[i])."""
    counts = np.zeros(3)
    depths = []
    for verts, mask in zip(vertices, masks):
        _, z = project(verts, view.K, view.R, view.T)
        in_front = z[z > NEAR]
        # Tolerances in pixels at the body's depth; a body behind the camera fails whatever the radius.
        depth = float(np.median(in_front)) if in_front.size else np.inf
        depths.append(depth)
        counts += overlap_counts(silhouette(verts, faces, view), mask, *_radii(view, tolerance, depth))
    scores = {"iou": float("nan"), "raw_iou": float("nan")}
    if counts[1] > 0:
        scores = {"iou": counts[2] / counts[1], "raw_iou": counts[0] / counts[1]}
    body_radius, garment_radius = _radii(view, tolerance, float(np.median(depths)))
    return {**scores, "body_radius_px": body_radius, "garment_radius_px": garment_radius}


def _radii(view: View, tolerance: Tolerance, depth: float) -> tuple[float, float]:
    """(body, garment) tolerance radii in pixels at the body's median `depth` (floored at MIN_DEPTH_M)."""
    depth = max(depth, MIN_DEPTH_M)
    return tuple(max(MIN_RADIUS_PX, view.K[0, 0] * t / depth) for t in (tolerance.body_m, tolerance.garment_m))


def inverted(view: View) -> View:
    """The view with its extrinsics inverted (what camera-to-world data read as world-to-camera needs)."""
    return View(view.K, view.R.T, -view.R.T @ view.T, view.width, view.height)


def check_projection(views: dict[str, View], frames: dict[str, list[int]], masks: dict[str, list[np.ndarray]],
                     vertices: dict[int, np.ndarray], faces: np.ndarray, tolerance: Tolerance,
                     min_iou: float) -> dict:
    """Score every camera; raise ProjectionCheckError naming the cameras that score below `min_iou`.

    frames[c][i] is the frame of masks[c][i]; vertices[frame] the posed body. When the failing
    cameras pass with inverted extrinsics the message says the calibration is camera-to-world.
    """
    scores = {}
    for name, view in views.items():
        verts = [vertices[f] for f in frames[name]]
        scores[name] = {**camera_score(view, verts, masks[name], faces, tolerance), "frames": frames[name]}
    failing = [c for c, s in scores.items() if not s["iou"] >= min_iou]
    report = {
        "definition": "tolerant IoU: body pixels within body_radius_px of the mask and mask pixels within "
                      "garment_radius_px of the body count as agreeing (radius = f * tolerance / median body depth, the "
                      f"depth at least {MIN_DEPTH_M} m, the radius at least {MIN_RADIUS_PX} px); raw_iou is the "
                      "plain IoU",
        "tolerance_m": asdict(tolerance),
        "min_iou": min_iou,
        "cameras": scores,
        "passed": not failing,
    }
    if not failing:
        return report
    listing = ", ".join(f"{c} {scores[c]['iou']:.2f} (raw {scores[c]['raw_iou']:.2f})" for c in failing)
    flipped = {c: camera_score(inverted(views[c]), [vertices[f] for f in frames[c]], masks[c], faces,
                               tolerance)["iou"] for c in failing}
    if all(score >= min_iou for score in flipped.values()):
        raise ProjectionCheckError(
            f"projection check failed: tolerant IoU below {min_iou} for {len(failing)} of {len(views)} cameras "
            f"({listing}), but {min(flipped.values()):.2f} or more with inverted extrinsics: the calibration looks "
            "camera-to-world; invert it (R <- R^T, T <- -R^T T) so that x_cam = R x_world + T")
    raise ProjectionCheckError(
        f"projection check failed: tolerant IoU below {min_iou} for {len(failing)} of {len(views)} cameras "
        f"({listing}); the cameras and the body parameters disagree. Check that the calibration is world-to-camera "
        "in metres, that the body parameters belong to this capture and frame numbering, and that the body model is "
        "the one the parameters were fitted with")
