"""A workflow job's stage ends with the job's shell (pig.job_lifetime): killing the shell leaves no orphan holding the
stage's output lock or a GPU slot, so the rerun proceeds."""
from __future__ import annotations

import contextlib
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
from preset_files import write_test_preset
from test_plan import workflow_waiting_for_a_gpu
from test_workflow import REPO, recorded  # noqa: F401  (recorded: the fixture)

from pig._outputs import OutputError, output_lock

# As the workflow marks its jobs' environment (workflow/rules/common.smk; the workflow test below checks it).
JOB_ENVIRONMENT = {"PIG_WORKFLOW_JOB": "1"}
# A safety net only: each wait ends on what the code writes or on a process's end.
SAFETY_S = 300


def _until(condition, what: str, process: subprocess.Popen | None = None):
    """The first true value of `condition()`; fails naming `what` if none comes within the safety net, or if
    `process` ends first."""
    deadline = time.monotonic() + SAFETY_S
    while not (value := condition()):
        assert time.monotonic() < deadline, f"still waiting for {what}"
        assert process is None or process.poll() is None, f"{what}: the process ended first"
        time.sleep(0.1)
    return value


def _ended(pid: int) -> bool:
    """Whether process `pid` has ended (gone, or a zombie that its new parent has not reaped yet)."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _lock_free(output: Path) -> bool:
    """Whether a rerun may take `output`'s lock now (it takes and releases it)."""
    try:
        with output_lock(output, "fit"):  # the rerun's first step: refused while another fit holds it
            return True
    except OutputError:
        return False


def _stage_pid(lock: Path) -> int | None:
    try:
        text = lock.read_text().strip()
    except FileNotFoundError:
        return None
    return int(text) if text.isdigit() else None


def test_killing_a_jobs_shell_ends_its_stage_and_the_rerun_takes_the_lock(small_capture, tmp_path):
    """A fit as the workflow's rule runs it (slot launcher, `tee` to the log) under a shell that is then killed."""
    output = tmp_path / "fit"
    preset = write_test_preset(tmp_path, iterations=1_000_000, eval_every=1_000_000)  # runs until stopped
    command = (f"set -euo pipefail; python -m pig.gpu_slots --gpus 0 --rule fit_avatar -- python -m pig fit "
               f"--capture {shlex.quote(str(small_capture))} --output {shlex.quote(str(output))} "
               f"--preset {shlex.quote(preset)} --threads 1 2>&1 | tee {shlex.quote(str(tmp_path / 'fit.log'))}")
    env = dict(os.environ, **JOB_ENVIRONMENT, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO),
                                                                                       os.environ.get("PYTHONPATH")])))
    shell = subprocess.Popen(["bash", "-c", command], env=env, start_new_session=True)
    stage = None
    try:
        lock = output.with_name(f".{output.name}.lock")
        stage = _until(lambda: _stage_pid(lock), "the fit to take its output lock", shell)  # it writes its pid there
        assert psutil.Process(stage).ppid() == shell.pid  # the launcher ran the stage in its own place
        shell.kill()
        shell.wait()
        _until(lambda: _ended(stage), f"the fit (pid {stage}) to end with its shell")
        # The kernel releases the lock once the last of the fit's threads is gone, a moment after its main thread.
        _until(lambda: _lock_free(output), "the rerun to take the fit's output lock")
    finally:
        if stage is not None and not _ended(stage):
            os.kill(stage, signal.SIGKILL)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(shell.pid, signal.SIGKILL)


def test_a_workflow_job_whose_shell_is_killed_leaves_no_launcher_waiting_for_a_slot(recorded, tmp_path,  # noqa: F811
                                                                                     monkeypatch):
    """A fit job of the workflow waits for the one stand-in GPU (held by the test); its shell is killed. Its slot
    launcher ends too: an orphan would take the slot once free and run the fit beside the rerun's."""
    monkeypatch.delenv("PIG_WORKFLOW_JOB", raising=False)  # the workflow sets it, nothing else
    work, held, log = workflow_waiting_for_a_gpu(recorded, tmp_path, monkeypatch)
    argv = [sys.executable, "-m", "snakemake", "all_tables", "--cores", "2", "--snakefile", str(REPO / "Snakefile"),
            "--directory", str(work)]
    with open(tmp_path / "snakemake.out", "w") as stream:
        run = subprocess.Popen(argv, stdout=stream, stderr=subprocess.STDOUT, start_new_session=True)
    launcher = None
    try:
        _until(lambda: log.exists() and "waiting for 1 free GPU slot" in log.read_text(), "the job to wait for a slot",
               run)
        launcher = next(p for p in psutil.Process(run.pid).children(recursive=True)
                        if p.cmdline()[1:3] == ["-m", "pig.gpu_slots"])
        assert launcher.environ().get("PIG_WORKFLOW_JOB") == "1"
        shell = launcher.parent()
        assert shell.name() == "bash" and shell.ppid() == run.pid
        shell.kill()
        _until(lambda: _ended(launcher.pid), f"the slot launcher (pid {launcher.pid}) to end with its shell")
        run.wait(timeout=SAFETY_S)  # Snakemake reports the job failed and stops
    finally:
        if launcher is not None and not _ended(launcher.pid):
            launcher.kill()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(run.pid, signal.SIGKILL)
        run.wait()
        os.close(held)


def test_only_a_workflow_job_ends_with_its_parent(tmp_path):
    """Outside the workflow (JOB_ENV unset) a process outlives its killed shell, as under `nohup`; in a job it ends."""
    child = ("from pig.job_lifetime import end_with_parent; import ctypes, os, sys, time; end_with_parent(); "
             "signal = ctypes.c_int(-1); ctypes.CDLL(None).prctl(2, ctypes.byref(signal), 0, 0, 0); "  # PR_GET_PDEATHSIG
             "open(sys.argv[1], 'w').write(f'{os.getpid()} {signal.value}'); time.sleep(600)")
    for marked in (False, True):
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
        env.pop("PIG_WORKFLOW_JOB", None)
        env.update(JOB_ENVIRONMENT if marked else {})
        started = tmp_path / f"started-{marked}"
        shell = subprocess.Popen(["bash", "-c", f"{shlex.quote(sys.executable)} -c {shlex.quote(child)} "
                                                f"{shlex.quote(str(started))}; true"], env=env, start_new_session=True)
        pid = None
        try:
            pid, death_signal = _until(lambda: started.exists() and started.read_text().split(), "the child to start",
                                         shell)
            assert int(death_signal) == (signal.SIGTERM if marked else 0)
            shell.kill()
            shell.wait()
            if marked:
                _until(lambda: _ended(int(pid)), "the job's child to end with its shell")
            else:  # orphaned (its parent is another process now), and it runs on
                _until(lambda: psutil.Process(int(pid)).ppid() != shell.pid, "the child to be orphaned")
                assert not _ended(int(pid))
        finally:
            if pid is not None and not _ended(int(pid)):
                os.kill(int(pid), signal.SIGKILL)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(shell.pid, signal.SIGKILL)
