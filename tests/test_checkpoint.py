"""Avatar checkpoints: read without running code, one-line errors naming the file, resume only of the same fit."""
import io
import json
import re
import shutil
import struct
import zipfile
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from pig.avatar.build import body_model_npz, build_avatar, build_optimizers
from pig.avatar.checkpoint import CheckpointError, load_avatar, load_training_state, loss_terms, save_checkpoint
from pig.avatar.config import AvatarConfig
from pig.body.model import BodyModel
from pig.body.params import SmplxParams
from pig.field.latent_grid import FieldConfig
from pig.field.precondition import PrecondConfig
from body_fixture import tiny_body_model

FINGERPRINT = {part: f"{i:064x}" for i, part in
               enumerate(("cameras", "smplx", "split", "background", "body_model", "images"))}
SETTINGS = {"fit": {"iterations": 10, "eval_every": 5, "checkpoint_minutes": 5.0, "lr_decoders": 1e-3, "seed": 0},
            "rasterizer": {"backend": "cpu", "max_pairs": 1000}}
TERMS = {"lpips": {"weight": 2.0, "net": "vgg", "state": "weights absent", "detail": "LPIPS vgg backbone: not found"}}


@pytest.fixture(scope="module")
def spec(tmp_path_factory):
    rng = np.random.default_rng(0)
    path = tmp_path_factory.mktemp("body") / "body_model.npz"
    np.savez(path, **tiny_body_model(rng))
    t = 3
    params = SmplxParams(rng.normal(scale=0.2, size=(t, 55, 3)), rng.normal(size=10), np.zeros((t, 10)),
                         rng.normal(scale=0.1, size=(t, 3)))
    cfg = AvatarConfig(num_anchors=300, levels=2, sh_degree=1, hidden_layers=1, hidden_width=16, refine_hidden_layers=1,
                       refine_hidden_width=8)
    return dict(avatar=asdict(cfg), field=asdict(FieldConfig(resolutions=[4, 6], features=4)), precond=asdict(PrecondConfig()),
                body_model_npz=body_model_npz(path), params=asdict(params), frame_ids=[10, 11, 12], variant="pig",
                capture=dict(FINGERPRINT))


def _training(spec, seed=7):
    torch.manual_seed(0)
    model = build_avatar(spec)
    return model, build_optimizers(model, 1e-2, 1e-3, PrecondConfig()), torch.Generator().manual_seed(seed)


def _step(model, optimizers, generator):
    lod = int(torch.randint(model.num_levels, (1,), generator=generator))
    g = model(torch.tensor([0, 2]), lod)
    loss = (g.means - 1).square().mean() + g.sh.square().mean() + g.opacities.mean() + g.scales.mean()
    for opt in optimizers:
        opt.zero_grad(set_to_none=True)
    loss.backward()
    for opt in optimizers:
        opt.step()


ROWS = [{"iteration": 0, "wall_s": 0.0, "lod": "", "loss": "", "heldout_psnr": 12.5},
        {"iteration": 2, "wall_s": 1.5, "lod": 1, "loss": np.float64(0.25), "heldout_psnr": float("nan")}]


def _trained(spec, steps=2):
    model, optimizers, generator = _training(spec)
    for _ in range(steps):
        _step(model, optimizers, generator)
    return model, optimizers, generator


@pytest.fixture(scope="module")
def saved(spec, tmp_path_factory):
    """A checkpoint after two optimiser steps, and the training state it was written from."""
    model, optimizers, generator = _trained(spec)
    path = tmp_path_factory.mktemp("saved") / "checkpoint.pt"
    save_checkpoint(path, model, spec, optimizers, generator, 2, 1.5, ROWS, SETTINGS, TERMS)
    return path, model, optimizers, generator


def test_checkpoint_reads_with_weights_only_and_resumes_bit_exactly(spec, tmp_path):
    model, optimizers, generator = _trained(spec)
    path = tmp_path / "checkpoint.pt"
    torch_rng = torch.get_rng_state()
    save_checkpoint(path, model, spec, optimizers, generator, 2, 1.5, ROWS, SETTINGS, TERMS)
    state = torch.load(path, weights_only=True)
    assert state["version"] == 2 and state["iteration"] == 2 and state["spec"]["capture"] == FINGERPRINT
    for key, value in spec["params"].items():  # stored as float64 tensors, not pickled numpy arrays
        assert torch.equal(state["spec"]["params"][key], torch.from_numpy(value)), key
    assert state["spec"]["body_model_npz"].dtype == torch.uint8  # raw storage, not pickled bytes
    assert state["spec"]["body_model_npz"].numpy().tobytes() == spec["body_model_npz"]
    assert type(state["log"][1]["loss"]) is float and state["log"][1]["loss"] == 0.25

    restored, restored_optimizers, restored_generator = _training(spec)
    assert not torch.equal(restored_generator.get_state(), generator.get_state())
    torch.manual_seed(123)
    iteration, wall, log = load_training_state(path, restored, restored_optimizers, restored_generator, spec, SETTINGS, TERMS)
    assert (iteration, wall) == (2, 1.5) and log[0] == ROWS[0] and log[1]["lod"] == 1
    assert torch.equal(restored_generator.get_state(), generator.get_state())
    assert torch.equal(torch.get_rng_state(), torch_rng)
    for a, b in zip(optimizers, restored_optimizers):
        for p, q in zip((p for g in a.param_groups for p in g["params"]), (q for g in b.param_groups for q in g["params"])):
            assert a.state[p]["step"] == b.state[q]["step"] == 2
            assert torch.equal(a.state[p]["exp_avg"], b.state[q]["exp_avg"])
            assert torch.equal(a.state[p]["exp_avg_sq"], b.state[q]["exp_avg_sq"])
    saved_weights = {k: v.clone() for k, v in model.state_dict().items()}
    avatar = load_avatar(path)
    assert not avatar.training
    for key, value in saved_weights.items():
        assert torch.equal(avatar.state_dict()[key], value), key

    # Continuing the original and the restored training gives the same weights, bit for bit.
    _step(model, optimizers, generator)
    _step(restored, restored_optimizers, restored_generator)
    after = restored.state_dict()
    assert any(not torch.equal(after[k], v) for k, v in saved_weights.items())
    for key, value in model.state_dict().items():
        assert torch.equal(after[key], value), key


def test_save_refuses_what_a_safe_load_could_not_read(spec, saved, tmp_path):
    _, model, optimizers, generator = saved
    path = tmp_path / "checkpoint.pt"
    with pytest.raises(TypeError, match=r"state\['log'\]\[0\]\['note'\]: a PosixPath"):
        save_checkpoint(path, model, spec, optimizers, generator, 3, 1.5, [{"note": Path("x")}], SETTINGS, TERMS)
    assert list(tmp_path.iterdir()) == []


class RunsCode:
    """Unpickling calls open(marker, "w"): a visible side effect of a code-running load."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


@pytest.mark.parametrize("loader", ["load_avatar", "resume"])
def test_crafted_pickle_is_not_executed(spec, tmp_path, loader):
    marker = tmp_path / "ran"
    path = tmp_path / "avatar.pt"
    torch.save({"version": 2, "spec": {**spec, "variant": RunsCode(marker)}, "model": {}}, path)
    with pytest.raises(CheckpointError) as err:
        if loader == "load_avatar":
            load_avatar(path)
        else:
            model, optimizers, generator = _training(spec)
            load_training_state(path, model, optimizers, generator, spec, SETTINGS, TERMS)
    assert not marker.exists()
    message = str(err.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    assert "older format (version 1) or not a pig checkpoint" in message and "delete it and re-run the fit stage" in message


def test_version_1_checkpoint_gives_a_migration_error(spec, saved, tmp_path):
    """Format 1 stored the SMPL-X parameters as numpy arrays: readable only by a code-running load."""
    _, model, optimizers, generator = saved
    path = tmp_path / "avatar.pt"
    old_spec = {key: value for key, value in spec.items() if key != "capture"}
    torch.save({"version": 1, "spec": old_spec, "model": model.state_dict(), "optimizers": [o.state_dict() for o in optimizers],
                "generator": generator.get_state(), "torch_rng": torch.get_rng_state(), "iteration": 3, "wall_s": 1.0,
                "log": [], "fit": SETTINGS["fit"]}, path)
    with pytest.raises(CheckpointError, match="older format") as err:
        load_avatar(path)
    assert str(err.value) == (
        f"{path}: not loaded: it holds Python objects that only a code-running load could restore, so it is an avatar "
        "checkpoint of an older format (version 1) or not a pig checkpoint; delete it and re-run the fit stage "
        "(python -m pig.stages.fit), which writes format version 2")


def _flip_tensor_byte(data: bytes) -> bytes:
    """One byte of a stored tensor changed: torch.load reads it silently, the archive's CRC does not match."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        info = max(archive.infolist(), key=lambda i: i.file_size)  # the largest member is tensor data
    name_length, extra_length = struct.unpack("<HH", data[info.header_offset + 26: info.header_offset + 30])
    offset = info.header_offset + 30 + name_length + extra_length + info.file_size // 2
    return data[:offset] + bytes([data[offset] ^ 0xFF]) + data[offset + 1:]


NOT_ZIP = "corrupt, truncated or not an avatar checkpoint (File is not a zip file)"
CORRUPT = {
    "empty": (lambda data: b"", "empty file, not an avatar checkpoint"),
    "random bytes": (lambda data: np.random.default_rng(0).bytes(4096), NOT_ZIP),
    "truncated": (lambda data: data[: len(data) * 3 // 4], NOT_ZIP),
    "flipped byte": (_flip_tensor_byte, "corrupt avatar checkpoint (member "),
}


@pytest.mark.parametrize("case", sorted(CORRUPT))
def test_corrupt_avatar_is_a_one_line_error_naming_the_file(saved, tmp_path, case):
    damage, expected = CORRUPT[case]
    path = tmp_path / "avatar.pt"
    path.write_bytes(damage(saved[0].read_bytes()))
    if case == "flipped byte":
        torch.load(path, weights_only=True)  # torch alone does not notice
    with pytest.raises(CheckpointError) as err:
        load_avatar(path)
    message = str(err.value)
    assert isinstance(err.value, ValueError) and "\n" not in message
    assert message.startswith(f"{path}: {expected}"), message
    assert message.endswith("; delete it and re-run the fit stage (python -m pig.stages.fit)")


@pytest.mark.parametrize("content, expected", [
    (torch.zeros(3), "not an avatar checkpoint (no format version)"),
    ({"spec": {}}, "not an avatar checkpoint (no format version)"),
    ({"version": 3, "spec": {}, "model": {}},
     "avatar checkpoint of format version 3, this pig reads version 2; use the pig that wrote it, or delete it"),
    ({"version": 2, "model": {}}, "avatar checkpoint without ['spec']"),
])
def test_foreign_torch_files_are_refused_by_name(tmp_path, content, expected):
    path = tmp_path / "avatar.pt"
    torch.save(content, path)
    with pytest.raises(CheckpointError, match="delete it and re-run the fit stage") as err:
        load_avatar(path)
    assert str(err.value).startswith(f"{path}: {expected}")


def test_weights_of_another_shape_are_refused_by_name(spec, saved, tmp_path):
    state = torch.load(saved[0], weights_only=True)
    state["model"] = {key: value[:1] if key.startswith("decoder.") else value for key, value in state["model"].items()}
    path = tmp_path / "avatar.pt"
    torch.save(state, path)
    with pytest.raises(CheckpointError, match=f"^{re.escape(str(path))}: checkpoint does not match the model "
                                              r"\(Error\(s\) in loading state_dict for AvatarModel: size mismatch for decoder\.") as err:
        load_avatar(path)
    assert "\n" not in str(err.value)


def test_missing_or_directory_checkpoint_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match=f"^{re.escape(str(tmp_path / 'avatar.pt'))}: avatar checkpoint not found"):
        load_avatar(tmp_path / "avatar.pt")
    with pytest.raises(CheckpointError, match=f"^{re.escape(str(tmp_path))}: not a file"):
        load_avatar(tmp_path)


def test_spec_with_a_pickled_body_model_is_refused(spec, saved, tmp_path):
    """The body model bytes inside the spec are read without pickle, too."""
    marker = tmp_path / "ran"
    buffer = io.BytesIO()
    np.savez(buffer, v_template=np.array([RunsCode(marker)], dtype=object))
    path = tmp_path / "avatar.pt"
    _, model, optimizers, generator = saved
    save_checkpoint(path, model, {**spec, "body_model_npz": buffer.getvalue()}, optimizers, generator, 3, 1.0, [], SETTINGS, TERMS)
    with pytest.raises(CheckpointError, match=f"^{re.escape(str(path))}: avatar spec unusable .*'v_template' holds pickled Python objects, which are not loaded"):
        load_avatar(path)
    assert not marker.exists()


def test_body_model_npz_keeps_the_model_and_drops_pickled_objects(tmp_path):
    """SMPL-X files may hold name tables and a sparse J_regressor as pickled objects; the spec's copy holds
    the same model as plain arrays."""
    from scipy import sparse

    arrays = tiny_body_model(np.random.default_rng(1))
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(path, **{**arrays, "J_regressor": np.array(sparse.csr_matrix(arrays["J_regressor"]), dtype=object),
                      "part2num": np.array({"global": 0}, dtype=object)})
    data = body_model_npz(path)
    with np.load(io.BytesIO(data), allow_pickle=False) as plain:
        assert sorted(plain.files) == sorted(arrays)
        copy = BodyModel({key: plain[key] for key in plain.files}, dtype=torch.float64)
    original = BodyModel.from_file(path, dtype=torch.float64)
    for key, value in original.state_dict().items():
        assert torch.equal(copy.state_dict()[key], value), key
    np.savez_compressed(path, **arrays)  # plain arrays: the file as it is, compressed
    assert body_model_npz(path) == path.read_bytes()


# ---- resuming only the same fit ----


def _resume(path, spec, settings=SETTINGS, terms=TERMS):
    model, optimizers, generator = _training(spec)
    return load_training_state(path, model, optimizers, generator, spec, settings, terms)


def _refusal(path, differs: str) -> str:
    return (f"{path}: checkpoint of another fit, not resumed: {differs}; "
            "delete it to start the fit over, or point --output elsewhere")


def test_resume_refuses_another_capture_preset_or_variant(spec, saved):
    path = saved[0]
    other_capture = {**spec, "capture": {**FINGERPRINT, "images": "0" * 64, "smplx": "1" * 64}}
    with pytest.raises(CheckpointError) as err:
        _resume(path, other_capture)
    assert str(err.value) == _refusal(path, "the capture differs (images, smplx)")

    settings = {**SETTINGS, "fit": {**SETTINGS["fit"], "lr_decoders": 5e-4, "seed": 1}}
    with pytest.raises(CheckpointError) as err:
        _resume(path, spec, settings)
    assert str(err.value) == _refusal(path, "preset section 'fit' differs in lr_decoders, seed")

    other_field = {**spec, "field": {**spec["field"], "init_std": 0.5}}
    with pytest.raises(CheckpointError) as err:
        _resume(path, other_field)
    assert str(err.value) == _refusal(path, "preset section 'field' differs in init_std")

    gsplat = {**SETTINGS, "rasterizer": {"backend": "gsplat", "max_pairs": 1000}}
    with pytest.raises(CheckpointError) as err:
        _resume(path, {**spec, "variant": "no_offsets"}, gsplat)
    assert str(err.value) == _refusal(
        path, "preset section 'rasterizer' differs in backend; the variant differs ('pig', now 'no_offsets')")


def test_resume_refuses_another_lpips_state(spec, saved):
    """Same preset, but the LPIPS weights appeared (or went) since the checkpoint: the loss is another one."""
    path = saved[0]
    on = {"lpips": {**TERMS["lpips"], "state": "on", "detail": ""}}
    with pytest.raises(CheckpointError) as err:
        _resume(path, spec, terms=on)
    assert str(err.value) == _refusal(path, "the LPIPS term differs ('weights absent', now 'on')")
    # The detail (where the weights were sought) may differ between machines; the state decides.
    assert _resume(path, spec, terms={"lpips": {**TERMS["lpips"], "detail": "elsewhere"}})[0] == 2


def test_loss_terms_read_back_and_an_older_file_reads_as_unknown(spec, saved, tmp_path):
    from pig.avatar.losses import fit_note

    path, model = saved[:2]
    assert loss_terms(path) == TERMS
    state = torch.load(path, weights_only=True)
    del state["loss_terms"]
    older = tmp_path / "avatar.pt"
    torch.save(state, older)
    terms = loss_terms(older)
    assert terms == {"lpips": {"weight": None, "net": None, "state": "unknown", "detail": ""}}
    assert fit_note(terms["lpips"]) == "fit's LPIPS term unknown (avatar.pt written before fits recorded it, re-run the fit)"
    loaded = load_avatar(older).state_dict()
    assert all(torch.equal(loaded[key], value) for key, value in model.state_dict().items())
    with pytest.raises(CheckpointError) as err:
        _resume(older, spec)
    assert str(err.value) == _refusal(older, "the LPIPS term differs ('unknown', now 'weights absent')")

    torch.save({**state, "loss_terms": {"lpips": {"state": "sometimes"}}}, older)
    with pytest.raises(CheckpointError, match=rf"^{re.escape(str(older))}: loss-term record unreadable \(expected 'lpips' "
                                              r"with a state among \('on', .*found \{'lpips': \{'state': 'sometimes'\}\}\); "
                                              r"re-run the fit stage"):
        loss_terms(older)


def test_resume_of_a_checkpoint_older_than_a_setting_takes_its_default(spec, saved, tmp_path):
    """A fit begun before pig had `avatar.offset_frame` ran with world offsets: it resumes under the default and
    is refused when the preset now asks for local offsets; CUDA-graph replay of CG is free to change."""
    state = torch.load(saved[0], weights_only=True)
    del state["spec"]["avatar"]["offset_frame"]
    older = tmp_path / "checkpoint.pt"
    torch.save(state, older)
    assert spec["avatar"]["offset_frame"] == "world"
    assert _resume(older, spec)[0] == 2
    with pytest.raises(CheckpointError) as err:
        _resume(older, {**spec, "avatar": {**spec["avatar"], "offset_frame": "local"}})
    assert str(err.value) == _refusal(older, "preset section 'avatar' differs in offset_frame")
    assert _resume(saved[0], {**spec, "precond": {**spec["precond"], "cg_graphs": not spec["precond"]["cg_graphs"]}})[0] == 2


def test_resume_accepts_a_longer_run_and_other_cadence(spec, saved):
    settings = {"fit": {**SETTINGS["fit"], "iterations": 50, "eval_every": 1, "checkpoint_minutes": 0.0},
                "rasterizer": {"backend": "cpu", "max_pairs": 10**7}}
    assert _resume(saved[0], spec, settings)[0] == 2


# ---- the capture's fingerprint ----


def test_capture_fingerprint_follows_content_not_location(small_capture, tmp_path):
    from pig.data.capture import Capture

    reference = Capture.load(small_capture).fingerprint()
    copy = tmp_path / "copy"
    shutil.copytree(small_capture, copy)
    assert Capture.load(copy).fingerprint() == reference

    def changed() -> list[str]:
        found = Capture.load(copy).fingerprint()
        return sorted(k for k in reference if found[k] != reference[k])

    params, frames = SmplxParams.load(copy / "smplx.npz")
    params.transl = params.transl + 0.01  # same frame numbers, other poses
    params.save(copy / "smplx.npz", frame_ids=frames)
    assert changed() == ["smplx"]
    shutil.copy(small_capture / "smplx.npz", copy / "smplx.npz")

    image = sorted((copy / "images").rglob("*.png"))[0]
    image.write_bytes(image.read_bytes() + b"\0")  # another file of the same name
    assert changed() == ["images"]
    image.unlink()
    assert changed() == ["images"]
    shutil.copy(small_capture / image.relative_to(copy), image)

    cameras = json.loads((copy / "cameras.json").read_text())
    name = sorted(cameras)[0]
    cameras[name]["T"][2] += 1e-6
    (copy / "cameras.json").write_text(json.dumps(cameras))
    assert changed() == ["cameras"]
    shutil.copy(small_capture / "cameras.json", copy / "cameras.json")

    split = json.loads((copy / "split.json").read_text())
    split["train"]["cameras"] = split["train"]["cameras"][:-1]
    (copy / "split.json").write_text(json.dumps(split))
    assert changed() == ["split"]
    shutil.copy(small_capture / "split.json", copy / "split.json")

    report = json.loads((copy / "report.json").read_text())
    report["seconds"] += 100  # a rerun of preprocess on the same data
    (copy / "report.json").write_text(json.dumps(report))
    assert changed() == []
    report["background"] = [255, 255, 255]
    (copy / "report.json").write_text(json.dumps(report))
    assert changed() == ["background"]
    shutil.copy(small_capture / "report.json", copy / "report.json")

    with open(copy / "body_model.npz", "ab") as file:
        file.write(b"\0")
    assert changed() == ["body_model"]
