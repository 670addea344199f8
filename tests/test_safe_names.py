"""Names that become paths (camera ids, subject, dataset, variant, sequence): a `../..` or absolute name is refused
with the file and value named, before any stage writes or deletes anything outside its folders (sweep two, 1-2)."""
from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import pytest
import yaml

from thuman4_fixture import write_thuman4

from pig.data.capture import Capture
from pig.data.dna import locate_smc
from pig.data.raw import CaptureError
from pig.data.thuman4 import read_calibration
from pig.names import NAME_BYTES, NAME_MAX, UnsafeName, safe_name
from pig._cli import run_cli

UNSAFE = [("../../victim", "contains a path separator"), ("/abs/victim", "contains a path separator"),
          ("a\\b", "contains a path separator"), ("..", "starts with '.'"), (".", "starts with '.'"),
          (".hidden", "starts with '.'"), ("", "is empty"), ("cam\x00", "contains a control character"),
          ("x" * 256, "is 256 bytes long, more than 219"), ("é" * 128, "is 256 bytes long, more than 219"),
          ("x" * 220, "is 220 bytes long, more than 219"), ("<logs>", "contains '<' '>', which Snakemake"),
          ("<results>", "contains '<' '>'"), ("a{x}", "contains '{' '}'"), ("a}", "contains '}'"),
          ("a\x85b", "contains a control character"), ("a\x9bb", "contains a control character"),
          ("abc\u202efed", "contains a bidirectional formatting character"),
          ("a\u2066b", "contains a bidirectional formatting character"),
          (7, "must be a string"), (None, "must be a string")]


def _snapshot(folder: Path) -> dict[str, str]:
    """Every file under `folder` (hidden ones included) by relative path -> SHA-256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("name", ["cam00", "0", "59", "0012_09", "subject-A", "noise_0.05", "é", "x" * 219,
                                  "é" * 109, "subject (1) [a]", "a=b,c;d"])
def test_plain_names_pass_unchanged(name):
    assert safe_name(name, "camera id", "calibration.json") == name


@pytest.mark.parametrize("name, problem", UNSAFE)
def test_unsafe_names_are_refused_naming_the_source_value_and_problem(name, problem):
    with pytest.raises(UnsafeName) as err:
        safe_name(name, "camera id", "/data/calibration.json")
    shown = repr(name) if not isinstance(name, str) or len(name) <= 80 else repr(name[:77]) + "..."
    assert str(err.value).startswith(f"/data/calibration.json: camera id {shown} {problem}")


def _victim(folder: Path) -> Path:
    """A user's folder holding hidden files and frames, where an escaping camera id would lead."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in (".notes", ".env", ".keep"):
        (folder / name).write_text(f"the user's {name}\n")
    return folder


@pytest.mark.parametrize("escape", ["relative", "absolute"])
def test_preprocess_refuses_an_escaping_calibration_camera_id_and_touches_nothing(tmp_path, capsys, escape):
    """Sweep two, case 1: the raw calibration's camera key `../../victim` (or an absolute path) made preprocess
    delete the hidden files of that folder and write images and masks there before any check failed."""
    from pig.stages.preprocess import main

    raw = write_thuman4(tmp_path / "data" / "subject", cameras=3, frames=3, width=48, height=40)
    victim = _victim(tmp_path / "data" / "victim")
    # The camera's frames moved into the victim folder, reached from images/ and masks/ by the bad id.
    for kind in ("images", "masks"):
        for frame in (raw / kind / "cam01").iterdir():
            shutil.copy(frame, victim / f"{kind}_{frame.name}" if kind == "masks" else victim / frame.name)
        shutil.rmtree(raw / kind / "cam01")
    name = "../../victim" if escape == "relative" else str(victim)
    calibration = json.loads((raw / "calibration.json").read_text())
    calibration = {name if key == "cam01" else key: value for key, value in calibration.items()}
    (raw / "calibration.json").write_text(json.dumps(calibration))
    before = _snapshot(tmp_path)
    out = tmp_path / "data" / "out"  # its work folder's images/../.. is data/: the victim is one step away

    status = run_cli(main, ["--input", str(raw), "--output", str(out), "--preset", "test", "--no-progress"])

    assert _snapshot(tmp_path) == before
    assert sorted(p.name for p in (tmp_path / "data").iterdir()) == ["subject", "victim"]
    assert status == 1
    assert f"{raw / 'calibration.json'}: camera id {name!r} contains a path separator" in capsys.readouterr().err
    with pytest.raises(CaptureError, match="camera id"):
        read_calibration(raw / "calibration.json")


def test_preprocess_refuses_an_unsafe_subject_before_writing(tmp_path, capsys):
    from pig.stages.preprocess import main

    raw = write_thuman4(tmp_path / "subject", cameras=3, frames=3, width=48, height=40)
    status = run_cli(main, ["--input", str(raw), "--output", str(tmp_path / "out"), "--preset", "test",
                            "--no-progress", "--subject", "../x"])
    assert not (tmp_path / "out").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["subject"]
    assert status == 1 and "subject '../x' contains a path separator" in capsys.readouterr().err


def _with_camera_renamed(capture: Path, copy: Path, old: str, new: str) -> Path:
    """A copy of a preprocessed capture whose cameras.json and split.json call camera `old` `new`."""
    shutil.copytree(capture, copy)
    for name in ("cameras.json", "split.json"):
        text = (copy / name).read_text().replace(f'"{old}"', json.dumps(new))
        (copy / name).write_text(text)
    return copy


@pytest.mark.parametrize("escape", ["relative", "absolute"])
def test_render_refuses_an_escaping_camera_id_of_the_capture_and_overwrites_nothing(tiny_fit, tmp_path, capsys,
                                                                                    escape):
    """Sweep two, case 1: the same id in a preprocessed capture's cameras.json made render overwrite a user's
    00000000.png outside its output folder, with exit status 0."""
    from pig.stages.render import main

    capture, avatar = tiny_fit
    victim = _victim(tmp_path / "work" / "victim")
    (victim / "00000000.png").write_bytes(b"the user's own image")
    name = "../../victim" if escape == "relative" else str(victim)
    split = json.loads((capture / "split.json").read_text())
    copy = _with_camera_renamed(capture, tmp_path / "capture", split["novel_view"]["cameras"][0], name)
    before = _snapshot(tmp_path / "work")
    out = tmp_path / "work" / "renders"  # lod0/../.. of its work folder is work/

    status = run_cli(main, ["--checkpoint", str(avatar), "--capture", str(copy), "--split", "novel_view",
                            "--output", str(out), "--preset", "test"])

    assert _snapshot(tmp_path / "work") == before and not out.exists()
    assert status == 1
    assert f"{copy / 'cameras.json'}: camera id {name!r} contains a path separator" in capsys.readouterr().err
    with pytest.raises(CaptureError, match="camera id"):
        Capture.load(copy)


def test_tables_refuses_an_escaping_dataset_name_and_keeps_the_users_file(tmp_path, capsys):
    """Sweep two, case 2: `tables --dataset ../../escaped` overwrote the user's escaped.csv outside --output."""
    from pig.stages.tables import main

    summary = tmp_path / "results" / "synthetic" / "s0" / "pig" / "metrics" / "novel_view_lod0.json"
    summary.parent.mkdir(parents=True)
    summary.write_text(json.dumps({"split": "novel_view", "lod": 0, "splats": 100, "psnr": 20.0, "ssim": 0.9,
                                   "lpips": 0.1, "lpips_net": "alex", "fid": None, "images": 1, "model_mb": 1.0,
                                   "fps": 1.0, "device": "cpu", "psnr_blank": 10.0, "ssim_blank": 0.5}))
    (tmp_path / "escaped.csv").write_text("the user's own table\n")
    before = _snapshot(tmp_path)

    status = run_cli(main, ["--dataset", "../../escaped", "--summaries", str(summary), "--variants", "pig",
                            "--output", str(tmp_path / "results" / "tables")])

    assert _snapshot(tmp_path) == before and not (tmp_path / "results" / "tables").exists()
    assert status == 1
    assert "--dataset: dataset name '../../escaped' contains a path separator" in capsys.readouterr().err


def test_dna_sequence_name_is_one_path_component(tmp_path):
    with pytest.raises(CaptureError, match=r"sequence name '\.\./seq'"):
        locate_smc(tmp_path, "../seq")


def test_workflow_refuses_an_escaping_subject_of_the_dataset_yaml(tmp_path):
    """A subject `../../escaped` in a dataset YAML would put results/{dataset}/{subject}/ outside results/."""
    import yaml

    import test_workflow as wf

    work = tmp_path / "work dir"
    wf._workflow_config(work, "thuman4")
    dataset = work / wf.DATASET
    data = yaml.safe_load(dataset.read_text())
    data["subjects"] = ["../../escaped"]
    dataset.write_text(yaml.safe_dump(data))
    wf._fake_thuman4_subject(work / "raw data" / "../../escaped")  # the raw data is there: only the name is wrong
    (work / "raw data" / "SMPLX NEUTRAL.npz").write_bytes(b"model")

    code, output = wf.snakemake_exit(work, wf.TARGET, "--dry-run")

    assert code != 0
    assert f"{wf.DATASET}: `subjects`: subject '../../escaped' contains a path separator" in output


def _workflow_with_subject(tmp_path, subject: str) -> Path:
    """The workflow's test folder (tests/test_workflow.py) whose dataset names `subject`; the raw folder `logs`
    beside it holds another subject's data, where a subject `<logs>` would lead."""
    import test_workflow as wf

    work = tmp_path / "work dir"
    wf._workflow_config(work, "thuman4")
    dataset = work / wf.DATASET
    data = yaml.safe_load(dataset.read_text())
    data["subjects"] = [subject]
    dataset.write_text(yaml.safe_dump(data))
    wf._fake_thuman4_subject(work / "raw data" / "logs")
    (work / "raw data" / "SMPLX NEUTRAL.npz").write_bytes(b"model")
    return work


@pytest.mark.parametrize("subject, problem", [
    ("<logs>", "contains '<' '>', which Snakemake reads in a path"),
    ("{subject}", "contains '{' '}', which Snakemake reads in a path"),
    ("s" * 250, f"is 250 bytes long, more than {NAME_BYTES}"),
])
def test_workflow_refuses_a_subject_snakemake_rewrites_or_too_long_before_writing(tmp_path, subject, problem):
    """Sweep three, case 3: Snakemake expands `<logs>` in rule paths, so subject `<logs>` ran preprocess on the
    raw folder `logs` (another subject's) and wrote results/thuman4/logs/; a 250-byte subject passed the name check
    and failed at its first job with "File name too long"."""
    import test_workflow as wf

    work = _workflow_with_subject(tmp_path, subject)
    before = _snapshot(work)

    code, output = wf.snakemake_exit(work, wf.TARGET, "--cores", "1")

    assert code != 0
    ours = {path: digest for path, digest in _snapshot(work).items() if not path.startswith(".snakemake/")}
    assert not (work / "results").exists() and ours == before
    shown = repr(subject) if len(subject) <= 80 else repr(subject[:77]) + "..."
    assert f"{wf.DATASET}: `subjects`: subject {shown} {problem}" in output


def test_the_name_bound_is_the_longest_file_name_the_workflow_builds(tmp_path, monkeypatch):
    """Every path of the workflow's rules (outputs, logs, benchmarks, the raw folder) with each name NAME_BYTES long
    and the other wildcards their longest values, and every temporary a stage writes beside each part (pig._io,
    at the largest Linux pid), fits in 255 bytes; one reaches it exactly, so the bound is no tighter than needed."""
    import pig._io as io

    monkeypatch.setattr(io.os, "getpid", lambda: 2 ** 22)  # pid_max's largest value on Linux
    rules = Path(__file__).resolve().parent.parent / "workflow" / "rules"
    text = "\n".join(path.read_text() for path in sorted(rules.glob("*.smk")))
    # Quoted paths of the rules and their helpers (`{wildcards.dataset}`, `{config['dataset']}` are the same names).
    patterns = {m for m in re.findall(r'"([^" \n]*\{(?:dataset|subject|variant)\}[^" \n]*)"', text)}
    assert len(patterns) > 20 and {"results/tables/{dataset}_{table}.html", "{subject}"} <= patterns
    longest = {"dataset": "d" * NAME_BYTES, "subject": "s" * NAME_BYTES, "variant": "v" * NAME_BYTES,
               "split": "novel_pose", "table": "ablation", "lod": "99", "clip": "turntable", "PREVIEW_CLIP": "preview"}
    names = []
    for pattern in patterns:
        filled = re.sub(r"\{(?:wildcards\.|config\[')?(\w+)(?:'\])?\}", lambda m: longest[m.group(1)], pattern)
        for part in filled.split("/"):
            path = tmp_path / part
            names += [part, io._temporary(path).name, io._temporary_dir(path).name, io._temporary_dir(path, "old").name,
                      f".{part}.partial", f".{part}.lock"]
    assert max(len(name.encode()) for name in names) == NAME_MAX


def test_workflow_refuses_snakemake_syntax_in_the_preset_path_and_the_raw_root(tmp_path):
    """A preset path with braces gave Snakemake's WildcardError naming neither; a dataset root `<logs>` silently
    became the folder `logs` (a root with another `<name>`: "Undefined pathvar")."""
    import test_workflow as wf

    work = _workflow_with_subject(tmp_path, wf.SUBJECT)
    wf._fake_thuman4_subject(work / "logs" / wf.SUBJECT)  # where the root `<logs>` would lead
    shutil.copyfile(work / wf.PRESET, work / "config" / "te{st}.yaml")
    code, output = wf.snakemake_exit(work, wf.TARGET, "--dry-run", "--config", "preset=config/te{st}.yaml")
    assert code != 0
    assert "config `preset` 'config/te{st}.yaml' contains '{' '}', which Snakemake reads in a path" in output

    data = yaml.safe_load((work / wf.DATASET).read_text())
    data.update(root="<logs>", body_model="raw data/SMPLX NEUTRAL.npz")
    (work / wf.DATASET).write_text(yaml.safe_dump(data))
    code, output = wf.snakemake_exit(work, wf.TARGET, "--dry-run")
    assert code != 0 and "rule preprocess_capture" not in output
    assert f"{wf.DATASET}: `root` '<logs>' contains '<' '>', which Snakemake reads in a path" in output


def test_a_dataset_name_with_regular_expression_characters_is_its_own_table(tmp_path):
    """The tables' rules join the dataset names into a wildcard constraint: unescaped, `thu+man4` matched only
    `thuman4`, `thuuman4`, ..., so its own table had no rule."""
    import test_workflow as wf

    work = _workflow_with_subject(tmp_path, "logs")
    config = yaml.safe_load((work / "config" / "config.yaml").read_text())
    config["datasets"]["thu+man4"] = config["datasets"].pop("thuman4")
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(config))

    output = wf.snakemake_run(work, "results/tables/thu+man4.csv", "--dry-run", "--config", "dataset=thu+man4")

    assert wf.job_counts(output)["make_tables"] == 1
