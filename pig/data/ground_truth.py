"""The files behind the ground-truth metrics: the synthetic capture's true meshes (gt_meshes.npz) and the render
stage's per-frame splat centres and opacities of one LOD (splats.npz).

Read without running code from the file and checked for shape, index range and finiteness, so that a bad file
stops with its name; data preparation, no paper equation.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pig.body.npz import read_npz
from pig.data.raw import CaptureError
from pig._io import atomic_path

GT_MESHES = "gt_meshes.npz"  # written by pig.data.synthetic.generate_capture, carried along by preprocess
SPLATS = "splats.npz"  # written by the render stage beside each renders/{split}/lod{l}/ when the capture has GT_MESHES
MESH_KEYS = ("frames", "body_vertices", "body_faces", "garment_vertices", "garment_faces")
MESH_EXPECTED = ("the true meshes of a synthetic capture: frames (T,), body_vertices (T, Vb, 3), body_faces (Fb, 3), "
                 "garment_vertices (T, Vg, 3), garment_faces (Fg, 3)")
SPLAT_KEYS = ("frames", "centres", "opacities")
SPLAT_EXPECTED = "the render stage's splat track: frames (F,), centres (F, N, 3), opacities (F, N)"


@dataclass
class TrueMeshes:
    """True body and garment meshes per frame, in world coordinates (metres)."""

    path: Path
    frames: np.ndarray  # (T,) frame ids
    body_vertices: np.ndarray  # (T, Vb, 3)
    body_faces: np.ndarray  # (Fb, 3)
    garment_vertices: np.ndarray  # (T, Vg, 3)
    garment_faces: np.ndarray  # (Fg, 3), indices into the garment vertices

    @classmethod
    def load(cls, path: str | Path) -> "TrueMeshes":
        path = Path(path)
        arrays = read_npz(path, CaptureError, MESH_EXPECTED, keys=MESH_KEYS)
        missing = [key for key in MESH_KEYS if key not in arrays]
        if missing:
            raise CaptureError(f"{path}: missing {missing}; expected {MESH_EXPECTED}")
        frames = arrays["frames"]
        if frames.ndim != 1 or not np.issubdtype(frames.dtype, np.integer) or len(set(frames.tolist())) != len(frames):
            raise CaptureError(f"{path}: 'frames' must be distinct integer frame ids (T,), found {frames.dtype} "
                               f"{frames.shape}")
        meshes = {}
        for part in ("body", "garment"):
            vertices, faces = arrays[f"{part}_vertices"], arrays[f"{part}_faces"]
            if vertices.shape[:1] != frames.shape or vertices.ndim != 3 or vertices.shape[2] != 3:
                raise CaptureError(f"{path}: '{part}_vertices' must be ({len(frames)}, V, 3) for its {len(frames)} "
                                   f"frames, found {vertices.shape}")
            if not np.isfinite(vertices).all():
                raise CaptureError(f"{path}: '{part}_vertices' holds NaN or infinite values")
            if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
                raise CaptureError(f"{path}: '{part}_faces' must be integer (F, 3), found {faces.dtype} {faces.shape}")
            if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[1]):
                raise CaptureError(f"{path}: '{part}_faces' index vertices outside 0..{vertices.shape[1] - 1}")
            meshes[part] = (vertices, faces.astype(np.int64))
        return cls(path, frames.astype(np.int64), *meshes["body"], *meshes["garment"])

    def row(self, frame: int) -> int:
        rows = np.flatnonzero(self.frames == frame)
        if not len(rows):
            raise CaptureError(f"{self.path}: no true meshes of frame {frame} (it has frames "
                               f"{self.frames.min()}..{self.frames.max()})")
        return int(rows[0])

    def require_frames(self, frames, what: str) -> None:
        """CaptureError unless every frame id of `frames` (those of `what`) has true meshes."""
        absent = sorted(set(int(f) for f in frames) - set(self.frames.tolist()))
        if absent:
            raise CaptureError(f"{self.path}: no true meshes of frame(s) {absent[:5]} of {what}; it has frames "
                               f"{self.frames.min()}..{self.frames.max()}")

    def surfaces(self, frame: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(body vertices, body faces), (garment vertices, garment faces)] of one frame id."""
        row = self.row(frame)
        return [(self.body_vertices[row], self.body_faces), (self.garment_vertices[row], self.garment_faces)]


@dataclass
class SplatTrack:
    """Splat centres and opacities of one LOD over the frames of a split; splat i is the same anchor in every frame."""

    frames: np.ndarray  # (F,) frame ids, ascending
    centres: np.ndarray  # (F, N, 3) world metres
    opacities: np.ndarray  # (F, N) in [0, 1]

    def save(self, path: str | Path) -> None:
        with atomic_path(path) as tmp:
            np.savez(tmp, frames=np.asarray(self.frames, dtype=np.int64),
                     centres=np.asarray(self.centres, dtype=np.float32),
                     opacities=np.asarray(self.opacities, dtype=np.float32))

    @staticmethod
    def require(path: str | Path) -> None:
        """FileNotFoundError saying what to do when the render stage's track `path` is absent."""
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path} not found: expected {SPLAT_EXPECTED}, which the render stage writes for "
                                    f"a capture with {GT_MESHES}; rerun render (e.g. `snakemake -R render_split`)")

    @classmethod
    def load(cls, path: str | Path) -> "SplatTrack":
        path = Path(path)
        cls.require(path)
        arrays = read_npz(path, CaptureError, SPLAT_EXPECTED, keys=SPLAT_KEYS)
        missing = [key for key in SPLAT_KEYS if key not in arrays]
        if missing:
            raise CaptureError(f"{path}: missing {missing}; expected {SPLAT_EXPECTED}")
        frames, centres, opacities = arrays["frames"], arrays["centres"], arrays["opacities"]
        count = len(frames)
        if (frames.ndim != 1 or centres.shape[:1] != (count,) or centres.ndim != 3 or centres.shape[2] != 3
                or opacities.shape != centres.shape[:2] or count == 0):
            raise CaptureError(f"{path}: expected {SPLAT_EXPECTED} with F > 0, found frames {frames.shape}, "
                               f"centres {centres.shape}, opacities {opacities.shape}")
        if not (np.isfinite(centres).all() and np.isfinite(opacities).all()):
            raise CaptureError(f"{path}: centres or opacities hold NaN or infinite values")
        if np.any(np.diff(frames) <= 0):
            raise CaptureError(f"{path}: 'frames' must be ascending distinct frame ids, found {frames.tolist()[:8]}")
        return cls(frames.astype(np.int64), centres, opacities)  # as stored (float32): a paper-sized track is large
