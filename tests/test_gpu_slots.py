"""Local GPU slots (pig.gpu_slots) with a stand-in device list (PIG_GPU_DEVICES), on the CPU.

The launcher is run as the workflow runs it, `python -m pig.gpu_slots ... -- COMMAND`, with a small job that records
its device and when it held it; the intervals are then checked against each other. The workflow-level tests run
Snakemake on the fake THuman4 subject of tests/test_workflow.py, whose jobs fail on its empty files after the
launcher has (or has not) given them a device: what counts here is what the launcher wrote at the head of the logs.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest
from test_workflow import (  # noqa: F401  (recorded: the fixture, shared with tests/test_workflow.py)
    PRESET,
    SUBJECT,
    TARGET,
    edit_yaml,
    recorded,
    scheduled,
    snakemake_exit,
    snakemake_run,
)

from pig.gpu_slots import DEVICES_ENV, LOCAL_SLOTS_ENV, LOCK_DIR_ENV, machine_devices

REPO = Path(__file__).resolve().parent.parent
# A job: marks its start (device, time), waits until `need` jobs have started or the release file exists, marks
# its end. The barrier makes jobs hold their slots at the same time whatever the machine's load.
JOB = """
import json, os, sys, time
from pathlib import Path
folder, name, need = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
record = {"device": os.environ.get("CUDA_VISIBLE_DEVICES"), "start": time.time()}
(folder / f"{name}.start").write_text(json.dumps(record))
deadline = time.time() + 60
while len(list(folder.glob("*.start"))) < need and not (folder / "release").exists() and time.time() < deadline:
    time.sleep(0.02)
record["end"] = time.time()
(folder / f"{name}.json").write_text(json.dumps(record))
"""


def wait_for(condition, what: str, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(0.05)


@pytest.fixture
def slots(tmp_path, monkeypatch):
    """A launcher for jobs on stand-in devices: start(name, devices, need=1, preset=...) -> Popen."""
    (tmp_path / "job.py").write_text(JOB)
    jobs = tmp_path / "jobs"
    jobs.mkdir()
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "locks"))
    monkeypatch.setenv(LOCAL_SLOTS_ENV, "1")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    started = []

    def start(name, devices, need=1, gpus=1, preset="paper"):
        env = {**os.environ, DEVICES_ENV: devices}
        command = [sys.executable, "-m", "pig.gpu_slots", "--gpus", str(gpus), "--preset", preset, "--rule", name,
                   "--poll", "0.05", "--", sys.executable, str(tmp_path / "job.py"), str(jobs), name, str(need)]
        job = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        started.append(job)
        return job

    start.jobs = jobs
    yield start
    for job in started:
        if job.poll() is None:
            job.kill()
        job.communicate()


def finished(job, name: str, jobs: Path) -> dict:
    _, err = job.communicate(timeout=120)
    assert job.returncode == 0, err
    return json.loads((jobs / f"{name}.json").read_text())


def test_machine_devices_from_stand_in_visible_devices_and_nvidia_smi(tmp_path, monkeypatch):
    monkeypatch.setenv(DEVICES_ENV, " a, b ")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "5")
    assert machine_devices()[0] == ["a", "b"]  # the stand-in list wins
    monkeypatch.setenv(DEVICES_ENV, "")
    assert machine_devices()[0] == []
    monkeypatch.delenv(DEVICES_ENV)
    for visible, expected in (("2,3", ["2", "3"]), ("-1", []), ("1,-1,2", ["1"]), ("", [])):
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)  # CUDA stops at the first invalid id
        assert machine_devices()[0] == expected, visible
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    smi = tmp_path / "bin" / "nvidia-smi"
    smi.parent.mkdir()
    smi.write_text("#!/bin/sh\necho 'GPU 0: NVIDIA H100 (UUID: GPU-1)'\necho '  MIG 1g.10gb Device 0: (UUID: MIG-1)'\n"
                   "echo 'GPU 1: NVIDIA H100 (UUID: GPU-2)'\necho 'GPU 2: NVIDIA H100 (UUID: GPU-3)'\n")
    smi.chmod(0o755)
    monkeypatch.setenv("PATH", f"{smi.parent}{os.pathsep}{os.environ['PATH']}")
    assert machine_devices() == (["0", "1", "2"], "nvidia-smi -L")


def test_a_hung_nvidia_smi_is_left_behind_and_said_so(tmp_path, monkeypatch, capsys):
    """An nvidia-smi that never answers, whose child keeps its output open even once it is killed (as one stuck in
    the driver stays): the lookup returns at its limit, counts the devices otherwise, and says why on stderr."""
    for name in (DEVICES_ENV, "CUDA_VISIBLE_DEVICES"):
        monkeypatch.delenv(name, raising=False)
    smi = tmp_path / "bin" / "nvidia-smi"
    smi.parent.mkdir()
    smi.write_text("#!/bin/sh\nsleep 20\n")
    smi.chmod(0o755)
    monkeypatch.setenv("PATH", f"{smi.parent}{os.pathsep}{os.environ['PATH']}")
    _, source = machine_devices(timeout_s=0.5)
    assert "nvidia-smi -L gave no answer in 0.5 s" in source and source != "nvidia-smi -L"
    assert "nvidia-smi -L gave no answer in 0.5 s" in capsys.readouterr().err


def test_concurrent_jobs_never_share_a_device(slots):
    names = [f"job{i}" for i in range(7)]
    jobs = [slots(name, "g0,g1,g2", need=3) for name in names]
    records = [finished(job, name, slots.jobs) for job, name in zip(jobs, names)]
    assert {r["device"] for r in records} == {"g0", "g1", "g2"}
    for i, a in enumerate(records):
        for b in records[i + 1:]:
            if a["device"] == b["device"]:
                assert a["end"] <= b["start"] or b["end"] <= a["start"], (a, b)
    # The barrier holds three jobs at once, and a fourth never joins them.
    events = sorted([(r["start"], 1) for r in records] + [(r["end"], -1) for r in records])
    running = [sum(step for _, step in events[: i + 1]) for i in range(len(events))]
    assert max(running) == 3


def test_a_job_waits_for_a_free_slot(slots):
    first = slots("first", "g0", need=99)  # holds until released
    wait_for(lambda: (slots.jobs / "first.start").exists(), "the first job to start")
    second = slots("second", "g0", need=1)
    line = second.stderr.readline()  # the launcher says once that it waits
    assert "waiting for 1 free GPU slot(s) of 1 (devices g0" in line
    assert not (slots.jobs / "second.start").exists()
    (slots.jobs / "release").touch()
    a, b = finished(first, "first", slots.jobs), finished(second, "second", slots.jobs)
    assert b["device"] == a["device"] == "g0"
    assert b["start"] >= a["end"]


def test_a_killed_jobs_slot_is_reused(slots):
    killed = slots("killed", "g0", need=99)
    wait_for(lambda: (slots.jobs / "killed.start").exists(), "the job to start")
    waiting = slots("next", "g0", need=1)
    assert "waiting for 1 free GPU slot(s)" in waiting.stderr.readline()
    killed.send_signal(signal.SIGKILL)  # the launcher's pid: it became the job
    killed.wait()
    record = finished(waiting, "next", slots.jobs)
    assert record["device"] == "g0"
    assert not (slots.jobs / "killed.json").exists()  # it never finished


def test_no_device_refuses_a_gpu_job_naming_the_preset(slots):
    job = slots("fit_avatar", "", preset="paper")
    _, err = job.communicate(timeout=60)
    assert job.returncode == 2
    assert "fit_avatar: the compute preset 'paper' asks for 1 GPU(s) per job and this machine has 0" in err
    assert "not run on the CPU" in err
    assert not (slots.jobs / "fit_avatar.start").exists()


def test_outside_a_local_run_or_without_a_gpu_the_command_runs_unchanged(slots, monkeypatch, tmp_path):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "7")
    monkeypatch.delenv(LOCAL_SLOTS_ENV)  # a Slurm job, or the command run by hand
    assert finished(slots("slurm", "g0,g1"), "slurm", slots.jobs)["device"] == "7"
    monkeypatch.setenv(LOCAL_SLOTS_ENV, "1")
    assert finished(slots("cpu", "", gpus=0), "cpu", slots.jobs)["device"] == "7"  # the preset asks no GPU
    assert not (tmp_path / "locks").exists()


# The workflow: a local run with stand-in devices, a preset that gives render_split a GPU.
RENDERS = [f"results/thuman4/{SUBJECT}/pig/logs/render_{split}.log" for split in ("novel_view", "novel_pose")]


@pytest.fixture
def gpu_workflow(recorded, tmp_path, monkeypatch):
    work = tmp_path / "work dir"
    shutil.copytree(recorded, work, symlinks=True)
    edit_yaml(work / PRESET, lambda p: p["resources"].update(render_split={"gpu": 1}))
    assert scheduled(work) == {}  # resources are no rerun trigger
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "locks"))
    return work


def render(work: Path, *args: str, target: str = TARGET) -> tuple[int, str]:
    """Reruns the render jobs of `target` (both splits of TARGET) and nothing after them."""
    return snakemake_exit(work, target, "--forcerun", "render_split", "--until", "render_split", "--cores", "2",
                          "--keep-going", *args)


def renders(log: str) -> str:
    """The renders folder whose job writes `log`."""
    return log.replace("logs/render_", "renders/").removesuffix(".log")


def planned_gpus(work: Path, *args: str) -> int:
    """The GPU count that plan_tables is given: the `gpu` resource this run schedules with."""
    output = snakemake_run(work, "plan_tables", "--dry-run", "--printshellcmds", *args)
    return int(re.search(r"--gpus (\d+)", output).group(1))


def provided_gpus(output: str) -> int:
    """The `gpu` resource of Snakemake's "Provided resources" line (`gpu=3`, or `gpu=Resource("gpu", 3)`)."""
    found = re.search(r'Provided resources: .*\bgpu=(?:Resource\("gpu", )?(\d+)', output)
    assert found, output[-3000:]
    return int(found.group(1))


def test_local_run_gives_each_gpu_job_a_device_and_the_gpu_resource_their_count(gpu_workflow, monkeypatch):
    monkeypatch.setenv(DEVICES_ENV, "x,y,z")
    code, output = render(gpu_workflow)
    assert code == 1  # the render stage fails on the fake avatar.pt, after the launcher gave it a device
    assert provided_gpus(output) == 3
    for log in RENDERS:
        head = (gpu_workflow / log).read_text().splitlines()[0]
        assert "render_split: GPU slot(s) held, CUDA_VISIBLE_DEVICES=" in head
        assert head.split("CUDA_VISIBLE_DEVICES=")[1].split(" ")[0] in ("x", "y", "z")
    assert planned_gpus(gpu_workflow) == 3
    assert planned_gpus(gpu_workflow, "--resources", "gpu=1") == 1  # the command line's K stands


def test_no_device_refuses_gpu_jobs_at_once_and_runs_cpu_jobs(gpu_workflow, monkeypatch):
    monkeypatch.setenv(DEVICES_ENV, "")
    code, output = render(gpu_workflow)
    assert code == 1
    assert (f"the compute preset '{PRESET}' ({PRESET}) gives rules render_split a GPU and this machine has none "
            f"({DEVICES_ENV}='')") in " ".join(output.split())
    # Nothing ran: the logs are still the empty files the fixture made, the renders still there.
    assert all((gpu_workflow / log).read_text() == "" for log in RENDERS)
    assert all((gpu_workflow / renders(log)).is_dir() for log in RENDERS)
    dry = snakemake_run(gpu_workflow, TARGET, "--forcerun", "render_split", "--dry-run")  # a plan needs no GPU
    assert "rule render_split:" in dry
    edit_yaml(gpu_workflow / PRESET, lambda p: p["resources"].pop("render_split"))  # the test preset: no GPU
    render(gpu_workflow, target=renders(RENDERS[0]))
    text = (gpu_workflow / RENDERS[0]).read_text()  # ran on the CPU as before: the stage's own error, no slot
    assert "render: error:" in text and "GPU slot" not in text


def test_cluster_job_steps_take_no_slot(gpu_workflow, monkeypatch):
    """A job step on a cluster node (`--mode remote`, how Slurm's jobs run each rule) passes the command through:
    the device is Slurm's (here the stand-in says there is none, which a local run would refuse)."""
    monkeypatch.setenv(DEVICES_ENV, "")
    code, output = snakemake_exit(gpu_workflow, renders(RENDERS[0]), "--forcerun", "render_split", "--cores", "1",
                                  "--mode", "remote")
    text = (gpu_workflow / RENDERS[0]).read_text()
    assert "render: error:" in text and "GPU slot" not in text, output[-3000:]
    assert "gives rules render_split a GPU" not in output


def test_a_gpu_for_a_rule_without_a_slot_is_refused(gpu_workflow):
    """make_tables runs no launcher: a GPU there would be counted by Snakemake and used by no slot."""
    edit_yaml(gpu_workflow / PRESET, lambda p: p["resources"].update(make_tables={"gpu": 1}))
    code, output = snakemake_exit(gpu_workflow, TARGET, "--dry-run")
    assert code == 1
    assert f"{PRESET}: section 'resources' gives rule make_tables a GPU, which it does not use" in output


class _Input(str):
    """An input path as Snakemake's scheduler sees it (no temp() flag)."""

    def is_flagged(self, flag: str) -> bool:
        return False


def test_a_ready_fit_takes_the_free_gpu_before_renders_and_evaluations_with_more_input_bytes(recorded):
    """Snakemake's greedy scheduler, given each rule's job priority as the workflow sets it (a dry run's job
    records), hands the one free GPU to a waiting fit, not to a ready render or evaluation whose inputs are larger:
    the fits are the longest jobs, and starting them last left GPUs idle (run44). Without the priorities the same
    scheduler picks the evaluation (the reward falls back to input bytes), so the test tells them apart."""
    from snakemake.scheduling.greedy import Scheduler, SchedulerSettings

    output = snakemake_run(recorded, TARGET, "--dry-run", "--forceall")
    priorities: dict[str, set[int]] = {}
    for block in re.split(r"\n(?:local)?rule ", output)[1:]:
        found = re.search(r"^\s+priority: (-?\d+)$", block, re.M)
        priorities.setdefault(block.split(":", 1)[0], set()).add(int(found.group(1)) if found else 0)
    assert {"fit_avatar", "render_split", "evaluate"} <= set(priorities), output[-3000:]
    sizes = {"fit_avatar": 10**6, "render_split": 10**9, "evaluate": 10**10}  # capture < avatar < renders

    def pick(priority_of) -> str:
        jobs = [types.SimpleNamespace(rule=rule, priority=priority_of(rule), input=[_Input(rule)],
                                      scheduler_resources={"_cores": 1, "gpu": 1}) for rule in sizes]
        scheduler = Scheduler(dag=None, settings=SchedulerSettings(), logger=None)
        chosen = scheduler.select_jobs(jobs, jobs, {"_cores": 64, "gpu": 1}, {_Input(r): n for r, n in sizes.items()})
        assert len(chosen) == 1
        return chosen[0].rule

    assert all(len(values) == 1 for values in priorities.values()), priorities  # per rule, not per job
    assert pick(lambda rule: next(iter(priorities[rule]))) == "fit_avatar"
    assert pick(lambda rule: 0) == "evaluate"
