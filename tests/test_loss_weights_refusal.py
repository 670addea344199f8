"""A workflow run whose fits use the LPIPS term of Eq. 15 (the paper preset's) is refused at its start when the
term's weights are missing or fail their checksum, naming `pig weights --fetch`; a dry run plans without them."""
from __future__ import annotations

import hashlib
import shutil

import pytest
from test_workflow import PRESET, TARGET, edit_yaml, recorded, scheduled, snakemake_exit  # noqa: F401

import pig.metrics.weight_files as wf

FIT_LOG = "results/thuman4/subject 00/pig/logs/fit.log"


@pytest.fixture
def lpips_workflow(recorded, tmp_path, monkeypatch):
    """A copy of the recorded workflow whose preset fits with a pretrained LPIPS-alex term, an empty hub cache."""
    work = tmp_path / "work dir"
    shutil.copytree(recorded, work, symlinks=True)
    edit_yaml(work / PRESET, lambda p: p["fit"].update(weight_lpips=1.0, lpips_net="alex", lpips_weights="pretrained"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setattr(wf, "lpips_package_weights", lambda: None)
    return work


def fit_once(work):
    """A forked Snakemake, which sees this test's patches of pig.metrics.weight_files (the DAG-time check)."""
    return snakemake_exit(work, TARGET, "--forcerun", "fit_avatar", "--until", "fit_avatar", "--cores", "1", fork=True)


def test_missing_or_corrupt_loss_weights_refuse_the_run(lpips_workflow, tmp_path, monkeypatch):
    assert scheduled(lpips_workflow)  # the preset change reruns the fit; planning needs no weights
    code, output = fit_once(lpips_workflow)
    flat = " ".join(output.split())
    assert code == 1 and "fits with the LPIPS term of Eq. 15" in flat and "`pig weights --fetch`" in flat
    assert "alexnet: missing" in flat and "lpips-alex: missing" in flat
    assert (lpips_workflow / FIT_LOG).read_text() == ""  # nothing ran

    # Stand-in files with their checksums in the table: the alex backbone corrupt, the linear layers good.
    hub = tmp_path / "torch_home" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    table = []
    for entry in wf.WEIGHT_FILES:
        content = f"stand-in {entry.name}".encode()
        table.append(wf.WeightFile(entry.name, entry.filename, entry.url, hashlib.sha256(content).hexdigest(),
                                   len(content), "test", entry.used_by, entry.in_lpips_package))
        (hub / entry.filename).write_bytes(b"corrupt" if entry.name == "alexnet" else content)
    monkeypatch.setattr(wf, "WEIGHT_FILES", tuple(table))
    code, output = fit_once(lpips_workflow)
    flat = " ".join(output.split())
    assert code == 1 and "alexnet: checksum bad" in flat and "lpips-alex" not in flat

    (hub / "alexnet-owt-7be5be79.pth").write_bytes(b"stand-in alexnet")
    code, output = fit_once(lpips_workflow)
    assert "LPIPS term of Eq. 15" not in output
    assert (lpips_workflow / FIT_LOG).read_text() != ""  # the fit ran (and failed on the fake capture)


def test_fetch_weights_runs_only_when_named(recorded):
    from test_workflow import snakemake_run

    output = snakemake_run(recorded, "fetch_weights", "--dry-run", "--printshellcmds")
    assert "python -m pig.stages.weights --fetch 2>&1 | tee results/logs/fetch_weights.log" in output
    assert scheduled(recorded) == {}  # not part of the tables' target
