"""Local GPU slots: one per device, each held through an exclusive `fcntl.flock` on a per-device lock file.

`python -m pig.gpu_slots --gpus N --preset NAME -- COMMAND...` waits until N slots are free, sets
CUDA_VISIBLE_DEVICES to their devices and replaces itself with COMMAND, which inherits the locks: the operating
system releases them when that process ends, however it ends, so a killed job never leaves a device marked busy.
It does so only where the workflow's local run marked the environment (PIG_GPU_SLOTS=1; workflow/rules/common.smk)
and N > 0; elsewhere (a Slurm job, a command run by hand, a job without a GPU) it runs COMMAND unchanged. No torch.
"""
from __future__ import annotations

import argparse
import datetime
import fcntl
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pig.job_lifetime import end_with_parent

# Set by the workflow on a local run: only then does the launcher hand out slots.
LOCAL_SLOTS_ENV = "PIG_GPU_SLOTS"
# A stand-in device list ("0,1,2"; empty: none) that replaces what the machine has (tests; or a subset of its GPUs).
DEVICES_ENV = "PIG_GPU_DEVICES"
# Where the lock files live; by default one folder per user in the temporary folder, shared by all its workflows.
LOCK_DIR_ENV = "PIG_GPU_LOCK_DIR"
POLL_S = 1.0  # how often a waiting job looks for a free slot again
# `nvidia-smi -L` answers in well under a second; a hung driver can hold it for minutes, and every Snakemake start
# asks it (workflow/rules/common.smk), as does each GPU job's launcher.
NVIDIA_SMI_TIMEOUT_S = 5.0


def machine_devices(timeout_s: float = NVIDIA_SMI_TIMEOUT_S) -> tuple[list[str], str]:
    """(device ids for CUDA_VISIBLE_DEVICES, where they came from): PIG_GPU_DEVICES, else CUDA_VISIBLE_DEVICES (the
    devices this process may use), else one per GPU that `nvidia-smi -L` lists, else per /proc/driver/nvidia/gpus/
    entry; none without a GPU. An `nvidia-smi` that gives no answer within `timeout_s` seconds (a hung driver) is
    left behind, said so on stderr, and the /proc entries count."""
    for name in (DEVICES_ENV, "CUDA_VISIBLE_DEVICES"):
        if name in os.environ:
            ids = [part.strip() for part in os.environ[name].split(",") if part.strip()]
            # CUDA stops at the first invalid id: "-1" (a common way to hide every GPU) leaves none.
            valid = ids[: next((i for i, dev in enumerate(ids) if dev.startswith("-")), len(ids))]
            return valid, f"{name}={os.environ[name]!r}"
    proc = Path("/proc/driver/nvidia/gpus")
    hung = None
    try:
        smi = subprocess.Popen(["nvidia-smi", "-L"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    except OSError:
        smi = None
    if smi is not None:
        try:
            listing, _ = smi.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            smi.kill()
            smi.stdout.close()
            try:  # reaped if it dies; one stuck in the driver ends only when the driver lets it go: not waited for
                smi.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                pass
            hung = f"nvidia-smi -L gave no answer in {timeout_s:g} s"
            print(f"{hung} (a hung driver?): GPUs counted from {proc} instead; set {DEVICES_ENV}=0,1,... to name "
                  "them and skip nvidia-smi", file=sys.stderr, flush=True)
        else:
            if smi.returncode == 0:
                count = sum(1 for line in listing.splitlines() if line.startswith("GPU "))
                return [str(i) for i in range(count)], "nvidia-smi -L"
    count = len(list(proc.iterdir())) if proc.is_dir() else 0
    if count:
        return [str(i) for i in range(count)], f"{proc} ({hung or 'nvidia-smi not usable'})"
    return [], "no NVIDIA GPU found" + (f" ({hung})" if hung else "")


def lock_dir() -> Path:
    """The folder of the slots' lock files (created on first use)."""
    folder = os.environ.get(LOCK_DIR_ENV) or Path(tempfile.gettempdir()) / f"pig-gpu-slots-{os.getuid()}"
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def lock_path(folder: Path, device: str) -> Path:
    """The lock file of one device (ids such as MIG-.../1/0 made safe as a file name)."""
    return folder / f"gpu-{re.sub(r'[^A-Za-z0-9_.-]', '_', device)}.lock"


def try_acquire(devices: list[str], count: int, folder: Path) -> list[tuple[str, int]] | None:
    """`count` free slots as (device, locked fd), or None (nothing held) when fewer are free.

    All or none: a job never holds some slots while it waits for others, so two jobs cannot wait on each other.
    """
    held = []
    for device in devices:
        fd = os.open(lock_path(folder, device), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        held.append((device, fd))
        if len(held) == count:
            return held
    for _, fd in held:
        os.close(fd)  # closing the last descriptor of the open file releases its lock
    return None


def acquire(devices: list[str], count: int, folder: Path, poll_s: float = POLL_S, log=sys.stderr):
    """Waits until `count` slots are free and returns them as (device, locked fd); says once that it waits."""
    waited = False
    while (held := try_acquire(devices, count, folder)) is None:
        if not waited:
            print(f"{_now()} waiting for {count} free GPU slot(s) of {len(devices)} (devices {','.join(devices)}; "
                  f"locks in {folder})", file=log, flush=True)
            waited = True
        time.sleep(poll_s)
    for _, fd in held:  # who holds the slot, for a person looking at the lock file
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    return held


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")


def main(argv: list[str] | None = None) -> int:
    end_with_parent()  # a job's shell killed while this waits for a slot: no orphan takes the slot later
    parser = argparse.ArgumentParser(prog="python -m pig.gpu_slots", description=__doc__.split("\n\n")[0])
    parser.add_argument("--gpus", type=int, default=1, help="slots (devices) the command needs (default 1)")
    parser.add_argument("--preset", default="?", help="the compute preset that asks for them (named in messages)")
    parser.add_argument("--rule", default="job", help="the workflow rule (named in messages)")
    parser.add_argument("--poll", type=float, default=POLL_S, help="seconds between looks for a free slot")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND [ARGS...]")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command or args.gpus < 0:
        parser.error("expected --gpus N (N >= 0) and a command after --")
    if args.gpus == 0 or os.environ.get(LOCAL_SLOTS_ENV) != "1":
        return run(command, os.environ, args.rule)
    devices, source = machine_devices()
    if args.gpus > len(devices):
        print(f"{args.rule}: the compute preset {args.preset!r} asks for {args.gpus} GPU(s) per job and this machine "
              f"has {len(devices)} ({source}); not run on the CPU. Use a preset whose `resources:` give this rule "
              "no GPU (e.g. --config preset=cpu-demo) or a machine with GPUs.", file=sys.stderr, flush=True)
        return 2
    try:
        held = acquire(devices, args.gpus, lock_dir(), args.poll)
    except KeyboardInterrupt:
        print(f"{_now()} {args.rule}: interrupted while waiting for a GPU slot", file=sys.stderr)
        return 130
    for _, fd in held:
        os.set_inheritable(fd, True)  # the command holds the locks from here on
    visible = ",".join(device for device, _ in held)
    print(f"{_now()} {args.rule}: GPU slot(s) held, CUDA_VISIBLE_DEVICES={visible} (of {','.join(devices)}, "
          f"from {source}); pid {os.getpid()}", file=sys.stderr, flush=True)
    return run(command, dict(os.environ, CUDA_VISIBLE_DEVICES=visible), args.rule)


def run(command: list[str], env, rule: str) -> int:
    """Replaces this process with `command` (same pid, open locks kept); returns only when it cannot start."""
    try:
        os.execvpe(command[0], command, env)
    except OSError as err:
        print(f"{rule}: cannot run {command[0]!r}: {err}", file=sys.stderr)
        return 127


if __name__ == "__main__":
    sys.exit(main())
