"""Stage outputs: never over an input or over files the stage did not write, an existing file is not a folder,
reruns over a stage's own output need no flag, temporaries of killed runs go away (those of live ones stay),
and the tables stage checks every input before it writes."""
from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import pandas as pd
import pytest
import yaml

from thuman4_fixture import write_thuman4

from pig.data.raw import CaptureError
from pig.stages import evaluate, fit, generate, preprocess, render, tables
from pig._cli import run_cli

MARKER = ".pig-stage"  # pig._outputs.MARKER; spelt out so that these tests also run on code without it


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (hidden ones too) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.fixture
def dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


@pytest.fixture
def live_pid():
    child = subprocess.Popen(["sleep", "60"])
    yield child.pid
    child.kill()
    child.wait()


@pytest.fixture
def raw(tmp_path_factory) -> Path:
    """A tiny THuman4 subject under a data root: data/thuman4/s."""
    return write_thuman4(tmp_path_factory.mktemp("raw") / "data" / "thuman4" / "s", cameras=3, frames=3)


def _preprocess(raw: Path, out: Path, *extra: str) -> int:
    return run_cli(preprocess.main, ["--input", str(raw), "--output", str(out), "--preset", "test", "--no-progress", *extra])


# -- preprocess: the raw capture, a data root and unrelated files are safe ------------------------------------

@pytest.mark.parametrize("where, message", [
    (lambda raw: raw, "the output is the input"),
    (lambda raw: raw.parent.parent, "the output contains the input"),
    (lambda raw: raw / "capture", "the output lies inside the input"),
])
@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_preprocess_never_writes_over_or_into_its_input(raw, where, message, overwrite, capsys):
    root = raw.parent.parent
    before = _snapshot(root)
    assert _preprocess(raw, where(raw), *overwrite) == 1
    err = capsys.readouterr().err
    assert f"preprocess: error: {where(raw)}: {message} {raw}" in err, err
    assert _snapshot(root) == before


def test_preprocess_keeps_a_folder_of_unrelated_files_unless_overwrite(raw, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "sub").mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    (out / "sub" / "data.bin").write_bytes(b"\x00\x01")
    before = _snapshot(out)
    assert _preprocess(raw, out) == 1
    err = capsys.readouterr().err
    assert (f"preprocess: error: {out}: holds files the preprocess stage did not write (notes.txt, sub); "
            "pass --overwrite to replace them, or choose another output folder") in err, err
    assert _snapshot(out) == before and _hidden(tmp_path) == []
    assert _preprocess(raw, out, "--overwrite") == 0
    assert not (out / "notes.txt").exists() and (out / "report.json").is_file() and (out / MARKER).is_file()


def test_preprocess_refuses_an_existing_file_as_output_and_leaves_it_alone(raw, tmp_path, capsys):
    out = tmp_path / "capture"
    out.write_bytes(b"a file, not a folder")
    assert _preprocess(raw, out) == 1
    assert (f"preprocess: error: {out}: the output folder is an existing file; nothing was written"
            in capsys.readouterr().err)
    assert out.read_bytes() == b"a file, not a folder" and sorted(p.name for p in tmp_path.iterdir()) == ["capture"]
    assert _preprocess(raw, out / "below") == 1
    assert f"the output folder lies under the file {out}" in capsys.readouterr().err
    assert out.read_bytes() == b"a file, not a folder" and sorted(p.name for p in tmp_path.iterdir()) == ["capture"]


def test_preprocess_reruns_over_its_own_output_and_removes_orphans_of_dead_runs(raw, tmp_path, dead_pid, live_pid):
    out = tmp_path / "capture"
    assert _preprocess(raw, out) == 0
    (out / "report.json").unlink()  # what Snakemake does before rerunning the rule
    (out / "stale.txt").write_text("from the previous run")
    orphans = [f".capture.{dead_pid}.tmp", f".capture.{dead_pid}.old", f".capture.tmp-{dead_pid}"]
    kept = [f".capture.{live_pid}.tmp", f".other.{dead_pid}.tmp", ".capture.notapid.tmp"]
    for name in orphans + kept:
        (tmp_path / name / "images").mkdir(parents=True)
    assert _preprocess(raw, out) == 0  # no --overwrite needed
    assert (out / "report.json").is_file() and not (out / "stale.txt").exists()
    assert _hidden(tmp_path) == sorted(kept)


# -- render, evaluate, fit: the variant folder and the inputs are safe ---------------------------------------

def _variant(tmp_path: Path) -> tuple[Path, Path, dict[str, bytes]]:
    variant = tmp_path / "pig"
    (variant / "renders" / "novel_view" / "lod0").mkdir(parents=True)
    (variant / "avatar.pt").write_bytes(b"weights")
    (variant / "train_log.csv").write_text("iteration,wall_s\n")
    capture = tmp_path / "capture"
    capture.mkdir()
    return variant, capture, _snapshot(tmp_path)


def test_render_pointed_at_a_variant_folder_keeps_avatar_pt(tmp_path, capsys):
    variant, capture, before = _variant(tmp_path)
    args = ["--capture", str(capture), "--split", "novel_view", "--preset", "test"]
    assert run_cli(render.main, ["--checkpoint", str(variant / "avatar.pt"), "--output", str(variant), *args, "--overwrite"]) == 1
    assert (f"render: error: {variant}: the output contains the input {variant / 'avatar.pt'}; "
            "choose another output folder") in capsys.readouterr().err
    other = tmp_path / "elsewhere.pt"
    assert run_cli(render.main, ["--checkpoint", str(other), "--output", str(variant), *args]) == 1
    assert (f"render: error: {variant}: holds files the render stage did not write (avatar.pt, renders, "
            "train_log.csv)") in capsys.readouterr().err
    assert _snapshot(tmp_path) == before and not other.exists()


def test_a_folder_marked_by_another_stage_is_refused(tmp_path):
    from pig._outputs import OutputError, claim_dir

    (tmp_path / "capture").mkdir()
    (tmp_path / "capture" / MARKER).write_text(json.dumps({"stage": "preprocess"}))
    with pytest.raises(OutputError, match="holds the preprocess stage's output, not the render stage's"):
        claim_dir(tmp_path / "capture", "render")
    assert claim_dir(tmp_path / "capture", "preprocess") == tmp_path / "capture"


def test_evaluate_never_writes_into_the_renders_or_over_foreign_files(tmp_path, capsys):
    variant, capture, before = _variant(tmp_path)
    renders = variant / "renders" / "novel_view"
    args = ["--capture", str(capture), "--renders", str(renders), "--split", "novel_view", "--preset", "test"]
    assert run_cli(evaluate.main, [*args, "--output", str(renders)]) == 1
    assert f"evaluate: error: {renders}: the output is the input {renders}" in capsys.readouterr().err
    metrics = variant / "metrics"
    metrics.mkdir()
    (metrics / "novel_view_lod0.json").write_text("{}")
    assert run_cli(evaluate.main, [*args, "--output", str(metrics)]) == 1
    assert (f"evaluate: error: {metrics}: holds files the evaluate stage did not write (novel_view_lod0.json)"
            in capsys.readouterr().err)
    assert (metrics / "novel_view_lod0.json").read_text() == "{}" and _hidden(metrics) == []
    assert _snapshot(tmp_path) == {**before, "pig/metrics/novel_view_lod0.json": b"{}"}


def test_fit_keeps_files_it_did_not_write(tmp_path, capsys):
    variant, capture, before = _variant(tmp_path)
    args = ["--capture", str(capture), "--preset", "test", "--device", "cpu"]
    assert run_cli(fit.main, [*args, "--output", str(variant)]) == 1
    assert (f"fit: error: {variant}: holds files the fit stage did not write (avatar.pt, train_log.csv); "
            "pass --overwrite") in capsys.readouterr().err
    assert run_cli(fit.main, [*args, "--output", str(capture), "--overwrite"]) == 1
    assert f"fit: error: {capture}: the output is the input {capture}" in capsys.readouterr().err
    assert _snapshot(tmp_path) == before


def test_fit_removes_the_temporaries_of_a_killed_fit(tmp_path, dead_pid, live_pid):
    variant = tmp_path / "pig"
    variant.mkdir()
    (variant / MARKER).write_text(json.dumps({"stage": "fit"}))
    orphans = [f".checkpoint.{dead_pid}.tmp.pt", f".checkpoint.pt.{dead_pid}.tmp", f".avatar.{dead_pid}.tmp.pt",
               f".train_log.{dead_pid}.tmp.csv", f".train_log.{dead_pid}.tmp.png"]
    kept = [f".checkpoint.{live_pid}.tmp.pt", f".notes.{dead_pid}.tmp.txt", MARKER]
    for name in orphans + kept[:-1]:
        (variant / name).write_bytes(b"partial")
    # The capture is absent: this run fails after claiming its output folder, which is when orphans go.
    with pytest.raises(CaptureError, match="preprocessed capture .* not found"):
        fit.fit(tmp_path / "capture", variant, "test")
    assert _hidden(variant) == sorted(kept)


# -- tables: every input checked before any output is written -------------------------------------------------

def _summary(root: Path, variant: str, split: str, psnr: float) -> Path:
    path = root / "synthetic" / "s0" / variant / "metrics" / f"{split}_lod0.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"split": split, "lod": 0, "psnr": psnr, "ssim": 0.9, "lpips": math.nan, "lpips_net": "alex", "fid": math.nan,
                                "psnr_blank": 10.0, "ssim_blank": 0.5, "splats": 100, "model_mb": 1.0, "fps": 50.0,
                                "device": "cpu"}))
    return path


@pytest.mark.parametrize("bad_log", [
    "iteration,wall_s\n0,0.0\n",  # no heldout_psnr column
    "iteration,wall_s,heldout_psnr\n0,zero,12.0\n",  # not a number
    "",  # empty
])
def test_tables_with_one_bad_train_log_write_nothing(tmp_path, bad_log):
    out = tmp_path / "tables"
    logs = []
    for variant in ("pig", "no_offsets"):
        log = tmp_path / "synthetic" / "s0" / variant / "train_log.csv"
        log.parent.mkdir(parents=True)
        log.write_text("iteration,wall_s,heldout_psnr\n0,0.0,12.0\n10,5.0,20.0\n")
        logs.append(log)
    summaries = [_summary(tmp_path, v, s, 30.0) for v in ("pig", "no_offsets") for s in tables.SPLITS]
    tables.make_tables("synthetic", summaries, logs, ["pig", "no_offsets"], out)
    before = _snapshot(out)
    assert {"synthetic.csv", "synthetic.md", "synthetic_lod.csv", "synthetic_lod.md", "synthetic_training.png"} <= set(before)
    summaries = [_summary(tmp_path, v, s, 25.0) for v in ("pig", "no_offsets") for s in tables.SPLITS]
    logs[1].write_text(bad_log)
    with pytest.raises(ValueError, match=f"{logs[1]}: (train log lacks columns|train log has a non-numeric|not a readable)"):
        tables.make_tables("synthetic", summaries, logs, ["pig", "no_offsets"], out)
    assert _snapshot(out) == before


def test_tables_keep_a_foreign_file_of_the_same_name(tmp_path, capsys):
    summary = _summary(tmp_path, "pig", "novel_view", 30.0)
    out = tmp_path / "tables"
    out.mkdir()
    (out / "synthetic.csv").write_text("my own table")
    argv = ["--dataset", "synthetic", "--summaries", str(summary), "--variants", "pig", "--output", str(out)]
    assert run_cli(tables.main, argv) == 1
    assert (f"tables: error: {out}: holds files the tables stage did not write (synthetic.csv)"
            in capsys.readouterr().err)
    assert sorted(p.name for p in out.iterdir()) == ["synthetic.csv"]
    assert run_cli(tables.main, [*argv, "--overwrite"]) == 0
    assert pd.read_csv(out / "synthetic.csv")["variant"].iloc[0] == "pig"
    assert run_cli(tables.main, argv) == 0  # a rerun over its own output


# -- generate: reruns, foreign folders, orphans ------------------------------------------------------------------

def test_generate_replaces_its_own_capture_without_overwrite_and_removes_orphans(tmp_path, dead_pid, live_pid):
    preset = tmp_path / "tiny.yaml"
    preset.write_text(yaml.safe_dump({"synthetic": {"cameras": 1, "frames": 1, "width": 16, "height": 16,
                                                     "workers": 1, "supersample": 1}}))
    out = tmp_path / "data" / "subject00"
    out.mkdir(parents=True)  # an earlier generated capture, as far as the stage can tell
    (out / MARKER).write_text(json.dumps({"stage": "generate"}))
    (out / "calibration.json").write_text("stale")
    for name in (f".subject00.{dead_pid}.tmp", f".subject00.{live_pid}.tmp"):
        (out.parent / name / "images").mkdir(parents=True)
    assert run_cli(generate.main, ["--output", str(out), "--preset", str(preset), "--quiet"]) == 0
    assert json.loads((out / "calibration.json").read_text())["cam00"]["imgSize"] == [16, 16]
    assert sorted(p.name for p in out.parent.iterdir()) == [f".subject00.{live_pid}.tmp", "subject00"]


# -- the shared helpers -----------------------------------------------------------------------------------------

def test_the_marker_name_is_the_stages(tmp_path):
    from pig._outputs import MARKER as STAGE_MARKER, claim_files

    assert STAGE_MARKER == MARKER
    claim_files(tmp_path / "out", ["a.csv"], "evaluate")
    assert json.loads((tmp_path / "out" / MARKER).read_text()) == {"stage": "evaluate"}


def test_atomic_dir_replaces_only_on_success(tmp_path):
    from pig._io import atomic_dir

    target = tmp_path / "out"
    target.mkdir()
    (target / "old.txt").write_text("old")
    with pytest.raises(RuntimeError, match="killed"):
        with atomic_dir(target) as tmp:
            (tmp / "new.txt").write_text("half")
            raise RuntimeError("killed")
    assert _snapshot(tmp_path) == {"out/old.txt": b"old"}
    with atomic_dir(target) as tmp:
        (tmp / "new.txt").write_text("new")
    assert _snapshot(tmp_path) == {"out/new.txt": b"new"}


def test_remove_orphans_matches_only_its_own_path(tmp_path, dead_pid):
    from pig._io import remove_orphans

    names = [f".avatar.{dead_pid}.tmp.pt", f".avatar.pt.{dead_pid}.tmp", f".avatar.{dead_pid}.tmp.csv",
             f".avatars.{dead_pid}.tmp.pt", f"avatar.{dead_pid}.tmp.pt", f".avatar.{dead_pid}x.tmp.pt"]
    for name in names:
        (tmp_path / name).write_text("x")
    removed = remove_orphans(tmp_path / "avatar.pt")
    assert sorted(p.name for p in removed) == sorted(names[:2])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names[2:])
    assert remove_orphans(tmp_path / "missing" / "avatar.pt") == []


@pytest.mark.parametrize("builder", ["resumable_dir", "build_dir"])
def test_a_symlinked_output_folder_is_refused_before_anything_changes(tmp_path, builder):
    """Sweep three: a render folder that was a symbolic link to an earlier render was renamed aside as the old
    folder, the new one put in its place, and then rmtree failed on the link ("Cannot call rmtree on a symbolic
    link"): the link was already gone. A stage replaces its folder as a whole, so a link there is refused first."""
    from pig._outputs import OutputError, build_dir, claim_dir, resumable_dir

    target = tmp_path / "elsewhere" / "novel_view"
    target.mkdir(parents=True)
    (target / MARKER).write_text(json.dumps({"stage": "render"}))
    (target / "view.png").write_bytes(b"the earlier render")
    link = tmp_path / "renders" / "novel_view"
    link.parent.mkdir()
    link.symlink_to(target)
    before = _snapshot(tmp_path / "elsewhere")

    with pytest.raises(OutputError, match=rf"{link}: a symbolic link \(to {target}\)"):
        output = claim_dir(link, "render")
        build = resumable_dir(output, "render", {}) if builder == "resumable_dir" else build_dir(output, "render")
        with build as work:
            (work / "view.png").write_bytes(b"the new render")

    assert link.is_symlink() and link.resolve() == target and sorted(p.name for p in link.parent.iterdir()) == [
        "novel_view"]
    assert _snapshot(tmp_path / "elsewhere") == before
