"""Artifacts paired with the wrong capture, diverged or altered checkpoints, duplicate summaries, full disks and
shared output folders are refused with the files named, and nothing is scored as if it were an avatar (sweep two,
cases 5-7 and the weak groups "disk full", "shared output folders", "checkpoints")."""
from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import shutil
from pathlib import Path

import pytest
import torch

from pig.avatar.checkpoint import CheckpointError, load_avatar
from pig.config import derive_preset
from pig.data.capture import Capture
from pig.data.capture_record import RECORD, capture_record
from pig.data.raw import CaptureError
from pig import _io
from pig._cli import run_cli
from pig._io import NoSpaceError, write_json
from pig._outputs import output_lock


def _snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _preset(tmp_path: Path, **fit) -> str:
    return str(derive_preset(tmp_path / "preset.yaml", "test",
                             fit={"iterations": 3, "eval_every": 3, "checkpoint_minutes": 0.0, **fit}))


def _other_capture(capture: Path, copy: Path) -> Path:
    """A copy of `capture` with one camera moved by 1 cm: another capture, by content."""
    shutil.copytree(capture, copy)
    cameras = json.loads((copy / "cameras.json").read_text())
    first = next(iter(cameras.values()))
    first["T"][0] += 0.01
    (copy / "cameras.json").write_text(json.dumps(cameras))
    return copy


def _altered(avatar: Path, path: Path, change) -> Path:
    """A copy of the checkpoint `avatar` with `change(state)` applied, saved as the fit stage saves it."""
    state = torch.load(avatar, weights_only=True)
    change(state)
    torch.save(state, path)
    return path


def _render(avatar: Path, capture: Path, out: Path) -> int:
    from pig.stages.render import main

    return run_cli(main, ["--checkpoint", str(avatar), "--capture", str(capture), "--split", "novel_view",
                          "--output", str(out), "--preset", "test"])


@pytest.fixture(scope="module")
def renders(tiny_fit, tmp_path_factory):
    """A renders folder of the tiny fit's capture as evaluate first sees it: its capture record and a LOD folder
    (evaluate refuses renders of another capture before it reads any image)."""
    capture, _ = tiny_fit
    out = tmp_path_factory.mktemp("checks") / "renders" / "novel_view"
    (out / "lod0").mkdir(parents=True)
    write_json(out / RECORD, capture_record(Capture.load(capture)))
    return out


# ---- case 6: artifacts of another capture (the render stage's record: tests/test_gt_metrics.py) ----

def test_render_refuses_an_avatar_of_another_capture_naming_both(tiny_fit, tmp_path, capsys):
    capture, avatar = tiny_fit
    other = _other_capture(capture, tmp_path / "other capture")
    out = tmp_path / "renders"
    assert _render(avatar, other, out) == 1
    assert (f"render: error: {avatar}: made from another capture ({capture.resolve()}) than {other}: their cameras "
            "differ") in capsys.readouterr().err
    assert not out.exists()


def test_evaluate_refuses_renders_of_another_capture_naming_both(tiny_fit, renders, tmp_path, capsys):
    from pig.stages.evaluate import EvaluateConfig, evaluate_split, main

    capture, _ = tiny_fit
    other = _other_capture(capture, tmp_path / "other capture")
    metrics = tmp_path / "metrics"
    status = run_cli(main, ["--capture", str(other), "--renders", str(renders), "--split", "novel_view",
                            "--output", str(metrics), "--preset", "test"])
    assert status == 1
    assert (f"evaluate: error: {renders}: made from another capture ({capture.resolve()}) than {other}: their "
            "cameras differ") in capsys.readouterr().err
    assert not list(metrics.glob("*.json")) and not list(metrics.glob("*.csv"))
    # Renders that record no capture (an older render stage, or copied by hand) are not scored either.
    unrecorded = tmp_path / "unrecorded"
    shutil.copytree(renders, unrecorded)
    (unrecorded / RECORD).unlink()
    with pytest.raises(CaptureError, match=f"{unrecorded / RECORD}: missing, so nothing says which"):
        evaluate_split(capture, unrecorded, "novel_view", tmp_path / "metrics2", EvaluateConfig(timing_frames=1))


# ---- case 5: a diverged fit ----

def test_a_fit_whose_weights_become_nan_stops_and_writes_no_avatar(small_capture, tmp_path, capsys):
    from pig.stages.fit import main

    preset = _preset(tmp_path, lr_decoders=math.nan, lr_refine=math.nan)
    out = tmp_path / "pig"
    assert run_cli(main, ["--capture", str(small_capture), "--output", str(out), "--preset", preset,
                          "--device", "cpu"]) == 1
    message = capsys.readouterr().err
    assert "fit: error: fit diverged at iteration 1: NaN or infinite weights in ['decoder." in message
    assert "stopped without writing avatar.pt (no checkpoint was written)" in message
    assert not (out / "avatar.pt").exists() and not (out / "checkpoint.pt").exists()


def test_a_fit_that_diverges_later_keeps_its_last_finite_checkpoint(small_capture, tmp_path, monkeypatch):
    from pig.avatar import training

    real, calls = training.iteration_loss, []

    def poisoned(*args, **kwargs):  # the loss turns NaN from the third iteration on
        terms = real(*args, **kwargs)
        calls.append(1)
        return {**terms, "total": terms["total"] * math.nan} if len(calls) >= 3 else terms

    monkeypatch.setattr(training, "iteration_loss", poisoned)
    out = tmp_path / "pig"
    with pytest.raises(training.FitDiverged) as err:
        training.fit(small_capture, out, _preset(tmp_path, iterations=4, eval_every=4))
    state_path = out / "checkpoint.pt"
    assert str(err.value).startswith(f"fit diverged at iteration 3: the training loss is nan; stopped without "
                                     f"writing avatar.pt ({state_path} keeps the last finite weights")
    state = torch.load(state_path, weights_only=True)
    assert state["iteration"] == 2 and all(t.isfinite().all() for t in state["model"].values() if t.is_floating_point())
    assert not (out / "avatar.pt").exists()


# ---- checkpoints: non-finite, wrong dtype, shifted frame ids ----

def _first_float(state) -> str:
    return next(key for key, t in state["model"].items() if t.is_floating_point() and t.numel() > 1)


def test_render_refuses_a_checkpoint_with_nan_weights(tiny_fit, tmp_path, capsys):
    capture, avatar = tiny_fit

    def poison(state):
        state["model"][_first_float(state)].view(-1)[0] = math.nan

    bad = _altered(avatar, tmp_path / "avatar.pt", poison)
    out = tmp_path / "renders"
    assert _render(bad, capture, out) == 1
    key = _first_float(torch.load(avatar, weights_only=True))
    assert (f"render: error: {bad}: 1 NaN or infinite weights ({key} (1)): the fit diverged; it is not an avatar to "
            "render or score") in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("dtype", [torch.int64, torch.float64])
def test_checkpoint_weights_of_another_dtype_are_refused(tiny_fit, tmp_path, dtype):
    _, avatar = tiny_fit
    key = _first_float(torch.load(avatar, weights_only=True))

    def cast(state):
        state["model"][key] = state["model"][key].to(dtype)

    bad = _altered(avatar, tmp_path / "avatar.pt", cast)
    with pytest.raises(CheckpointError) as err:
        load_avatar(bad)
    assert str(err.value) == (f"{bad}: weight {key!r} is {dtype}, the avatar's spec builds it as torch.float32; the "
                              "file was altered or written by another program")


def test_render_refuses_shifted_training_frame_ids(tiny_fit, tmp_path, capsys):
    capture, avatar = tiny_fit

    def shift(state):
        state["spec"]["frame_ids"] = [f + 100 for f in state["spec"]["frame_ids"]]

    bad = _altered(avatar, tmp_path / "avatar.pt", shift)
    train = json.loads((capture / "split.json").read_text())["train"]["frames"]
    out = tmp_path / "renders"
    assert _render(bad, capture, out) == 1
    assert (f"render: error: {bad}: the avatar's training frame ids {[f + 100 for f in train]} are not the train "
            f"frames {train} of {capture}") in capsys.readouterr().err
    assert not out.exists()


# ---- case 7: duplicate summaries ----

def test_tables_refuses_two_summaries_of_one_run_naming_both(tmp_path):
    from pig.stages.tables import make_tables

    summary = {"split": "novel_view", "lod": 0, "splats": 100, "ssim": 0.9, "lpips": 0.1, "lpips_net": "alex",
               "fid": None, "images": 1, "model_mb": 1.0, "fps": 1.0, "device": "cpu", "psnr_blank": 10.0,
               "ssim_blank": 0.5}
    paths = []
    for tree, psnr in (("a", 19.2), ("b", 99.0)):
        path = tmp_path / tree / "synthetic" / "s0" / "pig" / "metrics" / "novel_view_lod0.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({**summary, "psnr": psnr}))
        paths.append(path)
    with pytest.raises(ValueError) as err:
        make_tables("synthetic", paths, [], ["pig"], tmp_path / "tables")
    assert str(err.value) == (f"{paths[1]}: a second summary of subject 's0', variant 'pig', split 'novel_view', "
                              f"LOD 0 (the first is {paths[0]}); pass one summary per run")
    assert not (tmp_path / "tables").exists()


# ---- disk full ----

def _full_disk(monkeypatch, free: int = 0) -> None:
    real = os.statvfs

    class Full:
        def __init__(self, stat):
            self.f_frsize, self.f_bavail = stat.f_frsize, free // stat.f_frsize

    monkeypatch.setattr(_io.os, "statvfs", lambda path: Full(real(path)))


def test_a_full_disk_is_named_with_the_file_for_oserror_writers(tmp_path, monkeypatch):
    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Path, "write_text", full)
    target = tmp_path / "metrics" / "novel_view_lod0.json"
    with pytest.raises(NoSpaceError) as err:
        write_json(target, {"psnr": 20.0})
    assert err.value.errno == errno.ENOSPC
    assert str(err.value).startswith(f"{target}: no space left on the device while writing it")
    assert list(target.parent.iterdir()) == []  # no temporary left behind


def test_a_full_disk_is_named_for_torch_save_which_reports_no_errno(small_capture, tmp_path, monkeypatch, capsys):
    """Sweep two, c33: a fit on a full disk said only `unexpected pos 17664 vs 17558`."""
    from pig.avatar import checkpoint
    from pig.stages.fit import main

    def save(obj, path):
        Path(path).write_bytes(b"PK" * 100)
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 17664 vs 17558")

    monkeypatch.setattr(checkpoint.torch, "save", save)
    _full_disk(monkeypatch, free=4096)
    out = tmp_path / "pig"
    assert run_cli(main, ["--capture", str(small_capture), "--output", str(out), "--preset", _preset(tmp_path),
                          "--device", "cpu"]) == 1
    assert (f"fit: error: {out / 'checkpoint.pt'}: no space left on the device while writing it ([enforce fail"
            in capsys.readouterr().err)
    assert not [p for p in out.iterdir() if p.name.endswith(".pt")]


def test_a_full_disk_is_named_for_a_render_png_that_opencv_could_not_write(tmp_path, monkeypatch):
    """Sweep two, c34: OpenCV's imwrite reports a full disk only by returning False."""
    import numpy as np

    monkeypatch.setattr(_io.cv2, "imwrite", lambda *args, **kwargs: False)
    _full_disk(monkeypatch)
    target = tmp_path / "lod0" / "cam00" / "00000000.png"
    with pytest.raises(NoSpaceError) as err:
        _io.write_png(target, np.zeros((4, 4, 3)))
    assert str(err.value).startswith(f"{target}: no space left on the device while writing it ({target}: OpenCV "
                                     "could not write the PNG)")
    assert list(target.parent.iterdir()) == []


def test_a_writer_error_with_space_left_is_not_blamed_on_the_disk(tmp_path, monkeypatch):
    _full_disk(monkeypatch, free=10 << 30)
    with pytest.raises(RuntimeError, match="encoder broke") as err:
        with _io.atomic_path(tmp_path / "x.exr"):
            raise RuntimeError("encoder broke")
    assert not isinstance(err.value, NoSpaceError)


# ---- shared output folders ----

def test_a_second_fit_into_a_folder_being_fitted_is_refused(small_capture, tmp_path):
    from pig.avatar.training import fit
    from pig._outputs import OutputError

    out = tmp_path / "pig"
    with output_lock(out, "fit"):  # another fit holds the folder
        with pytest.raises(OutputError, match=f"{out}: another fit run \\(pid {os.getpid()}\\) is writing it"):
            fit(small_capture, out, _preset(tmp_path))
    assert not out.exists()


def test_preprocess_refuses_another_subject_into_a_capture_naming_the_one_it_holds(tmp_path, capsys):
    from thuman4_fixture import write_thuman4

    from pig.stages.preprocess import main

    def preprocess(raw, out, *extra):
        return run_cli(main, ["--input", str(raw), "--output", str(out), "--preset", "test", "--no-progress", *extra])

    first = write_thuman4(tmp_path / "a", cameras=3, frames=3, width=48, height=40)
    second = write_thuman4(tmp_path / "b", cameras=3, frames=3, width=48, height=40, seed=1)
    out = tmp_path / "capture"
    assert preprocess(first, out) == 0
    before = _snapshot(out)
    assert preprocess(second, out) == 1
    assert (f"preprocess: error: {out}: holds the preprocessed capture of {first} (subject 'a'), not of {second} "
            "(subject 'b'); choose another --output, or pass --overwrite") in capsys.readouterr().err
    assert _snapshot(out) == before
    assert preprocess(first, out) == 0  # a rerun on its own raw capture may replace it
    assert preprocess(second, out, "--overwrite") == 0
    assert json.loads((out / "report.json").read_text())["subject"] == "b"
