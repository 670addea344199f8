"""The all_tables target's fits and the plan_tables estimate (pig.avatar.plan, pig.stages.plan), and a run of the
target resumed after a kill without redoing finished fits."""
from __future__ import annotations

import fcntl
import itertools
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from test_workflow import (  # noqa: F401  (recorded: the fixture, shared with tests/test_workflow.py)
    PRESET,
    REPO,
    SUBJECT,
    _workflow_config,
    edit_yaml,
    job_counts,
    recorded,
    scheduled,
    snakemake_run,
)

from pig.avatar.plan import format_plan, makespan_s, plan_fits
from pig.config import load_preset
from pig.gpu_slots import DEVICES_ENV, LOCK_DIR_ENV, lock_path

PAPER_TABLES = ("--configfile", str(REPO / "config" / "paper_tables.yaml"))


def test_makespan_longest_first_on_the_device_that_frees_first():
    # By hand: 3 and 3 on the two devices, then 2 on each, the last 2 on either: 3 + 2 + 2 = 7 (the optimum, 6, puts
    # 3 + 3 on one; longest-first does not find it).
    assert makespan_s([2, 3, 2, 3, 2], 2) == 7
    assert makespan_s([2, 3, 2, 3, 2], 1) == 12
    assert makespan_s([2, 3, 2, 3, 2], 8) == 3
    assert makespan_s([], 4) == 0
    rng = random.Random(0)
    for _ in range(50):  # Graham's bounds for list scheduling, against the exhaustive optimum
        jobs, gpus = [rng.uniform(0.1, 5) for _ in range(rng.randint(1, 7))], rng.randint(1, 3)
        best = min(max(sum(j for j, d in zip(jobs, assign) if d == g) for g in range(gpus))
                   for assign in itertools.product(range(gpus), repeat=len(jobs)))
        assert best - 1e-9 <= makespan_s(jobs, gpus) <= best * (4 / 3 - 1 / (3 * gpus)) + 1e-9
    with pytest.raises(ValueError, match="at least one GPU"):
        makespan_s([1.0], 0)


def test_plan_counts_iterations_lpips_budget_and_checkpoints(tmp_path):
    preset = load_preset("test")
    preset["fit"].update(iterations=1000, weight_lpips=2.0)
    preset["variants"]["no_lpips"] = {"fit": {"weight_lpips": 0.0, "iterations": 400}}
    preset["variants"]["budget"] = {"fit": {"weight_lpips": 0.0, "time_budget_s": 5.0}}
    results = tmp_path / "results" / "synthetic"
    (results / "s1" / "pig").mkdir(parents=True)
    (results / "s1" / "pig" / "avatar.pt").write_bytes(b"")  # done
    (results / "s2" / "pig").mkdir(parents=True)
    torch.save({"iteration": 250, "wall_s": 12.5, "other": torch.zeros(3)}, results / "s2" / "pig" / "checkpoint.pt")
    (results / "s2" / "budget").mkdir(parents=True)
    torch.save({"iteration": 10, "wall_s": 4.0}, results / "s2" / "budget" / "checkpoint.pt")
    runs = [("s1", "pig"), ("s2", "pig"), ("s1", "no_lpips"), ("s1", "budget"), ("s2", "budget")]
    planned = plan_fits(preset, runs, results, ms_per_iteration=20.0, ms_per_iteration_lpips=300.0)
    got = {(p.subject, p.variant): (p.state, p.lpips, p.iterations, p.remaining_s) for p in planned}
    assert got == {
        ("s1", "pig"): ("done", True, 1000, 0.0),
        ("s2", "pig"): ("resumes at 250", True, 1000, pytest.approx(750 * 0.3)),
        ("s1", "no_lpips"): ("to run", False, 400, pytest.approx(400 * 0.02)),
        ("s1", "budget"): ("to run", False, 1000, pytest.approx(5.0)),  # 1000 x 20 ms = 20 s > the 5 s budget
        ("s2", "budget"): ("resumes at 10", False, 1000, pytest.approx(1.0)),  # 4 of its 5 s spent
    }
    text = format_plan(planned, gpus=2)
    total_h = (750 * 0.3 + 400 * 0.02 + 5.0 + 1.0) / 3600
    assert f"4 of 5 fits to run: {total_h:.2f} GPU-hours" in text
    assert f"on 2 GPU(s), one fit each at a time: about {makespan_s([225, 8, 5, 1], 2) / 3600:.2f} h wall" in text
    with pytest.raises(ValueError, match="positive"):
        plan_fits(preset, runs, results, ms_per_iteration=0.0)
    (results / "s2" / "pig" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"s2/pig/checkpoint.pt: not a readable fit checkpoint"):
        plan_fits(preset, runs, results)
    torch.save({"iteration": 3}, results / "s2" / "pig" / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"s2/pig/checkpoint.pt: expected a fit checkpoint with `iteration`"):
        plan_fits(preset, runs, results)


@pytest.fixture(scope="module")
def fresh(tmp_path_factory) -> Path:
    """A workflow folder with the repository's config and the test preset, nothing generated."""
    work = tmp_path_factory.mktemp("fresh") / "work dir"
    _workflow_config(work, "synthetic")
    return work


def test_all_tables_of_the_synthetic_dataset_with_the_paper_runs(fresh):
    # subject00 carries every table: the full method, 4 structural ablations, 3 noise levels = 8 fits.
    jobs = scheduled(fresh, "all_tables")
    assert jobs == {"generate_capture": 1, "preprocess_capture": 1, "fit_avatar": 1, "render_split": 2,
                    "evaluate": 4, "make_tables": 1, "make_table": 3, "all_tables": 1}
    jobs = job_counts(snakemake_run(fresh, "all_tables", "--dry-run", "--quiet", "rules", *PAPER_TABLES))
    assert {rule: jobs[rule] for rule in ("fit_avatar", "render_split", "make_table")} == {
        "fit_avatar": 8, "render_split": 16, "make_table": 3}


def test_plan_of_the_paper_tables_on_dna_needs_no_data(fresh):
    """The paper's DNA-Rendering runs (3 main subjects, 4 ablations + the full method on 0102, 3 noise levels + the
    full method on 0012), planned before any data is there; the `paper` preset's 100k iterations with LPIPS."""
    snakemake_run(fresh, "plan_tables", "--cores", "1", *PAPER_TABLES, "--config", "preset=paper", "dataset=dna",
                  "ms_per_iteration_lpips=500")
    output = (fresh / "results" / "tables" / "logs" / "plan_dna.log").read_text()  # also on the terminal
    expected = [("0165_08", "pig"), ("0166_04", "pig"), ("0206_04", "pig"), ("0102", "pig"), ("0102", "no_precond"),
                ("0102", "fixed_anchors"), ("0102", "no_offsets"), ("0102", "single_mlp"), ("0012", "pig"),
                ("0012", "noise_0.1"), ("0012", "noise_0.2"), ("0012", "noise_0.25")]
    rows = [line.split() for line in output.splitlines() if line.split()[:2] in [list(run) for run in expected]]
    assert [tuple(row[:2]) for row in rows] == expected
    assert all(row[2:5] == ["100000", "on", "500"] for row in rows)
    assert f"12 of 12 fits to run: {12 * 100_000 * 0.5 / 3600:.2f} GPU-hours" in output


def _hold(path: Path):
    fd = os.open(path, os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)
    return fd


# A safety net only: each wait below ends on what the code writes or on the process's exit, never on a deadline that a
# loaded machine could miss. (The launcher's wait for a slot, a sleep, ends at once on SIGINT, load or not.)
SAFETY_S = 900


def _wait_for(condition, process: subprocess.Popen, output: Path) -> None:
    """Returns once `condition()` holds; fails, showing the output, if `process` ends first."""
    deadline = time.monotonic() + SAFETY_S
    while not condition():
        assert process.poll() is None and time.monotonic() < deadline, output.read_text()[-3000:]
        time.sleep(0.1)


def test_a_killed_run_resumes_without_redoing_finished_fits(recorded, tmp_path, monkeypatch):
    """all_tables with a second variant: its fit starts (and waits for the one stand-in GPU, which the test holds),
    Snakemake is interrupted; the next run schedules that fit again, with no manual step, and not the finished one."""
    work = tmp_path / "work dir"
    shutil.copytree(recorded, work, symlinks=True)
    edit_yaml(work / PRESET, lambda p: p["resources"].update(fit_avatar={"gpu": 1}))
    edit_yaml(work / "config" / "config.yaml", lambda c: c.update(variants=["pig", "no_offsets"]))
    monkeypatch.setenv(DEVICES_ENV, "g0")
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "locks"))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    (tmp_path / "locks").mkdir()
    held = _hold(lock_path(tmp_path / "locks", "g0"))
    log = work / "results" / "thuman4" / SUBJECT / "no_offsets" / "logs" / "fit.log"
    output = tmp_path / "killed.out"
    argv = [sys.executable, "-m", "snakemake", "all_tables", "--cores", "2", "--snakefile", str(REPO / "Snakefile"),
            "--directory", str(work)]
    # A process group of its own, as a terminal's foreground job: Ctrl-C reaches Snakemake and its jobs. A fresh
    # interpreter rather than a fork of this (threaded) test process.
    with open(output, "w") as stream:
        run = subprocess.Popen(argv, stdout=stream, stderr=subprocess.STDOUT, process_group=0)
    try:
        _wait_for(lambda: log.exists() and "waiting for 1 free GPU slot" in log.read_text(), run, output)
        os.killpg(run.pid, signal.SIGINT)  # Ctrl-C
        run.wait(timeout=SAFETY_S)
        assert run.returncode != 0, output.read_text()[-3000:]
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait()
        os.close(held)  # only now is the slot free: a job that stopped before this stopped while it waited
    assert "fit_avatar: GPU slot(s) held" not in log.read_text()  # the job stopped while it waited
    assert not (work / "results" / "thuman4" / SUBJECT / "no_offsets" / "avatar.pt").exists()
    assert scheduled(work, "all_tables") == {"fit_avatar": 1, "render_split": 2, "evaluate": 4, "make_tables": 1,
                                             "all_tables": 1}
    output = snakemake_run(work, "all_tables", "--dry-run", "--printshellcmds")
    fits = [line for line in output.splitlines() if " -m pig fit " in line]
    assert len(fits) == 1 and "--variant no_offsets" in fits[0]
