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

from pig.avatar.plan import (REFERENCE_MEGAPIXELS, Protocol, ProtocolRates, SplitSize, format_plan, makespan_s,
                             plan_fits, plan_tables, preprocess_seconds, split_seconds)
from pig.config import load_preset
from pig.doctor import load_dataset, nominal_protocol
from pig.gpu_slots import DEVICES_ENV, LOCK_DIR_ENV, lock_path

PAPER_TABLES = ("--configfile", str(REPO / "config" / "paper_tables.yaml"))


def fits_alone(durations: list[float]) -> list[tuple[float, list[float]]]:
    return [(duration, []) for duration in durations]


def test_makespan_of_fits_alone_longest_first_on_the_device_that_frees_first():
    # By hand: 3 and 3 on the two devices, then 2 on each, the last 2 on either: 3 + 2 + 2 = 7 (the optimum, 6, puts
    # 3 + 3 on one; longest-first does not find it).
    assert makespan_s(fits_alone([2, 3, 2, 3, 2]), 2) == 7
    assert makespan_s(fits_alone([2, 3, 2, 3, 2]), 1) == 12
    assert makespan_s(fits_alone([2, 3, 2, 3, 2]), 8) == 3
    assert makespan_s([], 4) == 0
    rng = random.Random(0)
    for _ in range(50):  # Graham's bounds for list scheduling, against the exhaustive optimum
        jobs, gpus = [rng.uniform(0.1, 5) for _ in range(rng.randint(1, 7))], rng.randint(1, 3)
        best = min(max(sum(j for j, d in zip(jobs, assign) if d == g) for g in range(gpus))
                   for assign in itertools.product(range(gpus), repeat=len(jobs)))
        assert best - 1e-9 <= makespan_s(fits_alone(jobs), gpus) <= best * (4 / 3 - 1 / (3 * gpus)) + 1e-9
    with pytest.raises(ValueError, match="at least one GPU"):
        makespan_s(fits_alone([1.0]), 0)


def test_makespan_of_fits_alone_closed_forms_and_the_optimum_with_few_jobs():
    rng = random.Random(1)
    for _ in range(50):
        jobs = [rng.uniform(0.1, 5) for _ in range(rng.randint(1, 6))]
        assert makespan_s(fits_alone(jobs), 1) == pytest.approx(sum(jobs))  # one GPU: one after the other
        assert makespan_s(fits_alone(jobs), len(jobs) + rng.randint(0, 3)) == max(jobs)  # a GPU each: the longest
        # One job more than GPUs: some GPU runs two, at best the two shortest, so the optimum is
        # max(longest, sum of the two shortest), which longest-first reaches; checked against every assignment.
        gpus = len(jobs) - 1
        if gpus:
            best = min(max(sum(j for j, d in zip(jobs, assign) if d == g) for g in range(gpus))
                       for assign in itertools.product(range(gpus), repeat=len(jobs)))
            assert makespan_s(fits_alone(jobs), gpus) == pytest.approx(best)
            assert best == pytest.approx(max(max(jobs), sum(sorted(jobs)[:2])))


def test_makespan_runs_every_fit_before_the_splits_as_the_workflow_does():
    # Three fits of 10 s with one 3-s split each, 2 GPUs. Fits a and b at 0-10, fit c at 10-20 on the first device
    # to free; the splits of a and b at 10-13 and 13-16 on the other; c's at 20-23. Each fit with its split as one
    # job (the model before run44) would end at 26: a and b's splits before c's fit.
    assert makespan_s([(10, [3]), (10, [3]), (10, [3])], 2) == 23
    # One GPU: everything one after the other; a GPU for each fit: the fit, then its splits side by side.
    assert makespan_s([(10, [3, 2]), (5, [4])], 1) == 24
    assert makespan_s([(10, [3, 2]), (5, [4])], 4) == 13
    # A finished fit's splits start at once on a device no fit needs; else after the fits have started.
    assert makespan_s([(0, [4]), (6, [1])], 2) == 7
    assert makespan_s([(0, [4]), (6, [1])], 1) == 11
    rng = random.Random(2)
    for _ in range(50):  # bounds: at least the busiest chain and the work over the devices; at most the work
        fits = [(rng.uniform(0, 5), [rng.uniform(0.1, 2) for _ in range(rng.randint(0, 2))])
                for _ in range(rng.randint(1, 6))]
        gpus = rng.randint(1, 4)
        work = sum(f + sum(s) for f, s in fits)
        longest_chain = max(f + max(s, default=0) for f, s in fits)
        got = makespan_s(fits, gpus)
        assert max(longest_chain, work / gpus) - 1e-9 <= got <= work + 1e-9
        assert makespan_s(fits, 1) == pytest.approx(work)


def test_a_split_costs_its_frames_views_pixels_and_one_pass():
    rates = ProtocolRates(render_ms_per_frame=20.0, render_ms_per_view=4.0, evaluate_s_per_split=10.0,
                          evaluate_ms_per_view=8.0, preprocess_views_per_s=50.0)
    size = SplitSize(frames=100, views=600, megapixels=2 * REFERENCE_MEGAPIXELS)  # twice the reference's pixels
    # By hand, at 3 LODs: render 3 x (100 x 20 ms + 600 x 2 x 4 ms) = 20.4 s; evaluate 10 s + 3 x 600 x 2 x 8 ms.
    assert split_seconds(size, 3, rates) == pytest.approx(20.4 + 10 + 28.8)
    assert split_seconds(size, 3, rates, rendered=True) == pytest.approx(10 + 28.8)
    with pytest.raises(ValueError, match="positive"):
        ProtocolRates(render_ms_per_view=0.0)


def test_plan_adds_render_and_evaluate_per_split_left_and_schedules_fit_and_splits(tmp_path):
    preset = load_preset("test")
    preset["fit"].update(iterations=1000, weight_lpips=0.0)
    preset["avatar"]["levels"] = 2
    preset["variants"]["one_level"] = {"avatar": {"levels": 1}}
    protocol = Protocol({"novel_view": SplitSize(10, 20, REFERENCE_MEGAPIXELS),
                         "novel_pose": SplitSize(5, 40, REFERENCE_MEGAPIXELS / 2)}, capture_views=300,
                        raw_megapixels=4 * REFERENCE_MEGAPIXELS)
    rates = ProtocolRates(100.0, 50.0, 3.0, 25.0, 10.0)
    results = tmp_path / "results"
    done = results / "a" / "pig"  # fit and both splits done
    (done / "metrics").mkdir(parents=True)
    for name in ("avatar.pt", "metrics/novel_view.json", "metrics/novel_pose.json"):
        (done / name).write_bytes(b"")
    rendered = results / "b" / "pig"  # fit done, novel_pose rendered, nothing scored
    (rendered / "renders" / "novel_pose").mkdir(parents=True)
    (rendered / "avatar.pt").write_bytes(b"")
    (results / "a" / "capture").mkdir(parents=True)
    (results / "a" / "capture" / "report.json").write_text("{}")
    runs = [("a", "pig"), ("b", "pig"), ("b", "one_level")]
    planned = plan_fits(preset, runs, results, ms_per_iteration=10.0, protocol=protocol, rates=rates)
    # By hand. novel_view at L LODs: render L (10 x 0.1 + 20 x 0.05) = 2L s, evaluate 3 + L x 20 x 0.025 = 3 + 0.5L;
    # novel_pose (half the pixels): render L (5 x 0.1 + 40 x 0.5 x 0.05) = 1.5L, evaluate 3 + L x 40 x 0.5 x 0.025.
    nv = {2: 4 + 4, 1: 2 + 3.5}
    np_render, np_eval = {2: 3.0, 1: 1.5}, {2: 4.0, 1: 3.5}
    got = {(p.subject, p.variant): (p.levels, p.fit_s, p.splits_left, p.split_s) for p in planned}
    assert got == {("a", "pig"): (2, 0.0, [], {}),
                   ("b", "pig"): (2, 0.0, ["novel_view", "novel_pose"],
                                  {"novel_view": pytest.approx(nv[2]), "novel_pose": pytest.approx(np_eval[2])}),
                   ("b", "one_level"): (1, pytest.approx(10.0), ["novel_view", "novel_pose"],
                                        {"novel_view": pytest.approx(nv[1]),
                                         "novel_pose": pytest.approx(np_render[1] + np_eval[1])})}
    assert planned[1].protocol_s == pytest.approx(nv[2] + np_eval[2])
    work = nv[2] + np_eval[2] + 10.0 + nv[1] + np_render[1] + np_eval[1]  # 12 s left of b/pig, 20.5 of b/one_level
    text = format_plan(planned, [1, 2, 5])
    assert "1 of 3 fits to run, 4 of 6 held-out splits to render and evaluate" in text
    assert f"GPU-hours: fits {10 / 3600:.2f}, render + evaluate {(work - 10) / 3600:.2f}, total " \
           f"{work / 3600:.2f}" in text
    # By hand, 2 GPUs: one_level's fit on one (0-10); b/pig's splits, 8 and 4 s, on the other (0-8, 8-12);
    # one_level's, 5.5 and 5 s, from 10 on the first to free: 10-15.5 and 12-17. 5 GPUs: 10 + 5.5.
    hours = {1: work, 2: 17.0, 5: 15.5}
    assert [line.strip() for line in text.splitlines() if line.startswith("  on ")] == [
        f"on {n} GPU(s): {hours[n] / 3600:.2f} h" for n in (1, 2, 5)]
    # Preprocess: subject b only (a's capture is written), 300 views of 4x the reference's pixels at 10 a second.
    assert preprocess_seconds(["a", "b", "b"], results, protocol, rates) == (1, pytest.approx(300 * 4 / 10))
    # Without the dataset's sizes: the fits alone, said so.
    text = format_plan(plan_fits(preset, runs, results, ms_per_iteration=10.0), [2])
    assert "render + evaluate not counted" in text and f"on 2 GPU(s): {10 / 3600:.2f} h" in text


def test_plan_with_everything_done_or_nothing_to_plan(tmp_path):
    preset = load_preset("test")
    folder = tmp_path / "s" / "pig"
    (folder / "metrics").mkdir(parents=True)
    for name in ("avatar.pt", "metrics/novel_view.json", "metrics/novel_pose.json"):
        (folder / name).write_bytes(b"")
    (tmp_path / "s" / "capture").mkdir()
    (tmp_path / "s" / "capture" / "report.json").write_text("{}")
    protocol = Protocol({"novel_view": SplitSize(1, 1, 1.0), "novel_pose": SplitSize(1, 1, 1.0)}, 2, 1.0)
    text = plan_tables(preset, [("s", "pig")], tmp_path, 10.0, 20.0, protocol, ProtocolRates(), [1, 8])
    assert "0 of 1 fits to run, 0 of 2 held-out splits" in text
    assert "total 0.00" in text and "on 8 GPU(s): 0.00 h" in text and "0 subject(s) to preprocess, 0.00 h" in text
    assert "on 1 GPU(s): 0.00 h" in format_plan([], [1])


def test_nominal_protocols_of_thuman4_and_dna_as_formats_md_gives_them():
    paper = load_preset("paper")
    thuman4 = nominal_protocol(paper, load_dataset("thuman4")[0])
    # 24 cameras x 2500 frames at 1330 x 1150: cam23 on frames 0..1999, all 24 on 2000..2499.
    assert thuman4 == Protocol({"novel_view": SplitSize(2000, 2000, pytest.approx(1.5295)),
                                "novel_pose": SplitSize(500, 12000, pytest.approx(1.5295))}, 60000,
                               pytest.approx(1.5295))
    dna = nominal_protocol(paper, load_dataset("dna")[0])
    # 48 cameras at 2448 x 2048 and 12 at 4096 x 3000, halved by the paper preset; 225 frames, the last 45 novel
    # pose: novel view on cameras 48..59 (2048 x 1500) on 180 frames, novel pose on all 60.
    big, small = 2048 * 1500 / 1e6, 1224 * 1024 / 1e6
    raw = (48 * 2448 * 2048 + 12 * 4096 * 3000) / 60 / 1e6
    assert dna == Protocol({"novel_view": SplitSize(180, 2160, pytest.approx(big)),
                            "novel_pose": SplitSize(45, 2700, pytest.approx((48 * small + 12 * big) / 60))}, 13500,
                           pytest.approx(raw))


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
    got = {(p.subject, p.variant): (p.state, p.lpips, p.iterations, p.fit_s) for p in planned}
    assert got == {
        ("s1", "pig"): ("done", True, 1000, 0.0),
        ("s2", "pig"): ("resumes at 250", True, 1000, pytest.approx(750 * 0.3)),
        ("s1", "no_lpips"): ("to run", False, 400, pytest.approx(400 * 0.02)),
        ("s1", "budget"): ("to run", False, 1000, pytest.approx(5.0)),  # 1000 x 20 ms = 20 s > the 5 s budget
        ("s2", "budget"): ("resumes at 10", False, 1000, pytest.approx(1.0)),  # 4 of its 5 s spent
    }
    text = format_plan(planned, gpus=[2])
    total_h = (750 * 0.3 + 400 * 0.02 + 5.0 + 1.0) / 3600
    assert "4 of 5 fits to run" in text and f"GPU-hours: fits {total_h:.2f}; render + evaluate not counted" in text
    assert f"on 2 GPU(s): {makespan_s(fits_alone([225, 8, 5, 1]), 2) / 3600:.2f} h" in text
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
                    "evaluate": 2, "make_tables": 1, "make_table": 3, "all_tables": 1}
    jobs = job_counts(snakemake_run(fresh, "all_tables", "--dry-run", "--quiet", "rules", *PAPER_TABLES))
    assert {rule: jobs[rule] for rule in ("fit_avatar", "render_split", "make_table")} == {
        "fit_avatar": 8, "render_split": 16, "make_table": 3}


def test_plan_of_the_paper_tables_on_dna_needs_no_data(fresh):
    """The paper's DNA-Rendering runs (3 main subjects, 4 ablations + the full method on 0102, 3 noise levels + the
    full method on 0012), planned before any data is there; the `paper` preset's 100k iterations with LPIPS."""
    snakemake_run(fresh, "plan_tables", "--cores", "1", *PAPER_TABLES, "--config", "preset=paper", "dataset=dna",
                  "ms_per_iteration_lpips=500", "plan_gpus=[1,8]", "plan_rates={evaluate_s_per_split: 60}")
    output = (fresh / "results" / "tables" / "logs" / "plan_dna.log").read_text()  # also on the terminal
    expected = [("0165_08", "pig"), ("0166_04", "pig"), ("0206_04", "pig"), ("0102", "pig"), ("0102", "no_precond"),
                ("0102", "fixed_anchors"), ("0102", "no_offsets"), ("0102", "single_mlp"), ("0012", "pig"),
                ("0012", "noise_0.1"), ("0012", "noise_0.2"), ("0012", "noise_0.25")]
    rows = [line.split() for line in output.splitlines() if line.split()[:2] in [list(run) for run in expected]]
    assert [tuple(row[:2]) for row in rows] == expected
    assert all(row[2:6] == ["100000", "on", "500.0", "4"] for row in rows)
    fits_h = 12 * 100_000 * 0.5 / 3600
    # The protocol's render and evaluate at the default rates but for the 60 s a pass set in plan_rates.
    protocol = nominal_protocol(load_preset("paper"), load_dataset("dna")[0])
    rates = ProtocolRates(evaluate_s_per_split=60.0)
    split_s = [split_seconds(size, 4, rates) for size in protocol.splits.values()]
    per_fit_s = sum(split_s)
    assert f"GPU-hours: fits {fits_h:.2f}, render + evaluate {12 * per_fit_s / 3600:.2f}" in output
    assert f"on 1 GPU(s): {(fits_h + 12 * per_fit_s / 3600):.2f} h" in output
    # 8 GPUs: 8 fits, then 4 (two rounds of 50,000 s); the first 8 fits' 16 splits on the 4 free devices meanwhile
    # (2 x per_fit_s each, far less than a fit), the last 4 fits' 8 splits on the 8 devices at once.
    assert f"on 8 GPU(s): {(2 * 100_000 * 0.5 + max(split_s)) / 3600:.2f} h" in output


def _hold(path: Path):
    fd = os.open(path, os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)
    return fd


def workflow_waiting_for_a_gpu(recorded: Path, tmp_path: Path, monkeypatch) -> tuple[Path, int, Path]:
    """The recorded workflow copied to `tmp_path`, with a second variant whose fit asks for a GPU, one stand-in
    device whose slot this test holds: (the work folder, the held lock's fd, that fit's log)."""
    work = tmp_path / "work dir"
    shutil.copytree(recorded, work, symlinks=True)
    edit_yaml(work / PRESET, lambda p: p["resources"].update(fit_avatar={"gpu": 1}))
    edit_yaml(work / "config" / "config.yaml", lambda c: c.update(variants=["pig", "no_offsets"]))
    monkeypatch.setenv(DEVICES_ENV, "g0")
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "locks"))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    (tmp_path / "locks").mkdir()
    held = _hold(lock_path(tmp_path / "locks", "g0"))
    return work, held, work / "results" / "thuman4" / SUBJECT / "no_offsets" / "logs" / "fit.log"


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
    work, held, log = workflow_waiting_for_a_gpu(recorded, tmp_path, monkeypatch)
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
    assert scheduled(work, "all_tables") == {"fit_avatar": 1, "render_split": 2, "evaluate": 2, "make_tables": 1,
                                             "all_tables": 1}
    output = snakemake_run(work, "all_tables", "--dry-run", "--printshellcmds")
    fits = [line for line in output.splitlines() if " -m pig fit " in line]
    assert len(fits) == 1 and "--variant no_offsets" in fits[0]
