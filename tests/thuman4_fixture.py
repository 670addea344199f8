"""A tiny THuman4-layout subject written by the tests: a rigid capsule 'body' seen by a ring of distorted cameras.

Masks are the capsule's silhouette drawn through OpenCV's distorted projection, so a correct reader and
preprocess stage find the body exactly on the masks; options produce every format variant of FORMATS.md.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import trimesh

from pig.body.model import NUM_JOINTS, SMPLX_PARENTS

DIST = np.array([-0.12, 0.03, 0.001, -0.0015, 0.0])


def capsule_body_arrays() -> dict[str, np.ndarray]:
    """SMPL-X-layout arrays of a 1.6 m capsule, every vertex skinned to the pelvis (all joints at the centroid)."""
    mesh = trimesh.creation.capsule(height=1.2, radius=0.2, count=[24, 24])
    vertices = mesh.vertices[:, [0, 2, 1]]  # capsule axis along y (up)
    faces = mesh.faces[:, [0, 2, 1]]  # swapping two axes flips orientation; keep outward normals
    num = len(vertices)
    weights = np.zeros((num, NUM_JOINTS))
    weights[:, 0] = 1
    regressor = np.full((NUM_JOINTS, num), 1.0 / num)  # every joint at the vertex centroid
    return {
        "v_template": vertices, "f": faces, "shapedirs": np.zeros((num, 3, 20)),
        "posedirs": np.zeros((num, 3, (NUM_JOINTS - 1) * 9)), "J_regressor": regressor, "weights": weights,
        "kintree_table": np.stack([np.array(SMPLX_PARENTS), np.arange(NUM_JOINTS)]),
    }


def look_at(center: np.ndarray, target=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, T) of an OpenCV camera (x right, y down, z forward) in a y-up world."""
    forward = np.asarray(target, dtype=np.float64) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(forward, right), forward])
    return R, -R @ center


def ring_cameras(count: int, width: int, height: int, radius: float = 3.5) -> dict[str, dict]:
    cams = {}
    for i in range(count):
        angle = 2 * np.pi * i / count
        R, T = look_at(np.array([radius * np.sin(angle), 0.3, radius * np.cos(angle)]))
        f = 0.95 * height
        K = np.array([[f, 0, width / 2 - 0.3], [0, f * 1.01, height / 2 + 0.7], [0, 0, 1]])
        cams[f"cam{i:02d}"] = {"K": K, "R": R, "T": T, "dist": DIST.copy(), "width": width, "height": height}
    return cams


def body_params(frames: int, seed: int = 0) -> dict[str, np.ndarray]:
    """THuman4 smpl_params.npz arrays: a slow turn about y and a small drift."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)
    orient = np.zeros((frames, 3))
    orient[:, 0] = 0.2 * np.sin(t)
    orient[:, 1] = 0.3 * t
    return {
        "betas": rng.normal(size=(1, 10)) * 0.1,
        "global_orient": orient,
        "transl": np.stack([0.05 * np.sin(t), 0.02 * t, 0.03 * np.cos(t)], axis=1),
        "body_pose": np.zeros((frames, 63)),
        "jaw_pose": np.zeros((frames, 3)),
        "expression": np.zeros((frames, 10)),
        "left_hand_pose": np.zeros((frames, 45)),
        "right_hand_pose": np.zeros((frames, 45)),
    }


def posed_vertices(arrays: dict, params: dict, frame: int) -> np.ndarray:
    """The capsule is rigid: rotate about the pelvis joint (the centroid), then translate."""
    R, _ = cv2.Rodrigues(params["global_orient"][frame])
    pivot = arrays["v_template"].mean(axis=0)
    return (arrays["v_template"] - pivot) @ R.T + pivot + params["transl"][frame]


def distorted_silhouette(vertices, faces, cam) -> np.ndarray:
    """Silhouette through OpenCV's distorted projection (uint8 0/255)."""
    rvec, _ = cv2.Rodrigues(cam["R"])
    uv, _ = cv2.projectPoints(vertices, rvec, cam["T"], cam["K"], cam["dist"])
    out = np.zeros((cam["height"], cam["width"]), np.uint8)
    for tri in np.round(uv[:, 0][faces] * 16).astype(np.int32):
        cv2.fillConvexPoly(out, tri, 255, lineType=cv2.LINE_8, shift=4)
    return out


def write_thuman4(root: Path, cameras: int = 4, frames: int = 5, width: int = 96, height: int = 80, *,
                  ext: str = "jpg", flat: bool = False, betas_rows: int = 1, missing: list[str] | None = None,
                  camera_to_world: bool = False, seed: int = 0) -> Path:
    """Write a subject folder; `missing` lines go to missing_img_files.txt (those images are not written)."""
    root = Path(root)
    rng = np.random.default_rng(seed)
    arrays = capsule_body_arrays()
    params = body_params(frames, seed)
    params["betas"] = np.repeat(params["betas"], betas_rows, axis=0)
    cams = ring_cameras(cameras, width, height)
    skipped = set()
    for line in missing or []:
        parts = line.replace("\\", "/").split("/")
        skipped.add((parts[-2], int(parts[-1].split(".")[0])))
    calibration = {}
    for name, cam in cams.items():
        R, T = cam["R"], cam["T"]
        if camera_to_world:
            R, T = R.T, -R.T @ T
        calibration[name] = {
            "K": cam["K"].reshape(-1).tolist() if flat else cam["K"].tolist(),
            "R": R.reshape(-1).tolist() if flat else R.tolist(),
            "T": T.tolist(), "imgSize": [width, height], "distCoeff": cam["dist"].tolist(),
        }
        (root / "images" / name).mkdir(parents=True, exist_ok=True)
        (root / "masks" / name).mkdir(parents=True, exist_ok=True)
        for frame in range(frames):
            if (name, frame) in skipped:
                continue
            sil = distorted_silhouette(posed_vertices(arrays, params, frame), arrays["f"], cam)
            image = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
            image[sil > 0] = (200, 120, 40)
            cv2.imwrite(str(root / "images" / name / f"{frame:08d}.{ext}"), image)
            cv2.imwrite(str(root / "masks" / name / f"{frame:08d}.{ext}"), sil)
    (root / "calibration.json").write_text(json.dumps(calibration))
    np.savez(root / "smpl_params.npz", **params)
    np.savez(root / "body_model.npz", **arrays)
    if missing:
        (root / "missing_img_files.txt").write_text("\n".join(missing) + "\n")
    return root
