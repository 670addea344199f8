"""Metrics from ground truth (issue 13): nearest points on triangles, region masks and region PSNR/SSIM, geometry
error against closed forms, correspondence drift, and the render/evaluate stages on a tiny synthetic capture."""
import json
import math
import shutil
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
import trimesh

from pig.data.ground_truth import GT_MESHES, SPLATS, SplatTrack, TrueMeshes
from pig.data.raw import CaptureError
from pig.metrics import geometry
from pig.metrics.geometry import GeometrySums, ground_truth_geometry, match_to_surfaces, sample_surface
from pig.metrics.regions import BACKGROUND, BODY, GARMENT, region_labels, region_psnr, region_ssim
from pig.metrics.ssim import ssim_map
from pig.metrics.surface import TriangleMesh, closest_on_triangles

GEOMETRY_KEYS = ["accuracy_mm_garment", "accuracy_mm_body", "completeness_mm_garment", "completeness_mm_body",
                 "drift_mm", "drift_mm_last"]
REGION_KEYS = ["psnr_garment", "psnr_body", "psnr_background", "ssim_garment", "ssim_body", "ssim_background"]


# ---- closest points on triangles ----

def test_closest_on_triangles_matches_trimesh(rng):
    triangles = rng.normal(size=(5000, 3, 3))
    points = rng.normal(size=(5000, 3)) * 2
    bary, dist = closest_on_triangles(points, triangles)
    reference = trimesh.triangles.closest_point(triangles, points)
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", bary, triangles), reference, atol=1e-9)
    np.testing.assert_allclose(dist, np.linalg.norm(points - reference, axis=1), atol=1e-9)
    assert bary.min() >= 0 and np.allclose(bary.sum(axis=1), 1)


def test_closest_on_degenerate_triangles_is_the_segment_or_point():
    p = np.array([[0.3, 2.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    collinear = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])  # zero area: the segment [0, 2] on x
    point = np.zeros((3, 3))  # all corners equal
    for triangle, expected in ((collinear, [2.0, 3.0, 1.0]), (point, np.linalg.norm(p, axis=1))):
        bary, dist = closest_on_triangles(p, np.broadcast_to(triangle, (3, 3, 3)))
        assert np.isfinite(bary).all()
        np.testing.assert_allclose(dist, expected, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(p - bary @ triangle, axis=1), expected, atol=1e-12)


def test_nearest_on_mesh_is_exact_against_all_triangles(rng):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    vertices = sphere.vertices + rng.normal(0, 0.01, sphere.vertices.shape)  # uneven triangles
    faces = np.concatenate([sphere.faces, [[0, 0, 0], [1, 2, 1]]])  # with degenerate triangles
    points = np.concatenate([rng.normal(0, 0.3, (300, 3)), rng.normal(0, 5.0, (20, 3))])  # inside, near, far off
    found = TriangleMesh(vertices, faces).nearest(points)
    corners = vertices[faces]
    brute = np.array([closest_on_triangles(np.broadcast_to(q, (len(faces), 3)), corners)[1].min() for q in points])
    np.testing.assert_allclose(found.distance, brute, atol=1e-12)
    on_surface = np.einsum("nk,nkd->nd", found.bary, corners[found.face])
    np.testing.assert_allclose(np.linalg.norm(points - on_surface, axis=1), brute, atol=1e-12)


# ---- region masks and region PSNR/SSIM ----

def _camera(width=16, height=16, focal=20.0, R=np.eye(3), T=np.zeros(3)):
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    return SimpleNamespace(name="cam", K=K, R=R, T=T, width=width, height=height)


def _expected_labels(camera, triangles):
    """Labels by hand: every triangle faces the camera at a constant depth (z plane); the nearest covering one wins."""
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(float)
    labels = np.zeros((camera.height, camera.width), np.uint8)
    depth = np.full(labels.shape, np.inf)
    for corners, label in triangles:
        z = corners[0, 2]
        if z <= 0:
            continue  # behind the camera
        pixels = (camera.K @ (corners / corners[:, 2:]).T).T[:, :2]
        a, b, c = pixels

        def side(p, q):
            return (q[0] - p[0]) * (v - p[1]) - (q[1] - p[1]) * (u - p[0])

        s = np.stack([side(a, b), side(b, c), side(c, a)])
        assert np.abs(s).min() > 1e-3, "a pixel centre lies on an edge: the scene is ambiguous"
        inside = (s > 0).all(axis=0) | (s < 0).all(axis=0)
        nearer = inside & (z < depth)
        labels[nearer], depth[nearer] = label, z
    return labels


@pytest.mark.parametrize("garment_depth", [2.0, 6.0])  # garment in front of the body, then behind it
def test_region_labels_of_a_hand_built_scene(garment_depth):
    camera = _camera()
    body = np.array([[-1.13, -1.07, 4.0], [1.21, -0.93, 4.0], [0.05, 1.17, 4.0]])
    garment = np.array([[0.013, 0.021, 0.0], [0.61, 0.07, 0.0], [0.09, 0.57, 0.0]]) * garment_depth / 2
    garment[:, 2] = garment_depth
    hidden = np.array([[-0.5, -0.5, -1.0], [0.5, -0.5, -1.0], [0.0, 0.5, -1.0]])  # behind the camera: never seen
    surfaces = [(np.concatenate([body, hidden]), np.array([[0, 1, 2], [3, 4, 5]])), (garment, np.array([[0, 1, 2]]))]
    labels = region_labels(surfaces, camera)
    expected = _expected_labels(camera, [(body, BODY), (garment, GARMENT)])
    np.testing.assert_array_equal(labels, expected)
    # The scene exercises what it is meant to: all three labels, and occlusion where the two overlap.
    assert {BACKGROUND, BODY, GARMENT} <= set(np.unique(labels).tolist())
    covered_by_both = (_expected_labels(camera, [(body, BODY)]) == BODY) & (
        _expected_labels(camera, [(garment, GARMENT)]) == GARMENT)
    assert covered_by_both.any()
    assert (labels[covered_by_both] == (GARMENT if garment_depth < 4 else BODY)).all()


@pytest.mark.parametrize("size", [(1, 1), (3, 2)])
def test_region_labels_and_psnr_of_tiny_images(size):
    camera = _camera(*size, focal=2.0)
    body = np.array([[-1.13, -1.07, 4.0], [1.21, -0.93, 4.0], [0.05, 1.17, 4.0]])
    surfaces = [(body, np.array([[0, 1, 2]])), (np.zeros((0, 3)), np.zeros((0, 3), np.int64))]
    labels = region_labels(surfaces, camera)
    np.testing.assert_array_equal(labels, _expected_labels(camera, [(body, BODY)]))
    assert (labels == BODY).any()
    x = torch.full((1, 3, size[1], size[0]), 0.5)
    psnr = region_psnr(x, x + 0.1, torch.from_numpy(labels)[None])[0]
    assert psnr[BODY] == pytest.approx(20.0) and math.isnan(psnr[GARMENT])


def test_region_labels_follow_the_camera_pose():
    """A camera turned 180 degrees about y looks from the other side: the same scene, mirrored in x."""
    body = np.array([[-1.13, -1.07, 4.0], [1.21, -0.93, 4.0], [0.05, 1.17, 4.0]])
    surfaces = [(body, np.array([[0, 1, 2]])), (np.zeros((0, 3)), np.zeros((0, 3), np.int64))]
    turned = _camera(R=np.diag([-1.0, 1.0, -1.0]), T=np.array([0.0, 0.0, 8.0]))  # camera centre at z = 8
    labels = region_labels(surfaces, turned)
    mirrored = body * [-1, 1, 1]
    mirrored[:, 2] = 4.0
    np.testing.assert_array_equal(labels, _expected_labels(_camera(), [(mirrored, BODY)]))


def test_region_psnr_and_ssim_against_direct_masks(rng):
    x = torch.from_numpy(rng.random((2, 3, 24, 20)))
    y = torch.from_numpy(rng.random((2, 3, 24, 20)))
    labels = torch.from_numpy(rng.integers(0, 3, (2, 24, 20)))
    labels[1][labels[1] == GARMENT] = BODY  # the second image has no garment
    y[0, :, labels[0] == BODY] = x[0, :, labels[0] == BODY]  # the first image's body is rendered exactly
    psnr = region_psnr(x, y, labels).numpy()
    similarity = ssim_map(x, y)
    ssim = region_ssim(similarity, labels).numpy()
    for b in range(2):
        for region in (BACKGROUND, BODY, GARMENT):
            mask = (labels[b] == region).numpy()
            inner = mask[5:-5, 5:-5]
            if not mask.any():
                assert math.isnan(psnr[b, region]) and math.isnan(ssim[b, region])
                continue
            mse = ((x[b] - y[b]).numpy() ** 2)[:, mask].mean()
            assert psnr[b, region] == pytest.approx(10 * np.log10(1 / mse) if mse > 0 else math.inf)
            assert ssim[b, region] == pytest.approx(similarity[b].mean(0).numpy()[inner].mean())
    assert psnr[0, BODY] == math.inf and math.isnan(psnr[1, GARMENT])


def test_region_ssim_of_a_region_only_on_the_border_is_nan():
    x = torch.rand(1, 3, 16, 16)
    labels = torch.zeros(1, 16, 16, dtype=torch.long)
    labels[0, :3] = GARMENT  # within the 5-pixel border the SSIM window does not reach
    values = region_ssim(ssim_map(x, x * 0.5), labels)[0]
    assert math.isnan(values[GARMENT]) and not math.isnan(values[BACKGROUND])
    assert not math.isnan(region_psnr(x, x * 0.5, labels)[0, GARMENT])


# ---- geometry error against closed forms ----

def _sphere(radius, centre, subdivisions=3):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return mesh.vertices + centre, mesh.faces


def _inscribed(vertices, faces, centre):
    """Smallest distance from the centre to the polyhedron's faces (all faces are tangent-ish planes)."""
    return TriangleMesh(vertices, faces).nearest(np.asarray(centre)[None]).distance[0]


def test_geometry_against_spheres_of_known_radius(monkeypatch):
    """Splats on spheres of radius r + d around true spheres of radius r: accuracy d and completeness d (within the
    polyhedron's own deviation from its sphere), per region; splats that render nothing change neither."""
    monkeypatch.setattr(geometry, "SURFACE_SAMPLES", 3000)
    specs = {"body": (0.5, np.zeros(3), 0.02), "garment": (0.3, np.array([2.0, 0.0, 0.0]), 0.007)}
    surfaces = [_sphere(r, c) for r, c, _ in specs.values()]
    # The completeness samples are drawn as add_frame draws them; each gets its splat straight outside it.
    rng = np.random.default_rng(4)
    samples = [sample_surface(v, f, geometry.SURFACE_SAMPLES, rng) for v, f in surfaces]
    centres = np.concatenate([c + (s - c) * (r + d) / np.linalg.norm(s - c, axis=1, keepdims=True)
                              for s, (r, c, d) in zip(samples, specs.values())])
    opacities = np.concatenate([np.full(len(samples[0]), 0.01), np.full(len(samples[1]), 1e6)])  # extreme weights
    # Invisible splats: far off (would spoil accuracy if weighted) and right on the surface (would spoil completeness).
    ghosts = np.array([[0.0, 3.0, 0.0], [0.0, 0.0, 0.5], [2.3, 0.0, 0.0]])
    centres = np.concatenate([centres, ghosts])
    opacities = np.concatenate([opacities, [0.0, 0.0, geometry.MIN_OPACITY / 2]])
    sums = GeometrySums.zeros(2)
    match = match_to_surfaces(centres, surfaces)
    sums.add_frame(match, opacities, centres, surfaces, np.random.default_rng(4))
    for index, (r, c, d) in enumerate(specs.values()):
        slack = r - _inscribed(*surfaces[index], c)  # the polyhedron lies between radii r - slack and r
        assert 0 < slack < 0.01 * r
        assert d - 1e-12 <= sums.accuracy()[index] <= d + slack
        assert d - 1e-12 <= sums.completeness()[index] <= d + slack
    np.testing.assert_array_equal(match.region[:len(samples[0])], 0)
    np.testing.assert_array_equal(match.region[len(samples[0]):-3], 1)


def test_geometry_of_a_region_without_splats_or_surface_is_nan():
    plane = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    centres = np.array([[0.2, 0.2, 0.01], [0.3, 0.1, -0.01]])
    sums = GeometrySums.zeros(2)
    sums.add_frame(match_to_surfaces(centres, [plane, empty]), np.ones(2), centres, [plane, empty],
                   np.random.default_rng(0))
    assert sums.accuracy()[0] == pytest.approx(0.01) and math.isnan(sums.accuracy()[1])
    assert math.isnan(sums.completeness()[1]) and sums.completeness()[0] > 0.0
    invisible = GeometrySums.zeros(2)
    invisible.add_frame(match_to_surfaces(centres, [plane, empty]), np.zeros(2), centres, [plane, empty],
                        np.random.default_rng(0))
    assert np.isnan(invisible.accuracy()).all() and np.isnan(invisible.completeness()).all()


# ---- correspondence drift ----

def _rotation_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _truth(body_frames, body_faces, garment_frames, garment_faces, frames):
    return TrueMeshes(None, np.asarray(frames), np.asarray(body_frames), body_faces, np.asarray(garment_frames),
                      garment_faces)


def _grid(n=6, size=1.0):
    """A flat grid of triangles in the z = 0 plane, n x n squares of `size`."""
    x, y = np.meshgrid(np.linspace(0, size, n + 1), np.linspace(0, size, n + 1))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None]
    i = i.ravel()
    faces = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    return vertices, faces


def _anchors(rng, faces, count):
    face = rng.integers(0, len(faces), count)
    bary = rng.dirichlet([2.0, 2.0, 2.0], count)  # inside the triangle: the tie is unique
    return face, bary


def _on(vertices, faces, face, bary):
    return np.einsum("nk,nkd->nd", bary, vertices[faces[face]])


@pytest.fixture
def moving_scene(rng):
    """A body sphere and a garment grid over 5 frames: non-rigid wobble, then a turn reaching 180 degrees."""
    sphere_v, sphere_f = _sphere(0.4, np.array([0.0, 0.0, 1.0]), subdivisions=2)
    grid_v, grid_f = _grid()
    grid_v = grid_v + [-0.5, -0.5, -0.5]
    angles = np.linspace(0, np.pi, 5)
    body = np.stack([(sphere_v + rng.normal(0, 0.005, sphere_v.shape)) @ _rotation_z(a).T for a in angles])
    garment = np.stack([(grid_v + [0, 0, 0.02 * t]) @ _rotation_z(a).T for t, a in enumerate(angles)])
    return _truth(body, sphere_f, garment, grid_f, [10, 11, 12, 13, 14]), angles


def test_drift_is_zero_for_anchors_that_follow_the_true_surface(moving_scene, rng):
    truth, _ = moving_scene
    body_face, body_bary = _anchors(rng, truth.body_faces, 200)
    garment_face, garment_bary = _anchors(rng, truth.garment_faces, 100)
    centres = np.stack([np.concatenate([_on(truth.body_vertices[t], truth.body_faces, body_face, body_bary),
                                        _on(truth.garment_vertices[t], truth.garment_faces, garment_face, garment_bary)])
                        for t in range(5)])
    track = SplatTrack(truth.frames, centres, np.ones(centres.shape[:2]))
    scores = ground_truth_geometry(track, truth, geometry_frames=2)
    assert scores["drift_mm"] == pytest.approx(0.0, abs=1e-9)
    assert scores["drift_mm_last"] == pytest.approx(0.0, abs=1e-9)
    assert scores["accuracy_mm_body"] == pytest.approx(0.0, abs=1e-9)
    assert scores["accuracy_mm_garment"] == pytest.approx(0.0, abs=1e-9)
    assert scores["completeness_mm_body"] > 0  # 300 anchors do not cover the surfaces' samples


def test_drift_equals_a_constant_shift(rng):
    """Anchors shifted off the true garment plane by a constant vector of length d (its normal at the first frame)
    while the plane moves and turns: the drift is d in every frame."""
    grid_v, grid_f = _grid()
    steps = 4
    garment = np.stack([grid_v @ _rotation_z(np.pi * t / (steps - 1)).T + [0.1 * t, -0.05 * t, 0.3 * t]
                        for t in range(steps)])
    body_v, body_f = _sphere(0.1, np.array([0.5, 0.5, 5.0]), subdivisions=1)  # far away: never the nearest
    truth = _truth(np.stack([body_v] * steps), body_f, garment, grid_f, range(steps))
    face, bary = _anchors(rng, grid_f, 150)
    d = 0.037
    shift = np.array([0.0, 0.0, d])
    centres = np.stack([_on(garment[t], grid_f, face, bary) + shift for t in range(steps)])
    scores = ground_truth_geometry(SplatTrack(truth.frames, centres, np.ones(centres.shape[:2])), truth, 4)
    assert scores["drift_mm"] == pytest.approx(d * 1000, rel=1e-9)
    assert scores["drift_mm_last"] == pytest.approx(d * 1000, rel=1e-9)
    assert scores["accuracy_mm_garment"] == pytest.approx(d * 1000, rel=1e-9)
    assert math.isnan(scores["accuracy_mm_body"])  # no splat is nearest to the body


def test_drift_of_anchors_left_behind_by_a_180_degree_turn(moving_scene, rng):
    """Anchors that stay where they were while the true mesh turns about z: drift 2 rho sin(angle / 2) per frame,
    2 rho at the 180-degree frame (rho: distance from the axis), no reflection or NaN."""
    truth, angles = moving_scene
    face, bary = _anchors(rng, truth.garment_faces, 120)
    start = _on(truth.garment_vertices[0], truth.garment_faces, face, bary)
    track = SplatTrack(truth.frames, np.stack([start] * 5), np.ones((5, len(start))))
    scores = ground_truth_geometry(track, truth, 1)
    rho = np.linalg.norm(start[:, :2], axis=1)
    # The garment also rises 2 cm per frame, straight along the axis.
    per_frame = [np.mean(np.hypot(2 * rho * np.sin(a / 2), 0.02 * t)) for t, a in enumerate(angles)]
    assert scores["drift_mm_last"] == pytest.approx(per_frame[-1] * 1000, rel=1e-9)
    assert scores["drift_mm"] == pytest.approx(np.mean(per_frame) * 1000, rel=1e-9)


# ---- files ----

def test_true_meshes_refuse_bad_files(tmp_path):
    path = tmp_path / GT_MESHES
    good = dict(frames=np.arange(2), body_vertices=np.zeros((2, 4, 3), np.float32), body_faces=np.array([[0, 1, 2]]),
                garment_vertices=np.zeros((2, 3, 3), np.float32), garment_faces=np.array([[0, 1, 2]]))
    np.savez(path, **good)
    assert TrueMeshes.load(path).surfaces(1)[1][0].shape == (3, 3)
    with pytest.raises(CaptureError, match="no true meshes of frame"):
        TrueMeshes.load(path).require_frames([0, 5], "split 'novel_pose'")
    for change, message in (({"body_faces": np.array([[0, 1, 9]])}, "outside 0..3"),
                            ({"garment_vertices": np.zeros((3, 3, 3))}, r"must be \(2, V, 3\)"),
                            ({"body_vertices": np.full((2, 4, 3), np.nan)}, "NaN")):
        np.savez(path, **{**good, **change})
        with pytest.raises(CaptureError, match=message) as err:
            TrueMeshes.load(path)
        assert str(path) in str(err.value)
    path.write_bytes(b"not a zip")
    with pytest.raises(CaptureError, match="not a valid npz"):
        TrueMeshes.load(path)


def test_splat_track_round_trip_and_errors(tmp_path):
    track = SplatTrack(np.array([3, 4]), np.ones((2, 5, 3)), np.full((2, 5), 0.5))
    track.save(tmp_path / SPLATS)
    loaded = SplatTrack.load(tmp_path / SPLATS)
    np.testing.assert_array_equal(loaded.centres, track.centres)
    assert [p.name for p in tmp_path.iterdir()] == [SPLATS]  # no temporary left behind
    with pytest.raises(FileNotFoundError, match="rerun render"):
        SplatTrack.load(tmp_path / "missing" / SPLATS)
    np.savez(tmp_path / "bad.npz", frames=np.array([3, 4]), centres=np.ones((2, 5, 3)), opacities=np.ones((2, 4)))
    with pytest.raises(CaptureError, match="bad.npz: expected"):
        SplatTrack.load(tmp_path / "bad.npz")


# ---- the stages on a tiny synthetic capture ----

@pytest.fixture(scope="module")
def rendered(tiny_fit, tmp_path_factory):
    """novel_view renders of the tiny fit: on the capture with its true meshes, and on a copy without them."""
    from pig.render.api import RasterizerConfig
    from pig.stages.evaluate import EvaluateConfig
    from pig.stages.render import render_split

    capture, checkpoint = tiny_fit
    root = tmp_path_factory.mktemp("gtrender")
    real = root / "real_capture"
    shutil.copytree(capture, real, ignore=shutil.ignore_patterns(GT_MESHES))
    cfg = EvaluateConfig(timing_frames=1)
    out = {}
    for name, folder in (("synthetic", capture), ("real", real)):
        out[name] = (folder, root / name / "novel_view")
        render_split(checkpoint, folder, "novel_view", out[name][1], cfg, RasterizerConfig(backend="cpu"))
    return out, cfg


def test_preprocess_carries_the_true_meshes(small_capture):
    raw = small_capture.parent / "raw" / GT_MESHES
    assert (small_capture / GT_MESHES).read_bytes() == raw.read_bytes()


def test_evaluate_adds_ground_truth_metrics_only_with_true_meshes(rendered, tmp_path):
    from pig.data.capture import Capture
    from pig.metrics.regions import RegionLabeller
    from pig.stages.evaluate import evaluate_split

    out, cfg = rendered
    capture, renders = out["synthetic"]
    csv = evaluate_split(capture, renders, "novel_view", tmp_path / "synthetic", cfg, [0])[0]
    summary = json.loads(csv.with_suffix(".json").read_text())
    table = pd.read_csv(csv)
    assert set(REGION_KEYS) <= set(table.columns)
    assert set(REGION_KEYS + GEOMETRY_KEYS) <= set(summary)
    for key in ("psnr_body", "ssim_body", "accuracy_mm_body", "completeness_mm_body", "drift_mm", "drift_mm_last"):
        assert math.isfinite(summary[key]) and summary[key] >= 0, key
    assert summary["psnr_body"] == pytest.approx(table["psnr_body"].dropna().mean(), rel=1e-5)  # CSV: 6 digits
    # Splats of a 3-iteration fit sit near the body they started on: centimetres, not metres.
    assert summary["accuracy_mm_body"] < 100
    # The true meshes' labels agree with the capture's own masks (same cameras, same pixel convention).
    loaded = Capture.load(capture)
    cam, frame = loaded.views("novel_view")[0]
    labels = RegionLabeller(TrueMeshes.load(capture / GT_MESHES), loaded.cameras)(cam, frame)
    mask = loaded.mask(cam, frame) > 0
    assert (mask & (labels > 0)).sum() / (mask | (labels > 0)).sum() > 0.97  # 0.98..0.996 over its views

    real, real_renders = out["real"]
    assert not (real_renders / "lod0" / SPLATS).exists() and (renders / "lod0" / SPLATS).exists()
    csv = evaluate_split(real, real_renders, "novel_view", tmp_path / "real", cfg, [0])[0]
    summary = json.loads(csv.with_suffix(".json").read_text())
    assert not set(REGION_KEYS + GEOMETRY_KEYS) & set(summary)
    assert not set(REGION_KEYS) & set(pd.read_csv(csv).columns)


def test_evaluate_with_true_meshes_needs_the_splat_track(rendered, tmp_path):
    from pig.stages.evaluate import evaluate_split

    out, cfg = rendered
    capture, renders = out["synthetic"]
    copy = tmp_path / "renders"
    shutil.copytree(renders, copy)
    (copy / "lod0" / SPLATS).unlink()
    with pytest.raises(FileNotFoundError, match=f"{copy / 'lod0' / SPLATS} not found.*rerun render"):
        evaluate_split(capture, copy, "novel_view", tmp_path / "metrics", cfg, [0])


def test_renders_record_the_fingerprint_and_folder_of_their_capture(rendered):
    """The render stage's capture record (evaluate refuses renders of another capture: test_artifact_checks.py)."""
    import hashlib

    from pig.data.capture import Capture
    from pig.data.capture_record import RECORD

    out, _ = rendered
    capture, renders = out["synthetic"]
    record = json.loads((renders / RECORD).read_text())
    assert record == {"capture": str(capture.resolve()), "fingerprint": Capture.load(capture).fingerprint()}
    # The fingerprint's image part, recomputed here from the file listing (names and sizes).
    listing = "".join(f"{kind}/{cam.name}/{f.name} {f.stat().st_size}\n" for kind in ("images", "masks")
                      for cam in sorted((capture / kind).iterdir()) for f in sorted(cam.iterdir()))
    assert record["fingerprint"]["images"] == hashlib.sha256(listing.encode()).hexdigest()


# ---- the labels' cost (issue 38): only the rays that can meet a surface, each view once per process ----

def _whole_frame_labels(surfaces, camera):
    """Reference: every pixel's centre ray cast (the labels before issue 38)."""
    from pig.metrics.regions import camera_rays, mesh_caster

    origin, directions = camera_rays(camera)
    directions = directions.reshape(-1, 3)
    triangle = mesh_caster(surfaces).intersects_first(np.broadcast_to(origin, directions.shape), directions)
    labels = np.where(triangle < 0, BACKGROUND, np.where(triangle < len(surfaces[0][1]), BODY, GARMENT))
    return labels.astype(np.uint8).reshape(camera.height, camera.width)


class _CountingCaster:
    """A caster that counts the rays cast through it."""

    def __init__(self, caster):
        self.caster, self.rays = caster, 0

    def intersects_first(self, origins, directions):
        self.rays += len(directions)
        return self.caster.intersects_first(origins, directions)


def test_region_labels_cast_only_the_box_and_equal_every_pixels_cast(small_capture):
    from pig.data.capture import Capture
    from pig.metrics.regions import camera_rays, covered_box, mesh_caster

    capture = Capture.load(small_capture)
    truth = TrueMeshes.load(small_capture / GT_MESHES)
    cast, pixels = 0, 0
    for camera, frame in capture.views("novel_view") + capture.views("novel_pose"):
        surfaces, cam = truth.surfaces(frame), capture.cameras[camera]
        caster = _CountingCaster(mesh_caster(surfaces))
        labels = region_labels(surfaces, cam, caster, camera_rays(cam))
        np.testing.assert_array_equal(labels, _whole_frame_labels(surfaces, cam))
        rows, cols = covered_box(surfaces, cam)
        assert caster.rays == (rows.stop - rows.start) * (cols.stop - cols.start)
        assert (labels[rows, cols] != BACKGROUND).any()
        cast, pixels = cast + caster.rays, pixels + cam.width * cam.height
    assert cast < 0.8 * pixels  # the subject leaves part of each 48-pixel frame to the background


def test_covered_box_holds_every_pixel_a_surface_covers(rng):
    from pig.metrics.regions import covered_box

    camera = _camera(40, 30, focal=30.0)
    for _ in range(20):
        corners = rng.normal(0, 0.6, (4, 3, 3)) + [0.0, 0.0, 4.0]
        surfaces = [(corners[:2].reshape(-1, 3), np.arange(6).reshape(2, 3)),
                    (corners[2:].reshape(-1, 3), np.arange(6).reshape(2, 3))]
        labels = region_labels(surfaces, camera)
        rows, cols = covered_box(surfaces, camera)
        outside = labels.copy()
        outside[rows, cols] = BACKGROUND
        assert not outside.any()
        np.testing.assert_array_equal(labels, _whole_frame_labels(surfaces, camera))
    # A vertex behind the camera projects without bound: the whole frame, which still labels correctly.
    behind = [(np.array([[-1.0, -1.0, 4.0], [1.0, -1.0, 4.0], [0.0, 1.0, -1.0]]), np.array([[0, 1, 2]])),
              (np.zeros((0, 3)), np.zeros((0, 3), np.int64))]
    assert covered_box(behind, camera) == (slice(0, 30), slice(0, 40))
    np.testing.assert_array_equal(region_labels(behind, camera), _whole_frame_labels(behind, camera))
    # Vertices that all project outside the frame: nothing to cast.
    aside = [(np.array([[9.0, 0.0, 4.0], [10.0, 0.0, 4.0], [9.5, 1.0, 4.0]]), np.array([[0, 1, 2]])),
             (np.zeros((0, 3)), np.zeros((0, 3), np.int64))]
    rows, cols = covered_box(aside, camera)
    assert cols.start == cols.stop and not region_labels(aside, camera).any()


def test_labeller_on_threads_builds_each_frame_and_camera_once_and_a_cache_casts_each_view_once(small_capture,
                                                                                                 monkeypatch):
    from concurrent.futures import ThreadPoolExecutor

    from pig.data.capture import Capture
    from pig.metrics import regions

    capture = Capture.load(small_capture)
    truth = TrueMeshes.load(small_capture / GT_MESHES)
    views = capture.views("novel_pose") + capture.views("novel_view")
    calls = {"mesh_caster": 0, "camera_rays": 0, "region_labels": 0}
    for name in calls:
        def counted(*args, _name=name, _function=getattr(regions, name), **kwargs):
            calls[_name] += 1
            return _function(*args, **kwargs)
        monkeypatch.setattr(regions, name, counted)
    cache = regions.LabelCache(1 << 30)
    shared = regions.RegionLabeller(truth, capture.cameras, cache)
    with ThreadPoolExecutor(4) as pool:
        labels = list(pool.map(lambda view: shared(*view), views))
    assert calls == {"mesh_caster": len({f for _, f in views}), "camera_rays": len({c for c, _ in views}),
                     "region_labels": len(views)}
    for (camera, frame), got in zip(views, labels):
        np.testing.assert_array_equal(got, _whole_frame_labels(truth.surfaces(frame), capture.cameras[camera]))
    # Another labeller with the same cache (a second evaluation in the process) casts nothing and agrees.
    before = dict(calls)
    again = regions.RegionLabeller(truth, capture.cameras, cache)
    for (camera, frame), got in zip(views, labels):
        np.testing.assert_array_equal(again(camera, frame), got)
    assert calls == before
    # Moved surfaces are another key: cast afresh.
    moved = TrueMeshes(truth.path, truth.frames, truth.body_vertices + [0.0, 0.0, 0.05], truth.body_faces,
                       truth.garment_vertices, truth.garment_faces)
    regions.RegionLabeller(moved, capture.cameras, cache)(*views[0])
    assert calls["region_labels"] == before["region_labels"] + 1


def test_label_cache_keeps_the_most_recent_within_its_bytes():
    from pig.metrics.regions import LabelCache

    cache = LabelCache(250)
    for key in (b"a", b"b", b"c"):
        cache.put(key, np.full(100, ord(key), np.uint8))
    assert cache.get(b"a") is None and cache.bytes == 200
    assert cache.get(b"b")[0] == ord("b") and not cache.get(b"b").flags.writeable
    cache.put(b"d", np.zeros(100, np.uint8))  # b was used last: c goes
    assert cache.get(b"c") is None and cache.get(b"b") is not None


def test_evaluate_twice_in_a_process_casts_the_labels_once_and_agrees_with_every_pixels_labels(rendered, tmp_path,
                                                                                                monkeypatch):
    from dataclasses import replace

    from pig.data.capture import Capture
    from pig.data.render_store import RenderReader
    from pig.metrics import regions
    from pig.stages import evaluate

    out, cfg = rendered
    capture, renders = out["synthetic"]
    monkeypatch.setattr(evaluate, "LABELS", regions.LabelCache(1 << 30))  # nothing from the other tests
    casts = []
    real = regions.region_labels
    monkeypatch.setattr(regions, "region_labels", lambda *args: casts.append(1) or real(*args))
    # One label thread, then three: labels a batch (8 views) ahead or further.
    first = evaluate.evaluate_split(capture, renders, "novel_view", tmp_path / "a", replace(cfg, label_workers=1),
                                    [0])[0]
    cast_first = len(casts)
    second = evaluate.evaluate_split(capture, renders, "novel_view", tmp_path / "b", replace(cfg, label_workers=3),
                                     [0])[0]
    loaded = Capture.load(capture)
    views = loaded.views("novel_view")
    assert cast_first == len(views) and len(casts) == cast_first
    assert first.read_text() == second.read_text()
    summaries = [json.loads(path.with_suffix(".json").read_text()) for path in (first, second)]
    assert {k: v for k, v in summaries[0].items() if k in REGION_KEYS + GEOMETRY_KEYS} == \
        {k: v for k, v in summaries[1].items() if k in REGION_KEYS + GEOMETRY_KEYS}
    # Each image's region PSNR from the labels of every pixel's ray (the code before issue 38).
    table = pd.read_csv(first)
    truth = TrueMeshes.load(capture / GT_MESHES)
    reader = RenderReader(renders / "lod0", {name: (c.width, c.height) for name, c in loaded.cameras.items()})
    for row in table.itertuples():
        camera, frame = row.camera, int(row.frame)
        labels = _whole_frame_labels(truth.surfaces(frame), loaded.cameras[camera])
        x = torch.from_numpy(reader.image_u8(camera, frame)).float().div(255).permute(2, 0, 1)[None]
        mask = torch.from_numpy(loaded.mask(camera, frame) > 0)
        truth_image = torch.from_numpy(np.array(loaded.image_u8(camera, frame))).float().div(255)
        y = (truth_image * mask[..., None]).permute(2, 0, 1)[None]
        expected = region_psnr(x, y, torch.from_numpy(labels)[None])[0].numpy()
        got = np.array([row.psnr_background, row.psnr_body, row.psnr_garment], dtype=float)
        np.testing.assert_allclose(got, expected, rtol=1e-5)  # the CSV's 6 digits
