"""Export stage: 3DGS .ply files read back by an independent parser, correspondences, bad input, output rules."""
from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pytest
import torch

from pig.avatar.build import body_model_npz, build_avatar
from pig.avatar.checkpoint import load_avatar, save_checkpoint
from pig.avatar.config import AvatarConfig
from pig.avatar.export import write_splat_ply
from pig.body.params import SmplxParams
from pig.field.latent_grid import FieldConfig
from pig.field.precondition import PrecondConfig
from pig._cli import run_cli
from pig.stages.export import main
from body_fixture import tiny_body_model

SH_DEGREE = 2
TERMS = {"lpips": {"weight": 0.0, "net": "vgg", "state": "off", "detail": ""}}


def read_ply(path) -> tuple[list[str], dict[str, np.ndarray]]:
    """(property names in file order, {name: float32 column}) of a binary little-endian float-only PLY."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = [line for line in data[:end].decode("ascii").splitlines() if not line.startswith("comment ")]
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    count = int(lines[2].split()[2]) if lines[2].startswith("element vertex ") else None
    assert count is not None and lines[-1] == "end_header"
    names = []
    for line in lines[3:-1]:
        kind, dtype, name = line.split()
        assert (kind, dtype) == ("property", "float"), line
        names.append(name)
    values = np.frombuffer(data[end:], dtype="<f4")
    assert values.size == count * len(names), "body size does not match the header"
    table = values.reshape(count, len(names))
    return names, {name: table[:, i] for i, name in enumerate(names)}


def expected_columns(means, quats, scales, opacities, sh) -> dict[str, np.ndarray]:
    """The 3DGS fields of splats in the renderer's conventions, in float64: logit, log, channel-major f_rest."""
    means, quats, scales, opacities, sh = (np.asarray(torch.as_tensor(a).double()) for a in (means, quats, scales, opacities, sh))
    columns = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    columns.update({f"n{a}": np.zeros(len(means)) for a in "xyz"})
    columns.update({f"f_dc_{c}": sh[:, 0, c] for c in range(3)})
    rest = sh.shape[1] - 1
    for c in range(3):  # INRIA order: all higher coefficients of red, then green, then blue
        for k in range(1, rest + 1):
            columns[f"f_rest_{c * rest + k - 1}"] = sh[:, k, c]
    p = np.clip(opacities, 2.0**-24, 1 - 2.0**-24)
    columns["opacity"] = np.log(p) - np.log1p(-p)
    columns.update({f"scale_{i}": np.log(scales[:, i]) for i in range(3)})
    unit = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    columns.update({f"rot_{i}": unit[:, i] for i in range(4)})
    return columns


def assert_ply_matches(path, gaussians) -> dict[str, np.ndarray]:
    names, read = read_ply(path)
    expected = expected_columns(*gaussians)
    assert names == list(expected)
    for name, column in expected.items():
        np.testing.assert_allclose(read[name], column, rtol=1e-6, atol=1e-7, err_msg=name)
    return read


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """avatar.pt of a small untrained avatar (3 levels of 75, 150, 300 anchors, SH degree 2, 3 timesteps)."""
    rng = np.random.default_rng(0)
    root = tmp_path_factory.mktemp("export")
    np.savez(root / "body_model.npz", **tiny_body_model(rng))
    t = 3
    params = SmplxParams(rng.normal(scale=0.3, size=(t, 55, 3)), rng.normal(size=10), np.zeros((t, 10)),
                         rng.normal(scale=0.1, size=(t, 3)))
    cfg = AvatarConfig(num_anchors=300, levels=3, sh_degree=SH_DEGREE, hidden_layers=1, hidden_width=16,
                       refine_hidden_layers=1, refine_hidden_width=8, output_init_gain=0.5)
    spec = dict(avatar=asdict(cfg), field=asdict(FieldConfig(resolutions=[4, 6], features=4)), precond=asdict(PrecondConfig()),
                body_model_npz=body_model_npz(root / "body_model.npz"), params=asdict(params), frame_ids=[10, 11, 12],
                variant="pig", capture={})
    torch.manual_seed(0)
    model = build_avatar(spec)
    with torch.no_grad():  # untrained, every anchor has the same features and so the same decoded splat
        for weight in [*model.grid.parameters(), *model.decoder.parameters()]:
            weight.add_(torch.randn_like(weight), alpha=0.3)
    path = root / "avatar.pt"
    save_checkpoint(path, model, spec, [], torch.Generator(), 0, 0.0, [], {}, TERMS)
    return path


@pytest.fixture(scope="module")
def motion(checkpoint):
    """A 5-frame motion: frames 1 and 3 lie near training timesteps 2 and 0, so gamma(t) must come from those."""
    model = load_avatar(checkpoint)
    rng = np.random.default_rng(1)
    poses = rng.normal(scale=0.5, size=(5, 55, 3))
    poses[1] = model.pose_init[2].numpy() + rng.normal(scale=1e-3, size=(55, 3))
    poses[3] = model.pose_init[0].numpy() + rng.normal(scale=1e-3, size=(55, 3))
    transl = rng.normal(size=(5, 3))
    path = checkpoint.parent / "motion.npz"
    np.savez(path, fullpose=poses, transl=transl)
    return path, poses, transl


def _gaussians(model, timestep, lod, pose, transl):
    with torch.no_grad():
        g = model(torch.tensor([timestep]), lod, torch.as_tensor(pose)[None], torch.as_tensor(transl)[None])
    return g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0]


def _error(capsys, argv) -> str:
    """The stage's stderr for `argv`, asserted to be one error line with exit status 1."""
    assert run_cli(main, argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("export: error: ") and err.count("\n") == 1, err
    return err


# ---- the .ply writer ----


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_layout_and_values_for_sh_degrees_0_to_3(tmp_path, degree):
    rng = np.random.default_rng(degree)
    n, k = 7, (degree + 1) ** 2
    # sh[i, k, c] = i + k / 100 + c / 1000 makes every coefficient identifiable after the reorder.
    sh = np.arange(n)[:, None, None] + np.arange(k)[None, :, None] / 100 + np.arange(3)[None, None, :] / 1000
    quats = rng.normal(size=(n, 4))
    quats[0] = [0.0, 1.0, 0.0, 0.0]  # a 180-degree rotation: w = 0
    quats[1] = [-2.0, 0.0, 0.0, 0.0]  # negative w, not unit
    scales = rng.random((n, 3)) * 10.0 ** rng.integers(-6, 2, size=(n, 1))
    scales[2] = [0.0, 1e-45, 1e3]  # zero and subnormal scales get a finite log
    opacities = rng.random(n)
    opacities[3:5] = [0.0, 1.0]  # saturated opacities get finite logits
    means = rng.normal(size=(n, 3)) * 100
    write_splat_ply(tmp_path / "s.ply", means, quats, scales, opacities, sh)
    names, read = read_ply(tmp_path / "s.ply")
    rest = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    assert names == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *rest,
                     "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(names) == {0: 17, 1: 26, 2: 41, 3: 62}[degree]
    for c in range(3):
        for j in range(1, k):
            np.testing.assert_allclose(read[f"f_rest_{c * (k - 1) + j - 1}"], np.arange(n) + j / 100 + c / 1000, rtol=1e-7)
    # What a 3DGS viewer recovers: sigmoid(opacity), exp(scale), the normalised quaternion.
    assert all(np.isfinite(column).all() for column in read.values())
    recovered = 1 / (1 + np.exp(-read["opacity"].astype(np.float64)))
    np.testing.assert_allclose(recovered, opacities, atol=2.0**-23)
    read_scales = np.exp(np.stack([read[f"scale_{i}"] for i in range(3)], 1).astype(np.float64))
    np.testing.assert_allclose(np.delete(read_scales, 2, 0), np.delete(scales, 2, 0), rtol=1e-6)
    assert np.exp(np.float64(read["scale_0"][2])) <= 1.2e-38 and read["scale_2"][2] == np.float32(np.log(1e3))
    np.testing.assert_array_equal(np.stack([read[f"rot_{i}"] for i in range(4)], 1)[:2], [[0, 1, 0, 0], [-1, 0, 0, 0]])
    assert_ply_matches(tmp_path / "s.ply", (means, quats, np.maximum(scales, np.finfo(np.float32).tiny), opacities, sh))


def test_ply_writer_refuses_invalid_splats_and_writes_nothing(tmp_path):
    n = 4
    good = dict(means=np.zeros((n, 3)), quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.ones((n, 3)),
                opacities=np.full(n, 0.5), sh=np.zeros((n, 4, 3)))
    cases = {"means": (2, [np.nan, 0, 0], "1 of 4 splats are invalid"), "quats": (1, [0, 0, 0, 0], "the first is splat 1"),
             "opacities": (3, 1.5, "the first is splat 3"), "scales": (0, [-1, 1, 1], "the first is splat 0")}
    for name, (row, value, message) in cases.items():
        bad = {key: value_.copy() for key, value_ in good.items()}
        bad[name][row] = value
        with pytest.raises(ValueError, match=f"frame 3: .*{message}"):
            write_splat_ply(tmp_path / "s.ply", **bad, what="frame 3")
    with pytest.raises(ValueError, match=r"sh of shape \(4, 5, 3\); expected \(4, 4, 3\)"):
        write_splat_ply(tmp_path / "s.ply", **{**good, "sh": np.zeros((n, 5, 3))})
    assert list(tmp_path.iterdir()) == []


# ---- the stage ----


def test_export_canonical_and_motion_frames_match_the_avatar(checkpoint, motion, tmp_path):
    """Frames are the motion as the animate stage places it (pig.body.motion.align_motion on the selected frames,
    with the avatar's refined shape and its capture's up, ground and centre); the canonical cloud is the rest pose
    turned upright along the capture's nearest axis."""
    from scipy.spatial.transform import Rotation

    from pig.avatar.driver import AvatarDriver
    from pig.body.motion import align_motion, capture_frame, read_motion

    motion_path, poses, transl = motion
    out = tmp_path / "export"
    assert main(["--checkpoint", str(checkpoint), "--output", str(out), "--motion", str(motion_path),
                 "--frames", "1:4:2", "--lod", "1"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [".pig-stage", "canonical.ply", "correspondences.npz",
                                                     "export.json", "frame_000001.ply", "frame_000003.ply"]
    model = load_avatar(checkpoint)
    up, ground, centre = capture_frame(model)
    axis = np.zeros(3)
    axis[np.argmax(np.abs(up))] = np.sign(up[np.argmax(np.abs(up))])
    # Canonical: zero body pose and translation, the root turning +y onto `axis`, timestep 0's embedding.
    rest = np.zeros((55, 3))
    turn = np.cross([0.0, 1.0, 0.0], axis)
    rest[0] = turn / np.linalg.norm(turn) * np.arccos(axis[1]) if np.linalg.norm(turn) > 0 else [0, 0, np.pi * (axis[1] < 0)]
    np.testing.assert_allclose(Rotation.from_rotvec(rest[0]).apply([0.0, 1.0, 0.0]), axis, atol=1e-12)
    canonical = _gaussians(model, 0, 1, rest, np.zeros(3))
    assert canonical[0].shape == (150, 3) and canonical[4].shape == (150, 9, 3)
    assert_ply_matches(out / "canonical.ply", canonical)
    clip = read_motion(motion_path, hands_mean=model.body_model.hands_mean.numpy())
    clip = align_motion(clip.select(slice(1, 4, 2)), model.body_model, AvatarDriver(model).refined()[0], up, ground, centre)
    corr = np.load(out / "correspondences.npz")
    assert sorted(corr.files) == ["anchor_ids", "frames", "lod", "positions", "timesteps"]
    np.testing.assert_array_equal(corr["frames"], [1, 3])
    timesteps = [model.nearest_timestep(torch.as_tensor(pose)) for pose in clip.full_pose]
    np.testing.assert_array_equal(corr["timesteps"], timesteps)
    assert int(corr["lod"]) == 1 and corr["positions"].shape == (2, 150, 3) and corr["positions"].dtype == np.float32
    np.testing.assert_array_equal(corr["anchor_ids"], np.arange(150))
    for row, frame in enumerate([1, 3]):
        read = assert_ply_matches(out / f"frame_{frame:06d}.ply",
                                  _gaussians(model, timesteps[row], 1, clip.full_pose[row], clip.transl[row]))
        np.testing.assert_array_equal(corr["positions"][row], np.stack([read["x"], read["y"], read["z"]], 1))
    # The motion moved the splats: a frame is not the canonical cloud, nor another frame.
    assert np.abs(corr["positions"][0] - corr["positions"][1]).max() > 0.1


def test_correspondence_ids_are_a_prefix_across_levels(checkpoint, motion, tmp_path):
    motion_path = motion[0]
    ids = {}
    for lod in (0, 2):
        out = tmp_path / f"lod{lod}"
        assert main(["--checkpoint", str(checkpoint), "--output", str(out), "--motion", str(motion_path), "--frames", "0:5:4",
                     "--lod", str(lod)]) == 0
        corr = np.load(out / "correspondences.npz")
        ids[lod] = corr["anchor_ids"]
        assert corr["positions"].shape == (2, len(ids[lod]), 3)
    assert len(ids[0]) == 75 and len(ids[2]) == 300
    np.testing.assert_array_equal(ids[2][:75], ids[0])
    # Without --lod the finest level is exported, without --frames every motion frame.
    out = tmp_path / "default"
    assert main(["--checkpoint", str(checkpoint), "--output", str(out), "--motion", str(motion_path)]) == 0
    corr = np.load(out / "correspondences.npz")
    np.testing.assert_array_equal(corr["frames"], np.arange(5))
    assert int(corr["lod"]) == 2 and corr["positions"].shape == (5, 300, 3)


def test_bad_inputs_give_one_line_errors_and_write_nothing(checkpoint, motion, tmp_path, capsys):
    motion_path = str(motion[0])
    out = tmp_path / "export"
    base = ["--checkpoint", str(checkpoint), "--output", str(out)]
    err = _error(capsys, ["--checkpoint", str(tmp_path / "none.pt"), "--output", str(out)])
    assert f"{tmp_path / 'none.pt'}: avatar checkpoint not found" in err
    err = _error(capsys, [*base, "--lod", "3"])
    assert f"--lod 3: {checkpoint} has levels of detail 0..2 (75, 150, 300 splats)" in err
    assert "--lod -1:" in _error(capsys, [*base, "--lod", "-1"])
    with_motion = [*base, "--motion", motion_path]
    for spec in ("3", "a:b", "1:2:3:4", "-1:3", "2:1:1:"):
        assert f"--frames {spec!r}: expected START:STOP[:STEP]" in _error(capsys, [*with_motion, f"--frames={spec}"])
    for spec in ("3:3", "4:2", "0:3:0"):
        assert f"--frames {spec!r} selects no frame" in _error(capsys, [*with_motion, f"--frames={spec}"])
    err = _error(capsys, [*base, "--motion", motion_path, "--frames", "2:9"])
    assert f"frames 2:9: {motion_path} has 5 frames (0..4), so STOP may be at most 5" in err
    assert "give one with --motion FILE" in _error(capsys, [*base, "--frames", "0:2"])
    assert f"{tmp_path / 'm.npz'}: motion file not found" in _error(capsys, [*base, "--motion", str(tmp_path / "m.npz")])
    # The motion reader's own messages (tests/test_motion.py covers every layout); here: they reach the user.
    bad = {"short.npz": dict(fullpose=np.zeros((4, 55, 3)), transl=np.zeros((3, 3))),
           "nan.npz": dict(fullpose=np.zeros((4, 55, 3)), transl=np.array([[0, 0, 0], [0, 0, 0], [np.nan, 0, 0], [0, 0, 0]])),
           "nokey.npz": dict(transl=np.zeros((4, 3)))}
    messages = {"short.npz": "'transl' has shape (3, 3), expected (4, 3)",
                "nan.npz": "the translation of frame 2 is [nan, 0.0, 0.0]",
                "nokey.npz": "no known motion layout (keys ['transl'])"}
    for name, arrays in bad.items():
        np.savez(tmp_path / name, **arrays)
        assert f"{tmp_path / name}: {messages[name]}" in _error(capsys, [*base, "--motion", str(tmp_path / name)])
    (tmp_path / "text.npz").write_text("not a zip")
    assert "not a valid npz archive" in _error(capsys, [*base, "--motion", str(tmp_path / "text.npz")])
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".export")]


def test_output_folder_rules(checkpoint, motion, tmp_path, capsys):
    out = tmp_path / "export"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    base = ["--checkpoint", str(checkpoint), "--output", str(out)]
    err = _error(capsys, base)
    assert "holds files the export stage did not write (notes.txt); pass --overwrite" in err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    err = _error(capsys, ["--checkpoint", str(checkpoint), "--output", str(checkpoint)])
    assert f"{checkpoint}: the output folder is an existing file" in err
    # An earlier export is replaced as a whole; --overwrite replaces a foreign folder.
    assert main([*base, "--overwrite", "--motion", str(motion[0]), "--frames", "0:1"]) == 0
    assert not (out / "notes.txt").exists() and (out / "frame_000000.ply").is_file()
    assert main(base) == 0
    assert sorted(p.name for p in out.iterdir()) == [".pig-stage", "canonical.ply", "export.json"]
    render = tmp_path / "render"
    render.mkdir()
    (render / ".pig-stage").write_text('{"stage": "render"}')
    assert "holds the render stage's output, not the export stage's" in _error(capsys, [*base[:2], "--output", str(render)])


def test_up_override_turns_the_canonical_cloud_and_the_frames(checkpoint, motion, tmp_path):
    """--up +z: the rest body turned by a quarter turn about x (+y onto +z), the frames aligned to +z, as animate's
    --up does; the headers and the sidecar name +z."""
    import json

    from pig.avatar.driver import AvatarDriver
    from pig.body.motion import align_motion, capture_frame, read_motion

    out = tmp_path / "export"
    assert main(["--checkpoint", str(checkpoint), "--output", str(out), "--motion", str(motion[0]), "--frames", "0:2",
                 "--lod", "0", "--up", "+z"]) == 0
    model = load_avatar(checkpoint)
    rest = np.zeros((55, 3))
    rest[0] = [np.pi / 2, 0.0, 0.0]
    assert_ply_matches(out / "canonical.ply", _gaussians(model, 0, 0, rest, np.zeros(3)))
    clip = read_motion(motion[0], hands_mean=model.body_model.hands_mean.numpy()).select(slice(0, 2))
    clip = align_motion(clip, model.body_model, AvatarDriver(model).refined()[0], *capture_frame(model), "+z")
    for row in range(2):
        timestep = model.nearest_timestep(torch.as_tensor(clip.full_pose[row]))
        assert_ply_matches(out / f"frame_{row:06d}.ply", _gaussians(model, timestep, 0, clip.full_pose[row], clip.transl[row]))
        header = (out / f"frame_{row:06d}.ply").read_bytes().split(b"end_header")[0].decode()
        assert "comment up_axis +z\ncomment up 0.000000000 0.000000000 1.000000000\n" in header
    record = json.loads((out / "export.json").read_text())
    assert record["up"] == [0.0, 0.0, 1.0] and record["up_axis"] == "+z" and record["lod"] == 0
    assert {entry["up_axis"] for entry in record["files"].values()} == {"+z"}


def _canonical_splats(checkpoint, lod):
    """(means, linear scales, unit quats, opacities, sh) of the canonical cloud, float64 numpy."""
    return [np.asarray(a.double()) for a in _gaussians(load_avatar(checkpoint), 0, lod, np.zeros((55, 3)), np.zeros(3))]


def test_splat_format_holds_every_splat_as_antimatter15_reads_it(checkpoint, tmp_path):
    """.splat: 32-byte records (xyz, linear scales float32; RGBA of the DC colour and opacity, quaternion w x y z as
    bytes v * 128 + 128), one per splat in any order; decoded here with numpy and matched by position."""
    out = tmp_path / "export"
    assert main(["--checkpoint", str(checkpoint), "--output", str(out), "--format", "splat", "--lod", "1"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [".pig-stage", "canonical.splat", "export.json"]
    record = np.frombuffer((out / "canonical.splat").read_bytes(), dtype=[("xyz", "<f4", 3), ("scale", "<f4", 3),
                                                                         ("rgba", "u1", 4), ("rot", "u1", 4)])
    means, quats, scales, opacities, sh = _canonical_splats(checkpoint, 1)
    assert len(record) == len(means) == 150
    mine, theirs = np.lexsort(means.T[::-1]), np.lexsort(record["xyz"].T[::-1].astype(np.float64))
    np.testing.assert_allclose(record["xyz"][theirs], means[mine], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(record["scale"][theirs], scales[mine], rtol=1e-5)
    colour = np.clip((0.28209479177387814 * sh[:, 0] + 0.5) * 255, 0, 255)
    np.testing.assert_allclose(record["rgba"][theirs, :3], colour[mine], atol=1.0)
    np.testing.assert_allclose(record["rgba"][theirs, 3], 255 * opacities[mine], atol=1.0)
    unit = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    np.testing.assert_allclose(record["rot"][theirs], np.clip(unit[mine] * 128 + 128, 0, 255), atol=1.0)


def test_compressed_ply_holds_the_splats_within_its_quantisation(checkpoint, tmp_path):
    """.compressed.ply (SuperSplat): chunks of 256 splats with float bounds, positions packed 11-10-11 bits between
    them; decoded here and each position matched to the nearest true splat within one quantisation step. Its
    header names the up axis as our .ply does."""
    from scipy.spatial import cKDTree

    out = tmp_path / "export"
    assert main(["--checkpoint", str(checkpoint), "--output", str(out), "--format", "ply_compressed"]) == 0
    data = (out / "canonical.compressed.ply").read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "comment up_axis +y"]
    assert header[3].startswith("comment up ")
    counts = {line.split()[1]: int(line.split()[2]) for line in header if line.startswith("element ")}
    floats = sum(1 for line in header if line.startswith("property float"))
    means, _, _, opacities, sh = _canonical_splats(checkpoint, 2)
    assert counts["vertex"] == int((opacities > 1 / 255).sum()) > 0 and floats == 18
    chunks = np.frombuffer(data, "<f4", counts["chunk"] * 18, end).reshape(-1, 18)
    packed = np.frombuffer(data, "<u4", counts["vertex"] * 4, end + chunks.nbytes).reshape(-1, 4)[:, 0].astype(np.int64)
    bits = np.stack([(packed >> 21) & 2047, (packed >> 11) & 1023, packed & 2047], 1) / np.array([2047, 1023, 2047])
    low, high = np.repeat(chunks[:, :3], 256, 0)[:len(packed)], np.repeat(chunks[:, 3:6], 256, 0)[:len(packed)]
    decoded = low + bits * (high - low)
    distance, _ = cKDTree(means).query(decoded)
    step = np.linalg.norm((high - low) / np.array([2047, 1023, 2047]), axis=1)
    assert (distance <= step + 1e-6).all(), distance.max()
    assert sh.shape[1] == 9 and sum(1 for line in header if line.startswith("property uchar f_rest_")) == 24
