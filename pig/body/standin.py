"""A procedural stand-in for SMPL-X: a watertight body with SMPL-X's 55-joint tree, in the SMPL-X npz layout.

Implements the body model the skinning of the paper's transport (Eqs. 2-3) runs on when no licensed
SMPLX_NEUTRAL.npz is configured: marching cubes of a smooth union of round cones and ellipsoids.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.optimize import nnls
from skimage.measure import marching_cubes

from pig._io import atomic_path

from .model import LEFT_HAND, NUM_JOINTS, RIGHT_HAND, SMPLX_JOINT_NAMES, SMPLX_PARENTS

NUM_BETAS = 10
NUM_EXPRESSION = 10
GRID_SPACING = 0.018  # metres, coarse grid step; the hands get a finer band

J = {name: i for i, name in enumerate(SMPLX_JOINT_NAMES)}


@dataclass(frozen=True)
class _Primitive:
    """A round cone from `a` (radius ra) to `b` (radius rb), or an ellipsoid when `radii` is set."""

    joint: int
    a: tuple
    b: tuple = (0.0, 0.0, 0.0)
    ra: float = 0.0
    rb: float = 0.0
    radii: tuple | None = None
    group: str = "body"  # primitives are blended with a group-specific smoothness


def _mirror(point, side):
    return (side * point[0], point[1], point[2])


def _rest_joints_and_primitives() -> tuple[np.ndarray, list[_Primitive]]:
    """Joint centres (T-pose, y-up, facing +z, pelvis at the origin, ~1.70 m tall) and the solids around them."""
    joints = np.zeros((NUM_JOINTS, 3))
    prims: list[_Primitive] = []

    def put(name, point):
        joints[J[name]] = point

    put("pelvis", (0.0, 0.0, 0.0))
    put("spine1", (0.0, 0.10, -0.01))
    put("spine2", (0.0, 0.23, 0.0))
    put("spine3", (0.0, 0.30, 0.0))
    put("neck", (0.0, 0.46, -0.01))
    put("head", (0.0, 0.56, 0.01))
    put("jaw", (0.0, 0.55, 0.03))
    prims += [
        _Primitive(J["pelvis"], (0.0, -0.03, 0.0), radii=(0.155, 0.12, 0.105)),
        _Primitive(J["spine1"], (0.0, 0.11, 0.0), radii=(0.14, 0.09, 0.095)),
        _Primitive(J["spine2"], (0.0, 0.24, 0.005), radii=(0.155, 0.10, 0.105)),
        _Primitive(J["spine3"], (0.0, 0.35, 0.0), radii=(0.165, 0.09, 0.10)),
        _Primitive(J["neck"], (0.0, 0.44, -0.01), (0.0, 0.56, 0.0), 0.055, 0.05),
        _Primitive(J["head"], (0.0, 0.64, 0.015), radii=(0.078, 0.105, 0.092)),
        _Primitive(J["jaw"], (0.0, 0.575, 0.055), radii=(0.05, 0.03, 0.045)),
    ]
    for side, prefix in ((1.0, "left"), (-1.0, "right")):
        m = lambda p: _mirror(p, side)  # noqa: E731 - the person's left is +x
        hip, knee, ankle, toe = m((0.09, -0.07, 0.0)), m((0.10, -0.48, 0.01)), m((0.10, -0.89, -0.02)), m((0.10, -0.95, 0.10))
        collar, shoulder, elbow, wrist = m((0.035, 0.40, -0.01)), m((0.17, 0.42, -0.015)), m((0.44, 0.42, -0.02)), m((0.69, 0.42, -0.01))
        eye = m((0.032, 0.655, 0.078))
        for name, point in (("hip", hip), ("knee", knee), ("ankle", ankle), ("foot", toe), ("collar", collar),
                            ("shoulder", shoulder), ("elbow", elbow), ("wrist", wrist), ("eye", eye)):
            put(f"{prefix}_{name}", point)
        prims += [
            _Primitive(J[f"{prefix}_hip"], hip, knee, 0.085, 0.055),
            _Primitive(J[f"{prefix}_knee"], knee, ankle, 0.052, 0.036),
            _Primitive(J[f"{prefix}_ankle"], ankle, m((0.10, -0.94, 0.09)), 0.04, 0.035),
            _Primitive(J[f"{prefix}_ankle"], ankle, m((0.10, -0.93, -0.05)), 0.04, 0.035),
            _Primitive(J[f"{prefix}_foot"], toe, m((0.10, -0.95, 0.16)), 0.033, 0.026),
            _Primitive(J[f"{prefix}_collar"], collar, shoulder, 0.06, 0.055),
            _Primitive(J[f"{prefix}_shoulder"], shoulder, elbow, 0.055, 0.042),
            _Primitive(J[f"{prefix}_elbow"], elbow, wrist, 0.04, 0.03),
            _Primitive(J[f"{prefix}_wrist"], m((0.755, 0.42, 0.0)), radii=(0.05, 0.043, 0.017), group="hand"),
            _Primitive(J[f"{prefix}_eye"], eye, radii=(0.014, 0.014, 0.014), group="eye"),
        ]
        # Palms face +z and the fingers fan out in the x-y plane (thumb up), so the finely meshed
        # band of the grid (see `_grid_axes`) stays thin in z.
        fingers = {  # name: (base y offset, fan angle in degrees, length scale, radius)
            "index": (0.028, 14.0, 1.0, 0.0085),
            "middle": (0.009, 4.0, 1.08, 0.0088),
            "ring": (-0.010, -6.0, 1.0, 0.0083),
            "pinky": (-0.028, -16.0, 0.8, 0.0075),
        }
        for finger, (dy, angle, scale, radius) in fingers.items():
            direction = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle)), 0.0])
            base = np.array([0.80, 0.42 + dy, 0.0])
            _finger(joints, prims, prefix, finger, side, base, direction, np.array([0.042, 0.028, 0.022]) * scale, radius)
        thumb_dir = np.array([0.6, 0.785, 0.15]) / np.linalg.norm([0.6, 0.785, 0.15])
        _finger(joints, prims, prefix, "thumb", side, np.array([0.725, 0.44, 0.005]), thumb_dir,
                np.array([0.035, 0.032, 0.026]), 0.011)
    return joints, prims


def _finger(joints, prims, prefix, finger, side, base, direction, lengths, radius) -> None:
    points = [base]
    for length in lengths:
        points.append(points[-1] + length * direction)
    points = [np.array(_mirror(p, side)) for p in points]
    for k in range(3):
        joint = J[f"{prefix}_{finger}{k + 1}"]
        joints[joint] = points[k]
        prims.append(_Primitive(joint, tuple(points[k]), tuple(points[k + 1]), radius * (1 - 0.06 * k),
                                radius * (1 - 0.06 * (k + 1)), group="hand"))


def _round_cone_sdf(p: np.ndarray, a, b, ra: float, rb: float) -> np.ndarray:
    """Exact signed distance to the convex hull of two spheres (a, ra) and (b, rb)."""
    a, b = np.asarray(a), np.asarray(b)
    ba = b - a
    length = np.linalg.norm(ba)
    axis = ba / length
    pa = p - a
    along = pa @ axis
    across = np.linalg.norm(pa - along[:, None] * axis, axis=1)
    # In the (along, across) half-plane the side line is tilted by asin((ra - rb) / length).
    sin_t = (ra - rb) / length
    cos_t = np.sqrt(max(1 - sin_t * sin_t, 0.0))
    side = along * sin_t + across * cos_t - ra  # distance to the tangent line, offset by ra
    proj = along * cos_t - across * sin_t  # position along the tangent line
    end_a = np.sqrt(along**2 + across**2) - ra
    end_b = np.sqrt((along - length) ** 2 + across**2) - rb
    return np.where(proj < 0, end_a, np.where(proj > length * cos_t, end_b, side))


def _ellipsoid_sdf(p: np.ndarray, centre, radii) -> np.ndarray:
    """A first-order signed-distance estimate whose zero set is exactly the ellipsoid."""
    q = (p - np.asarray(centre)) / np.asarray(radii)
    k0 = np.linalg.norm(q, axis=1)
    k1 = np.linalg.norm(q / np.asarray(radii), axis=1)
    return k0 * (k0 - 1) / np.maximum(k1, 1e-12)


def _primitive_sdf(prim: _Primitive, p: np.ndarray) -> np.ndarray:
    if prim.radii is not None:
        return _ellipsoid_sdf(p, prim.a, prim.radii)
    return _round_cone_sdf(p, prim.a, prim.b, prim.ra, prim.rb)


def _primitive_bounds(prim: _Primitive) -> tuple[np.ndarray, np.ndarray]:
    if prim.radii is not None:
        return np.array(prim.a) - prim.radii, np.array(prim.a) + prim.radii
    a, b = np.array(prim.a), np.array(prim.b)
    return np.minimum(a - prim.ra, b - prim.rb), np.maximum(a + prim.ra, b + prim.rb)


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: a fillet of size ~k where two solids meet."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1 - h)


BLEND = {"body": 0.03, "hand": 0.006, "eye": 0.004}
BLEND_HAND_TO_BODY = 0.02
FAR = 0.1  # beyond every blend width
SNAP = 0.001


def _grid_sdf(axes: list[np.ndarray], prims: list[_Primitive]) -> np.ndarray:
    """Blended signed distance of the whole body on the rectilinear grid `axes`.

    Each primitive only touches the block of the grid within FAR of its bounding box; beyond it the
    blend cannot move the zero set.
    """
    shape = tuple(len(a) for a in axes)
    groups = {group: np.full(shape, FAR) for group in BLEND}
    for prim in prims:
        lo, hi = _primitive_bounds(prim)
        block = tuple(slice(np.searchsorted(ax, l - FAR), np.searchsorted(ax, h + FAR)) for ax, l, h in zip(axes, lo, hi))
        points = np.stack(np.meshgrid(*(ax[b] for ax, b in zip(axes, block)), indexing="ij"), axis=-1)
        value = np.minimum(_primitive_sdf(prim, points.reshape(-1, 3)), FAR).reshape(points.shape[:-1])
        target = groups[prim.group][block]  # a view: updated in place
        target[...] = _smooth_min(target, value, BLEND[prim.group])
    total = _smooth_min(groups["body"], groups["hand"], BLEND_HAND_TO_BODY)
    return _smooth_min(total, groups["eye"], BLEND["eye"])


def _nearest_primitive(points: np.ndarray, prims: list[_Primitive]) -> np.ndarray:
    """Index of the primitive each point is deepest in (or closest to): the point's body part."""
    return np.stack([_primitive_sdf(prim, points) for prim in prims], axis=1).argmin(axis=1)


def _graded_axis(lo: float, hi: float, coarse: float, fine: float, fine_intervals) -> np.ndarray:
    """Sample positions on [lo, hi]: spacing `fine` inside the given intervals, `coarse` elsewhere."""
    cuts = sorted({lo, hi, *(v for interval in fine_intervals for v in interval)})
    samples = []
    for start, stop in zip(cuts[:-1], cuts[1:]):
        is_fine = any(a <= start and stop <= b for a, b in fine_intervals)
        count = max(1, int(np.ceil((stop - start) / (fine if is_fine else coarse))))
        samples.append(np.linspace(start, stop, count + 1)[:-1])
    return np.concatenate(samples + [[hi]])


def _grid_axes(coarse: float) -> list[np.ndarray]:
    """A rectilinear grid, fine only where the fingers are (they need ~6 mm, the body does not)."""
    fine = 0.45 * coarse
    return [
        _graded_axis(-0.95, 0.95, coarse, fine, [(-0.95, -0.70), (0.70, 0.95)]),
        _graded_axis(-1.0, 0.78, coarse, fine, [(0.355, 0.525)]),
        _graded_axis(-0.16, 0.22, coarse, fine, [(-0.025, 0.025)]),
    ]


def _surface(prims: list[_Primitive], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    axes = _grid_axes(spacing)
    sdf = _grid_sdf(axes, prims)
    # Grid values near zero put a vertex on every edge next to that grid point: slivers. Pushing
    # them 1 mm off the surface moves it by at most that much and keeps triangles well shaped.
    sdf = np.where(np.abs(sdf) < SNAP, np.where(sdf < 0, -SNAP, SNAP), sdf)
    # Marching cubes in index space; an axis-aligned edge maps linearly to its physical segment.
    verts, faces, _, _ = marching_cubes(sdf, level=0.0)
    verts = np.stack([np.interp(verts[:, k], np.arange(len(axes[k])), axes[k]) for k in range(3)], axis=1)
    # marching cubes can emit zero-area triangles and vertices used by nothing; drop both.
    a, b, c = (verts[faces[:, k]] for k in range(3))
    faces = faces[np.linalg.norm(np.cross(b - a, c - a), axis=1) > 1e-14]
    used = np.unique(faces)
    remap = np.full(len(verts), -1)
    remap[used] = np.arange(len(used))
    verts, faces = verts[used], remap[faces]
    if _signed_volume(verts, faces) < 0:  # outward normals, whatever marching cubes' convention
        faces = faces[:, ::-1]
    return verts, faces


def _signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (verts[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6)


def _vertex_adjacency(num_vertices: int, faces: np.ndarray) -> sp.csr_matrix:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.concatenate([edges, edges[:, ::-1]])
    adj = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(num_vertices,) * 2).tocsr()
    adj.data[:] = 1.0
    return adj


def _skinning_weights(labels: np.ndarray, adjacency: sp.csr_matrix, iterations: int = 10) -> np.ndarray:
    """Hard part labels diffused along the surface (not through space, so the legs never mix)."""
    weights = np.zeros((len(labels), NUM_JOINTS))
    weights[np.arange(len(labels)), labels] = 1.0
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    mean_of_neighbours = sp.diags(1 / degree) @ adjacency
    for _ in range(iterations):
        weights = 0.5 * weights + 0.5 * (mean_of_neighbours @ weights)
    return weights / weights.sum(axis=1, keepdims=True)


def _joint_regressor(vertices: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Non-negative rows summing to 1 that reproduce each joint from nearby vertices (SMPL-style regressor)."""
    regressor = np.zeros((NUM_JOINTS, len(vertices)))
    for j, joint in enumerate(joints):
        order = np.argsort(np.linalg.norm(vertices - joint, axis=1))
        for count in (24, 64, 160, 400):
            near = order[:count]
            # The affine constraint sum(w) = 1 as a heavily weighted extra row of the NNLS system.
            system = np.vstack([vertices[near].T, 100.0 * np.ones(count)])
            w, residual = nnls(system, np.concatenate([joint, [100.0]]))
            if residual < 1e-7:
                break
        else:
            raise RuntimeError(f"stand-in joint {SMPLX_JOINT_NAMES[j]} lies outside the hull of its nearest vertices")
        regressor[j, near] = w / w.sum()
    return regressor


def _axis_points(vertices: np.ndarray, labels: np.ndarray, prims: list[_Primitive]) -> np.ndarray:
    """The point on each vertex's primitive axis (segment, or ellipsoid centre line) nearest to it."""
    out = np.empty_like(vertices)
    for index, prim in enumerate(prims):
        sel = labels == index
        p = vertices[sel]
        if prim.radii is not None:
            centre = np.array(prim.a)
            longest = int(np.argmax(prim.radii))
            foot = centre + np.outer(p[:, longest] - centre[longest], np.eye(3)[longest])
        else:
            a, b = np.array(prim.a), np.array(prim.b)
            t = np.clip((p - a) @ (b - a) / np.dot(b - a, b - a), 0, 1)
            foot = a + t[:, None] * (b - a)
        out[sel] = foot
    return out


def _shape_directions(vertices, normals, labels, prims, joints, rng) -> np.ndarray:
    """(V, 3, 20): 10 body-shape directions (height, girth, ...) then 10 local facial expression bumps."""
    dirs = np.zeros((len(vertices), 3, NUM_BETAS + NUM_EXPRESSION))
    y = vertices[:, 1]
    x = vertices[:, 0]
    hip_y = joints[J["left_hip"], 1]
    dirs[:, 1, 0] = 0.035 * y  # stature: ~6 cm per unit, about the pelvis
    hands_or_head = np.isin([prims[i].joint for i in labels], [J["head"], J["jaw"], J["left_eye"], J["right_eye"]]
                            + list(range(LEFT_HAND.start, RIGHT_HAND.stop)) + [J["left_wrist"], J["right_wrist"]])
    girth_scale = np.where(hands_or_head, 0.3, 1.0)
    dirs[:, :, 1] = 0.12 * girth_scale[:, None] * (vertices - _axis_points(vertices, labels, prims))
    dirs[:, 0, 2] = 0.05 * np.sign(x) * np.maximum(np.abs(x) - 0.15, 0.0)  # shoulder width and arm length
    torso = np.exp(-((y - 0.15) / 0.18) ** 2) * (np.abs(x) < 0.2)
    dirs[:, 2, 3] = 0.25 * torso * vertices[:, 2]  # belly and chest depth
    dirs[:, 1, 4] = 0.05 * np.minimum(y - hip_y, 0.0)  # leg length
    for k in range(5, NUM_BETAS):  # smooth seeded bulges along the normals
        freq = rng.normal(size=(3, 3)) * 4.0
        phase = rng.uniform(0, 2 * np.pi, size=3)
        field = np.sin(vertices @ freq + phase).sum(axis=1) / 3
        dirs[:, :, k] = 0.008 * field[:, None] * normals
    head = joints[J["head"]]
    for k in range(NUM_EXPRESSION):  # bumps on the face (front of the head)
        theta, phi = rng.uniform(-0.9, 0.9), rng.uniform(-0.6, 0.3)
        centre = head + np.array([0.07 * np.sin(theta), 0.08 + 0.08 * phi, 0.09 * np.cos(theta)])
        dist_sq = np.sum((vertices - centre) ** 2, axis=1)
        bump = np.where(dist_sq < 0.08**2, np.exp(-dist_sq / (2 * 0.02**2)), 0.0)  # cut at 4 sigma: local
        dirs[:, :, NUM_BETAS + k] = 0.006 * bump[:, None] * normals
    return dirs


def make_standin_arrays(seed: int = 0, spacing: float = GRID_SPACING) -> dict[str, np.ndarray]:
    """The stand-in body model as SMPL-X npz arrays; `seed` picks the free shape and expression directions."""
    import trimesh  # heavy import, only needed here

    joints, prims = _rest_joints_and_primitives()
    verts, faces = _surface(prims, spacing)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    labels = _nearest_primitive(verts, prims)
    adjacency = _vertex_adjacency(len(verts), faces)
    weights = _skinning_weights(np.array([prims[i].joint for i in labels]), adjacency)
    regressor = _joint_regressor(verts, joints)
    rng = np.random.default_rng(seed)
    shapedirs = _shape_directions(verts, np.asarray(mesh.vertex_normals), labels, prims, joints, rng)
    return {
        "v_template": verts.astype(np.float64),
        "f": faces.astype(np.int64),
        "shapedirs": shapedirs,
        "posedirs": np.zeros((len(verts), 3, (NUM_JOINTS - 1) * 9)),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": np.stack([np.array(SMPLX_PARENTS), np.arange(NUM_JOINTS)]).astype(np.int64),
        "hands_meanl": np.zeros(45),
        "hands_meanr": np.zeros(45),
        **_hand_components(seed),
    }


def _hand_components(seed: int) -> dict[str, np.ndarray]:
    """Orthonormal 45 x 45 hand pose directions with falling scales, as SMPL-X's `hands_components{l,r}` (PCA
    rows): enough for a fit stored as hand PCA coefficients (EasyMocap's) to mean one hand pose. Their own
    generator leaves the other arrays as they were before the stand-in had components."""
    rng = np.random.default_rng([seed, 45])
    scales = np.linspace(1.0, 0.2, 45)[:, None]
    return {key: scales * np.linalg.qr(rng.normal(size=(45, 45)))[0].T
            for key in ("hands_componentsl", "hands_componentsr")}


def write_standin(path: str | Path, seed: int = 0) -> Path:
    """Write the stand-in model npz to `path` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        np.savez(tmp, **make_standin_arrays(seed))
    return path
