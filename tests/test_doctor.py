"""`pig doctor`: each check's verdict under monkeypatched conditions (no CUDA, nvcc missing, a broken gsplat build,
weights missing or corrupt, a real capture without its body model, little disk), the disk estimate against measured
sizes, and the command itself on this machine."""
from __future__ import annotations

import hashlib
import re
import shutil
from collections import namedtuple
from pathlib import Path

import pytest
import torch
import yaml

import pig.doctor as doctor
import pig.metrics.weight_files as wf
from pig.config import load_preset


@pytest.fixture
def no_nvcc(monkeypatch, tmp_path):
    """No nvcc anywhere torch's extension builder looks."""
    for name in ("CUDA_HOME", "CUDA_PATH"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("PATH", str(tmp_path / "empty-bin"))
    monkeypatch.setattr(doctor, "CUDA_DEFAULT", tmp_path / "no-cuda")


@pytest.fixture
def fake_nvcc(monkeypatch, tmp_path):
    """An `nvcc` on PATH that reports release 12.8."""
    folder = tmp_path / "bin"
    folder.mkdir()
    nvcc = folder / "nvcc"
    nvcc.write_text("#!/bin/sh\necho 'Cuda compilation tools, release 12.8, V12.8.93'\n")
    nvcc.chmod(0o755)
    for name in ("CUDA_HOME", "CUDA_PATH"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("PATH", str(folder))
    monkeypatch.setattr(doctor, "CUDA_DEFAULT", tmp_path / "no-cuda")
    return nvcc


@pytest.fixture
def no_gsplat_build(monkeypatch, tmp_path):
    """An empty extension folder, so no JIT build of gsplat is found (a prebuilt one is not installed here)."""
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    monkeypatch.setattr(doctor, "gsplat_extensions", lambda: ("1.5.3", []))


@pytest.fixture
def hub(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setattr(wf, "lpips_package_weights", lambda: None)
    return tmp_path / "torch_home" / "hub" / "checkpoints"


def test_gpu_preset_without_cuda_is_missing_and_a_cpu_preset_is_ok(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.version, "cuda", None)
    check = doctor.check_torch(gpu=True)
    assert check.verdict == "missing" and "CPU-only build" in check.detail and "CUDA build" in check.detail
    assert doctor.check_torch(gpu=False).verdict == "ok"
    monkeypatch.setattr(torch.version, "cuda", "12.8")
    assert "no CUDA GPU is visible" in doctor.check_torch(gpu=True).detail


def test_a_visible_gpu_is_named(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i: f"Stand-in GPU {i}")
    monkeypatch.setattr(torch.version, "cuda", "12.8")
    check = doctor.check_torch(gpu=True)
    assert check.verdict == "ok" and "CUDA 12.8 build" in check.detail and "Stand-in GPU 1" in check.detail


def test_the_presets_say_whether_they_use_a_gpu():
    assert doctor.needs_gpu(load_preset("paper")) and not doctor.needs_gpu(load_preset("cpu-demo"))
    assert doctor.needs_gpu({"resources": {"default": {"gpu": 1}}})


def test_nvcc_missing_is_missing_only_where_gsplat_must_compile(no_nvcc, no_gsplat_build):
    assert doctor.nvcc_version() == (None, None)
    assert doctor.check_nvcc(gpu=True).verdict == "missing"
    assert doctor.check_nvcc(gpu=False).verdict == "ok"
    check = doctor.check_gsplat(gpu=True)
    assert check.verdict == "missing" and "no nvcc" in check.detail


def test_nvcc_found_its_release_read_and_a_major_mismatch_warned(fake_nvcc, no_gsplat_build, monkeypatch):
    assert doctor.nvcc_version() == (fake_nvcc, "12.8")
    monkeypatch.setattr(torch.version, "cuda", "12.6")
    assert doctor.check_nvcc(gpu=True).verdict == "ok"
    monkeypatch.setattr(torch.version, "cuda", "13.0")
    check = doctor.check_nvcc(gpu=True)
    assert check.verdict == "warn" and "CUDA 13.0" in check.detail
    check = doctor.check_gsplat(gpu=True)
    assert check.verdict == "warn" and "first GPU call compiles it" in check.detail


def test_the_jit_build_is_found_where_torch_builds_it_and_a_broken_one_does_not_load(monkeypatch, tmp_path, no_nvcc):
    from torch.utils.cpp_extension import _get_build_directory

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    assert doctor.jit_folder() == Path(_get_build_directory(doctor.GSPLAT_JIT_NAME, verbose=False))
    monkeypatch.delenv("TORCH_EXTENSIONS_DIR")
    monkeypatch.setattr(torch.version, "cuda", "12.8")
    monkeypatch.setattr("torch.utils.cpp_extension.get_default_build_root", lambda: str(tmp_path / "root"))
    assert doctor.jit_folder() == Path(_get_build_directory(doctor.GSPLAT_JIT_NAME, verbose=False))

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    broken = tmp_path / "ext" / "gsplat_cuda" / "gsplat_cuda.so"
    broken.parent.mkdir(parents=True, exist_ok=True)
    broken.write_bytes(b"not an ELF file")
    version, built = doctor.gsplat_extensions()
    assert version == "1.5.3" and broken in built
    check = doctor.check_gsplat(gpu=True)
    assert check.verdict == "missing" and "does not load" in check.detail
    assert doctor.check_nvcc(gpu=True).verdict == "missing"  # a build that does not load is rebuilt: nvcc needed


def test_a_compiled_extension_that_loads_is_seen_to_load():
    import _json

    assert doctor.loads(Path(_json.__file__)) == ""


def write_weights(hub: Path, monkeypatch, names: list[str], corrupt: str | None = None) -> None:
    """Stand-in weight files (small bytes, their SHA-256 in a monkeypatched table) in the hub cache; `corrupt`
    gets other bytes than its checksum says."""
    hub.mkdir(parents=True, exist_ok=True)
    table = []
    for entry in wf.WEIGHT_FILES:
        content = f"stand-in {entry.name}".encode()
        table.append(wf.WeightFile(entry.name, entry.filename, entry.url, hashlib.sha256(content).hexdigest(),
                                   len(content), "test", entry.used_by, entry.in_lpips_package))
        if entry.name in names:
            (hub / entry.filename).write_bytes(b"corrupt" if entry.name == corrupt else content)
    monkeypatch.setattr(wf, "WEIGHT_FILES", tuple(table))


def verdicts(checks) -> dict[str, str]:
    return {re.match(r"(\S+) ", c.detail).group(1): c.verdict for c in checks}


def test_weights_for_the_evaluation_warn_and_for_the_loss_are_needed(hub, monkeypatch):
    write_weights(hub, monkeypatch, [])
    assert verdicts(doctor.check_weights(load_preset("cpu-demo"))) == {
        "alexnet": "warn", "lpips-alex": "warn", "inception": "warn"}
    paper = verdicts(doctor.check_weights(load_preset("paper")))
    assert paper == {"vgg16": "missing", "lpips-vgg": "missing", "inception": "warn"}

    write_weights(hub, monkeypatch, ["vgg16", "lpips-vgg", "inception"], corrupt="vgg16")
    checks = doctor.check_weights(load_preset("paper"))
    assert verdicts(checks) == {"vgg16": "missing", "lpips-vgg": "ok", "inception": "ok"}
    assert "checksum bad" in checks[0].detail and "LPIPS term" in checks[0].detail

    (hub / "vgg16-397923af.pth").write_bytes(b"stand-in vgg16")
    assert set(verdicts(doctor.check_weights(load_preset("paper"))).values()) == {"ok"}


def test_configured_weight_paths_are_the_ones_checked(hub, monkeypatch, tmp_path):
    write_weights(hub, monkeypatch, ["alexnet", "lpips-alex", "inception"])
    preset = load_preset("cpu-demo")
    preset["evaluate"]["lpips_backbone_weights"] = str(tmp_path / "mine.pth")
    checks = doctor.check_weights(preset)
    assert verdicts(checks)["alexnet"] == "warn" and str(tmp_path / "mine.pth") in checks[0].detail
    # The paper's loss with the user's own (fine-tuned) VGG by path: used as it is, whatever its checksum.
    write_weights(hub, monkeypatch, ["lpips-vgg", "inception"])
    (tmp_path / "my_vgg.pth").write_bytes(b"fine-tuned")
    paper = load_preset("paper")
    paper["fit"]["lpips_backbone_weights"] = str(tmp_path / "my_vgg.pth")
    checks = [c for c in doctor.check_weights(paper) if c.detail.startswith("vgg16") and "LPIPS loss" in c.detail]
    assert [c.verdict for c in checks] == ["warn"] and "a configured file, used as it is" in checks[0].detail


def test_body_model(tmp_path):
    cpu = load_preset("cpu-demo")
    synthetic, source = doctor.load_dataset("synthetic")
    check = doctor.check_body_model(cpu, synthetic, source)
    assert check.verdict == "ok" and "the real captures need one: actorshq, avatarrex, dna, easymocap, thuman4" in check.detail
    thuman4, source = doctor.load_dataset("thuman4")
    check = doctor.check_body_model(cpu, thuman4, source)
    assert check.verdict == "missing" and "SMPLX_NEUTRAL.npz" in check.detail and "not set" in check.detail
    model = tmp_path / "SMPLX_NEUTRAL.npz"
    model.write_bytes(b"x")
    mine = tmp_path / "mine.yaml"
    mine.write_text(yaml.safe_dump({**thuman4, "body_model": str(model)}))
    data, source = doctor.load_dataset(str(mine))
    assert doctor.check_body_model(cpu, data, source).verdict == "ok"
    cpu["synthetic"]["body_model"] = str(tmp_path / "absent.npz")
    assert doctor.check_body_model(cpu, synthetic, "synthetic").verdict == "missing"


Usage = namedtuple("Usage", "total used free")


def test_little_disk_is_missing(monkeypatch, tmp_path):
    preset, (dataset, _) = load_preset("cpu-demo"), doctor.load_dataset("synthetic")
    need = doctor.estimate_disk(preset, dataset).total
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(10 * need, 9 * need, need - 1))
    check = doctor.check_disk(preset, dataset, tmp_path / "not" / "yet" / "results")
    assert check.verdict == "missing" and str(tmp_path) in check.detail
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(10 * need, 0, 10 * need))
    assert doctor.check_disk(preset, dataset, tmp_path).verdict == "ok"


def test_disk_estimate_against_measured_sizes():
    """The formula's THuman4 capture against benchmarks/encoding.py's 11.8 GB a subject (NOTES.md, 23 x 2000 training,
    1 x 2000 novel view, 24 x 500 novel pose views), and the default target's estimate against what the default run
    wrote (results/synthetic: 72,664,559 bytes, NOTES.md)."""
    thuman4 = doctor.estimate_disk(load_preset("paper"), doctor.load_dataset("thuman4")[0])
    assert thuman4.parts["capture"] / doctor.MARGIN == pytest.approx(11.8e9, rel=0.02)
    assert thuman4.subjects == 3
    default = doctor.estimate_disk(load_preset("cpu-demo"), doctor.load_dataset("synthetic")[0])
    assert 72_664_559 <= default.total <= 2 * 72_664_559
    # max_side 512 shrinks THuman4's 1330 x 1150 views by (512 / 1330)^2 on the CPU preset
    small = doctor.estimate_disk(load_preset("cpu-demo"), doctor.load_dataset("thuman4")[0])
    assert small.parts["capture"] / thuman4.parts["capture"] == pytest.approx((512 / 1330) ** 2, rel=0.01)
    assert doctor.estimate_disk(load_preset("paper"), {"name": "mine", "format": "thuman4", "subjects": ["a"]}) is None


def test_disk_estimate_of_a_users_thuman4_layout_capture(tmp_path):
    """Sizes from the first subject's calibration.json and its images: 3 cameras x 8 frames at 200 x 100, two held
    out (novel_view_count) on the first 6 frames, the last 2 frames (novel_pose_fraction 0.25) on all three."""
    import os

    from thuman4_fixture import write_thuman4

    train, heldout, views = 1 * 6, 2 * 6 + 3 * 2, 1 * 6 + 2 * 6 + 3 * 2
    capture = 200 * 100 * (train * doctor.JPEG_BPP + heldout * doctor.PNG_BPP + views * doctor.MASK_BPP)
    for ext in ("jpg", "png"):  # the layout allows either
        root = write_thuman4(tmp_path / ext / "s0", cameras=3, frames=8, width=200, height=100, ext=ext)
        dataset = {"name": "mine", "format": "thuman4", "root": str(tmp_path / ext), "subjects": ["s0", "s1"],
                   "split": {"novel_view_count": 2, "novel_pose_fraction": 0.25}}
        estimate = doctor.estimate_disk(load_preset("paper"), dataset)
        assert estimate.subjects == 2 and "calibration" in estimate.how
        assert estimate.parts["capture"] == pytest.approx(doctor.MARGIN * capture, rel=1e-12)
    (root / "calibration.json").write_text("{}")  # a calibration the reader refuses: no estimate, not an error
    assert doctor.estimate_disk(load_preset("paper"), dataset) is None
    (root / "calibration.json").unlink()
    os.mkfifo(root / "calibration.json")  # never opened: a FIFO would block a reader that opens it
    assert doctor.estimate_disk(load_preset("paper"), dataset) is None


def test_pig_doctor_runs_here_and_reports_what_is_missing(hub, capsys):
    from pig.cli import main

    status = main(["doctor"])
    out = capsys.readouterr().out
    names = [line.split()[1] for line in out.splitlines()[1:-1]]
    assert names[:3] == ["torch", "gsplat", "nvcc"] and names[-2:] == ["body", "disk"]
    assert re.search(r"^warn +weights +alexnet for the evaluation: missing", out, re.M)
    assert status == (1 if re.search(r"^missing ", out, re.M) else 0)
    status = main(["doctor", "--preset", "paper", "--dataset", "thuman4"])
    out = capsys.readouterr().out
    assert status == 1 and re.search(r"^missing +body +thuman4", out, re.M)
    assert re.search(r"^missing +weights +vgg16 for the evaluation and fit's LPIPS loss", out, re.M)
    assert "missing for this preset and dataset:" in out.splitlines()[-1]


def test_the_doctor_never_loads_gsplats_cuda_backend(tmp_path):
    """gsplat.cuda._backend compiles the CUDA extension when it finds none; the doctor looks on disk instead."""
    import os
    import subprocess
    import sys

    code = ("import sys; from pig.cli import main; main(['doctor', '--preset', 'paper', '--results', sys.argv[1]]); "
            "print('backend imported:', 'gsplat.cuda._backend' in sys.modules)")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "TORCH_HOME": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, env=env,
                          timeout=120)
    assert done.stdout.splitlines()[-1] == "backend imported: False", done.stdout + done.stderr
    assert re.search(r"^\S+ +gsplat ", done.stdout, re.M)
