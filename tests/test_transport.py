"""3D barycentric transport (Eqs. 2-3): rest pose, rigid motion, degenerate triangles, reference frames."""
import numpy as np
import pytest
import torch

from pig.body.rotation import axis_angle_to_matrix
from pig.body.transport import barycentric_points, surface_frames, transport_points, transport_rotation


def _mesh(rng, dtype=torch.float64):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    vertices = sphere.vertices * np.array([0.3, 0.9, 0.2]) + rng.normal(scale=0.01, size=sphere.vertices.shape)
    return torch.tensor(vertices, dtype=dtype), torch.tensor(sphere.faces, dtype=torch.long)


def _attachments(rng, faces, n=200):
    face_ids = torch.tensor(rng.integers(0, faces.shape[0], n))
    bary = torch.tensor(rng.dirichlet(np.ones(3), n))
    return face_ids, bary


def _run(canon, posed, faces, face_ids, bary, anchors):
    x_init = barycentric_points(canon[None], faces, face_ids, bary)[0]
    frames_c = surface_frames(canon[None], faces, face_ids)[0]
    frames_p = surface_frames(posed, faces, face_ids)
    rot = transport_rotation(frames_p, frames_c)
    return transport_points(anchors, x_init, barycentric_points(posed, faces, face_ids, bary), rot), rot, x_init


def test_rest_pose_returns_canonical_anchors(rng):
    canon, faces = _mesh(rng)
    face_ids, bary = _attachments(rng, faces)
    x_init = barycentric_points(canon[None], faces, face_ids, bary)[0]
    anchors = x_init + torch.tensor(rng.normal(scale=0.05, size=x_init.shape))
    moved, rot, _ = _run(canon, canon[None], faces, face_ids, bary, anchors)
    torch.testing.assert_close(moved[0], anchors, rtol=0, atol=1e-14)
    torch.testing.assert_close(rot[0], torch.eye(3, dtype=rot.dtype).expand_as(rot[0]), rtol=0, atol=1e-14)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_rigid_motion_moves_anchors_rigidly(rng, dtype, tol):
    canon, faces = _mesh(rng, dtype)
    face_ids, bary = _attachments(rng, faces)
    x_init = barycentric_points(canon[None], faces, face_ids, bary)[0]
    anchors = x_init + torch.tensor(rng.normal(scale=0.1, size=x_init.shape), dtype=dtype)
    q = axis_angle_to_matrix(torch.tensor([[0.3, -2.5, 1.1], [3.1, 0.0, 0.05]], dtype=dtype))
    shift = torch.tensor([[0.5, -1.0, 2.0], [-3.0, 0.2, 0.0]], dtype=dtype)
    posed = canon[None] @ q.transpose(1, 2) + shift[:, None]
    moved, rot, _ = _run(canon, posed, faces, face_ids, bary, anchors)
    expected = anchors[None] @ q.transpose(1, 2) + shift[:, None]
    assert (moved - expected).abs().max() < tol
    assert (rot - q[:, None]).abs().max() < tol


def test_body_model_global_motion_is_rigid():
    standin = pytest.importorskip("pig.body.standin")
    from pig.body.model import BodyModel

    model = BodyModel(standin.make_standin_arrays(0)).to(torch.float64)
    rng = np.random.default_rng(1)
    face_ids, bary = _attachments(rng, model.faces, 500)
    pose = torch.zeros(2, 55, 3, dtype=torch.float64)
    pose[1, 0] = torch.tensor([0.4, 1.3, -0.2])
    transl = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.1, 2.0]], dtype=torch.float64)
    out = model(pose, transl=transl)
    canon = out.vertices[0]
    x_init = barycentric_points(canon[None], faces := model.faces, face_ids, bary)[0]
    anchors = x_init + torch.tensor(rng.normal(scale=0.05, size=x_init.shape))
    moved, _, _ = _run(canon, out.vertices[1:], faces, face_ids, bary, anchors)
    # Global orientation pivots about the pelvis joint; the whole body moves as one rigid body.
    q = axis_angle_to_matrix(pose[1, 0])
    pelvis = out.joints[0, 0]
    expected = (anchors - pelvis) @ q.T + out.joints[1, 0]
    assert (moved[0] - expected).abs().max() < 1e-5


def test_frames_match_reference_and_are_proper(rng):
    canon, faces = _mesh(rng)
    face_ids, _ = _attachments(rng, faces, 50)
    frames = surface_frames(canon[None], faces, face_ids)[0].numpy()
    tri = canon.numpy()[faces.numpy()[face_ids.numpy()]]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    t = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(frames[:, :, 0], t, atol=1e-12)
    np.testing.assert_allclose(frames[:, :, 2], n, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-12)


def test_degenerate_and_flipped_triangles_give_finite_proper_rotations():
    tris = torch.tensor([
        [[0, 0, 0], [1, 0, 0], [0, 1, 0]],  # regular
        [[0, 0, 0], [0, 0, 0], [0, 0, 0]],  # all corners equal
        [[0, 0, 0], [0, 0, 0], [0, 1, 0]],  # zero first edge
        [[0, 0, 0], [1, 0, 0], [2, 0, 0]],  # collinear
        [[0, 0, 0], [1, 0, 0], [0.5, 1e-9, 0]],  # sliver, nearly flat
        [[0, 0, 0], [0, 1, 0], [1, 0, 0]],  # flipped orientation
    ], dtype=torch.float64, requires_grad=True)
    vertices = tris.reshape(1, -1, 3)
    faces = torch.arange(18).reshape(6, 3)
    ids = torch.arange(6)
    frames = surface_frames(vertices, faces, ids)
    reference = surface_frames(torch.tensor([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], dtype=torch.float64), torch.arange(3)[None], torch.zeros(6, dtype=torch.long))
    rot = transport_rotation(frames, reference[0])
    assert torch.isfinite(rot).all()
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(rot @ rot.transpose(-1, -2), eye.expand_as(rot), atol=1e-9, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(1, 6, dtype=torch.float64), atol=1e-9, rtol=0)
    rot.sum().backward()
    assert torch.isfinite(tris.grad).all()


def _mesh_with_degenerate_triangles(dtype=torch.float64):
    """An ellipsoid mesh where one triangle is collinear, one has three coincident corners (which leaves
    its three edge neighbours with two coincident corners each): (vertices, faces, {name: face id})."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=1)
    vertices = sphere.vertices * np.array([0.3, 0.9, 0.2])
    faces = np.asarray(sphere.faces)
    collinear = 0
    a, b, c = faces[collinear]
    vertices[c] = 0.3 * vertices[a] + 0.7 * vertices[b]
    touching = np.isin(faces, faces[collinear]).any(axis=1)
    coincident = int(np.flatnonzero(~touching)[5])
    vertices[faces[coincident]] = vertices[faces[coincident]].mean(axis=0)
    shares_edge = (np.isin(faces, faces[coincident]).sum(axis=1) == 2)
    named = {"collinear": collinear, "coincident": coincident}
    named.update({f"two_coincident_{i}": int(f) for i, f in enumerate(np.flatnonzero(shares_edge))})
    return torch.tensor(vertices, dtype=dtype), torch.tensor(faces, dtype=torch.long), named


def test_degenerate_triangles_are_what_the_mesh_says():
    vertices, faces, named = _mesh_with_degenerate_triangles()
    tri = vertices[faces[list(named.values())]]
    area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
    assert len(named) == 5 and area.max() < 1e-15
    assert (tri[1] == tri[1, 0]).all()  # coincident corners
    assert (tri[0, 1] - tri[0, 0]).norm() > 0.1  # collinear, not coincident


HALF_TURN_AXES = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1], [0.2, -0.5, 0.9]]


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_degenerate_triangles_rotate_with_the_body(rng, dtype, tol):
    """Half turns about several axes and a generic rotation, plus a shift: anchors on zero-area triangles
    (collinear, coincident corners) move rigidly, with proper rotations and finite gradients."""
    vertices, faces, named = _mesh_with_degenerate_triangles(dtype)
    degenerate = torch.tensor(list(named.values()))
    face_ids = torch.cat([degenerate.repeat_interleave(4), torch.tensor(rng.integers(0, faces.shape[0], 20))])
    bary = torch.tensor(rng.dirichlet(np.ones(3), len(face_ids)))
    x_init = barycentric_points(vertices[None], faces, face_ids, bary)[0]
    anchors = x_init + torch.tensor(rng.normal(scale=0.1, size=x_init.shape), dtype=dtype)
    axes = torch.tensor(HALF_TURN_AXES, dtype=torch.float64)
    generic = torch.tensor([[0.3, -2.5, 1.1]], dtype=torch.float64)
    axis_angles = torch.cat([np.pi * axes / axes.norm(dim=1, keepdim=True), generic])
    q = axis_angle_to_matrix(axis_angles).to(dtype)
    shift = torch.tensor(rng.normal(size=(len(q), 3)), dtype=dtype)
    posed = (vertices[None] @ q.transpose(1, 2) + shift[:, None]).requires_grad_(True)
    moved, rot, _ = _run(vertices, posed, faces, face_ids, bary, anchors)
    expected = anchors[None] @ q.transpose(1, 2) + shift[:, None]
    assert torch.isfinite(moved).all() and torch.isfinite(rot).all()
    assert (moved - expected).abs().max() < tol
    assert (rot - q[:, None]).abs().max() < tol
    det = torch.linalg.det(rot.double())
    torch.testing.assert_close(det, torch.ones_like(det), atol=tol, rtol=0)
    moved.sum().backward()
    assert torch.isfinite(posed.grad).all()


def test_degenerate_frames_follow_the_surface():
    """The borrowed normal is the surface's: on the ellipsoid it points outwards, like the neighbours'."""
    vertices, faces, named = _mesh_with_degenerate_triangles()
    ids = torch.tensor(list(named.values()))
    frames = surface_frames(vertices[None], faces, ids)[0]
    centroids = vertices[faces[ids]].mean(dim=1)
    outward = centroids / torch.tensor([0.3, 0.9, 0.2], dtype=torch.float64) ** 2  # ellipsoid gradient
    cosine = (frames[:, :, 2] * outward).sum(-1) / outward.norm(dim=-1)
    assert (cosine > 0.8).all()
    eye = torch.eye(3, dtype=torch.float64).expand(len(ids), 3, 3)
    torch.testing.assert_close(frames.transpose(1, 2) @ frames, eye, atol=1e-12, rtol=0)


def test_sync_free_frames_equal_the_checked_ones():
    """`sync_free` (the real-time frame graph) always computes the neighbourhood sums instead of asking the device
    whether any triangle needs them: the frames are the same, bit for bit, on a regular mesh (where the checked
    path skips the sums) and on one with degenerate triangles (where both use them)."""
    rng = np.random.default_rng(3)
    regular = torch.tensor(rng.normal(size=(1, 30, 3)))
    faces = torch.tensor(np.stack([rng.permutation(30)[:3] for _ in range(20)]))
    ids = torch.arange(20)
    assert torch.equal(surface_frames(regular, faces, ids, sync_free=True), surface_frames(regular, faces, ids))
    degenerate = regular.clone()
    degenerate[0, faces[3, 1]] = degenerate[0, faces[3, 0]]  # a zero first edge
    degenerate[0, faces[7, 2]] = 2 * degenerate[0, faces[7, 1]] - degenerate[0, faces[7, 0]]  # collinear corners
    assert torch.equal(surface_frames(degenerate, faces, ids, sync_free=True), surface_frames(degenerate, faces, ids))
