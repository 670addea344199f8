"""How long Snakemake takes to stop on Ctrl-C while a job waits for a GPU slot, idle and beside busy processes.

    python benchmarks/ctrl_c_stop.py [--busy 0 6] [--repeats 3]

A one-rule workflow in a temporary folder whose job has the shape of the fit rule's (`python -m pig.gpu_slots --gpus 1
-- COMMAND 2>&1 | tee LOG`) waits for the one stand-in GPU, whose lock this script holds. Snakemake runs in a process
group of its own, as a terminal's foreground job; once the job's log says it waits, the group gets SIGINT (Ctrl-C).
Prints, per number of busy processes (endless loops beside it), the seconds from the SIGINT until the slot launcher
ended and until Snakemake exited. Prints Markdown.
"""
from __future__ import annotations

import argparse
import fcntl
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SNAKEFILE = '''rule wait_for_slot:
    output:
        "done.txt",
    log:
        "wait.log",
    shell:
        "python -m pig.gpu_slots --gpus 1 --rule wait_for_slot -- sleep 1000 2>&1 | tee {log}"
'''


def one_run(folder: Path) -> tuple[float, float]:
    """(seconds until the launcher ended, seconds until Snakemake exited) after the SIGINT."""
    (folder / "Snakefile").write_text(SNAKEFILE)
    locks = folder / "locks"
    locks.mkdir()
    held = os.open(locks / "gpu-g0.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(held, fcntl.LOCK_EX)
    env = dict(os.environ, PIG_GPU_SLOTS="1", PIG_GPU_DEVICES="g0", PIG_GPU_LOCK_DIR=str(locks),
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    with open(folder / "snakemake.out", "w") as out:
        run = subprocess.Popen([sys.executable, "-m", "snakemake", "--cores", "1", "--directory", str(folder),
                                "--snakefile", str(folder / "Snakefile")], stdout=out, stderr=subprocess.STDOUT,
                               env=env, process_group=0)
    try:
        log = folder / "wait.log"
        while not (log.exists() and "waiting for 1 free GPU slot" in log.read_text()):
            if run.poll() is not None:
                raise RuntimeError((folder / "snakemake.out").read_text()[-2000:])
            time.sleep(0.05)
        launcher = next(int(pid) for pid in os.listdir("/proc") if pid.isdigit() and _is_launcher(int(pid), folder))
        start = time.monotonic()
        os.killpg(run.pid, signal.SIGINT)
        launcher_s = exited_s = None
        while launcher_s is None or exited_s is None:
            now = time.monotonic() - start
            if launcher_s is None and not _alive(launcher):
                launcher_s = now
            if exited_s is None and run.poll() is not None:
                exited_s = now
            time.sleep(0.005)
        return launcher_s, exited_s
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait()
        os.close(held)


def _is_launcher(pid: int, folder: Path) -> bool:
    try:
        words = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        return words[1:3] == [b"-m", b"pig.gpu_slots"] and os.readlink(f"/proc/{pid}/cwd") == str(folder)
    except OSError:
        return False


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--busy", type=int, nargs="+", default=[0, 6], help="busy processes beside the run")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"{os.cpu_count()} CPU cores\n")
    print("| busy processes | load (1 min) | launcher ended after SIGINT (s) | Snakemake exited after SIGINT (s) |")
    print("|---|---|---|---|")
    for busy in args.busy:
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
        try:
            time.sleep(2 if busy else 0)
            results = []
            for _ in range(args.repeats):
                with tempfile.TemporaryDirectory() as folder:
                    results.append(one_run(Path(folder).resolve()))
            load = os.getloadavg()[0]
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
        launcher, exited = zip(*results)
        print(f"| {busy} | {load:.1f} | median {statistics.median(launcher):.2f}, max {max(launcher):.2f} "
              f"| median {statistics.median(exited):.2f}, max {max(exited):.2f} |")


if __name__ == "__main__":
    main()
