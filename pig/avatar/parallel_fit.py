"""Starting a data-parallel fit (pig.avatar.distributed): one spawned process per GPU, meeting through a store that
the starting process serves on the loopback interface; what a failed rank raised comes back here.

Its own module: it starts pig.avatar.training's fit in each process, and the fit loop imports pig.avatar.distributed.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Callable

import torch
import torch.distributed as dist
from torch.multiprocessing import ProcessExitedException, ProcessRaisedException, start_processes

from pig.avatar.distributed import GradientReducer, Parallel
from pig.avatar.fit_progress import TENSORBOARD_DIR
from pig.avatar.training import OUTPUT_FILES, fit_rank
from pig.progress import LOG_INTERVAL_S
from pig.resources import host_cores
from pig._outputs import claim_files, output_lock

FIRST_FAILURE = "first_failure"  # the store's key for the error of the first rank that failed
DEFAULT_TIMEOUT_S = 1800.0  # a collective that waits longer fails (a rank died or hangs) instead of hanging forever


@dataclass
class RankHooks:
    """What a caller (a test, a benchmark) gives each rank of a data-parallel fit: the clock the rank reads (rank
    0's decides), a callback after each iteration and a phase timer (as pig.avatar.training.fit takes them), and
    one told of the rank's gradient all-reduce (pig.avatar.distributed.GradientReducer) when it is made."""

    clock: Callable[[], float] = time.perf_counter
    on_iteration: Callable[[int], None] | None = None
    phase: Callable[[str], object] | None = None
    on_reducer: Callable[[GradientReducer], None] | None = None


def rank_threads(processes: int, cores: int) -> int:
    """Each rank's torch intra-op threads: the fit's `cores` shared out, at least 1. Torch's own default is a thread
    per core in every process, which `processes` ranks on one host oversubscribe `processes`-fold (torchrun sets 1
    thread for the same reason): each rank's host-side work (kernel launches, autograd, the view loader's staging)
    then competes for the cores with the other ranks' OpenMP threads."""
    return max(1, cores // processes)


def parse_cpu_list(text: str) -> set[int]:
    """A Linux CPU list ("0-31,64-95", as /sys's local_cpulist writes it) as a set of CPU numbers."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        if part:
            first, _, last = part.partition("-")
            cpus.update(range(int(first), int(last or first) + 1))
    return cpus


def gpu_local_cpus(index: int, sysfs: Path = Path("/sys/bus/pci/devices")) -> set[int] | None:
    """The CPUs of CUDA device `index`'s NUMA node (its PCI device's local_cpulist), or None where torch or the
    system does not tell."""
    props = torch.cuda.get_device_properties(index)
    bus = getattr(props, "pci_bus_id", None)
    if bus is None:
        return None
    path = sysfs / f"{getattr(props, 'pci_domain_id', 0):04x}:{bus:02x}:{getattr(props, 'pci_device_id', 0):02x}.0" / "local_cpulist"
    try:
        return parse_cpu_list(path.read_text()) or None
    except (OSError, ValueError):
        return None


def core_of(cpus: list[int], sysfs: Path = Path("/sys/devices/system/cpu")) -> dict[int, int]:
    """Each CPU's physical core, named by its first hardware thread (topology/thread_siblings_list); a CPU whose
    topology the system does not tell is its own core."""
    cores = {}
    for cpu in cpus:
        try:
            cores[cpu] = min(parse_cpu_list((sysfs / f"cpu{cpu}" / "topology" / "thread_siblings_list").read_text()))
        except (OSError, ValueError):
            cores[cpu] = cpu
    return cores


def rank_cpu_sets(processes: int, allowed: list[int], near: list[set[int] | None] | None = None,
                  cores: dict[int, int] | None = None) -> list[list[int]]:
    """Disjoint sets of the `allowed` CPUs, one a rank, their sizes differing by one at most; where `near` gives a
    rank's device-local CPUs (its GPU's NUMA node), its set is drawn from those first, and where `cores` names each
    CPU's physical core (core_of), a core's hardware threads go to one rank together. Each rank then launches its
    kernels from cores no other rank's threads (OpenMP's, OpenCV's, the view loader's) run on."""
    if not 1 <= processes <= len(allowed):
        raise ValueError(f"rank_cpu_sets: {processes} ranks for {len(allowed)} CPUs; pinning needs a CPU a rank at least")
    cores = cores or {}
    free = sorted(set(allowed), key=lambda cpu: (cores.get(cpu, cpu), cpu))
    base, extra = divmod(len(free), processes)
    sets = []
    for rank in range(processes):
        size = base + (rank < extra)
        local = near[rank] if near is not None and near[rank] else set()
        chosen = [cpu for cpu in free if cpu in local][:size]
        chosen += [cpu for cpu in free if cpu not in chosen][:size - len(chosen)]
        free = [cpu for cpu in free if cpu not in chosen]
        sets.append(sorted(chosen))
    return sets


def pin_rank(cpus: list[int]) -> None:
    """This process onto `cpus`, with as many torch intra-op and OpenCV threads."""
    import cv2

    os.sched_setaffinity(0, cpus)
    torch.set_num_threads(len(cpus))
    cv2.setNumThreads(len(cpus))


def fit_parallel(capture_dir: Path, output_dir: Path, preset_name: str, variant: str, processes: int, device_type: str,
                 overwrite: bool = False, progress_s: float | None = None, tensorboard: bool = False,
                 rank_hooks: Callable[[int], RankHooks] | None = None, timeout_s: float = DEFAULT_TIMEOUT_S,
                 cores: int | None = None, pin_cpus: bool = False) -> Path:
    """Fit one avatar with `processes` processes, on as many CUDA devices (`device_type` "cuda": cuda:0..N-1 of
    those visible, NCCL) or on the CPU ("cpu": gloo); returns the path of avatar.pt, which rank 0 writes.

    The processes are started here (spawned) and meet through a store that this process serves on the loopback
    interface; the first that fails stops the others, and its error is raised here. `rank_hooks(rank)` gives a rank
    its clock and callbacks (tests, benchmarks); `timeout_s` bounds a collective's wait. `cores`: the CPU threads the
    fit may use, shared out among the ranks as their torch intra-op threads (`rank_threads`; default: the cores this
    process may run on, unless OMP_NUM_THREADS is set, which torch then reads in each rank; on the CPU the preset's
    fit.cpu_threads where set, as in a one-process CPU fit). `pin_cpus`: each rank pinned to its own share of those
    cores (rank_cpu_sets, its GPU's NUMA node first), with as many torch and OpenCV threads."""
    if processes < 2:
        raise ValueError(f"fit_parallel: expected 2 or more processes, found {processes}")
    if device_type == "cuda":
        visible = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if visible < processes:
            raise ValueError(f"fit --gpus {processes}: only {visible} CUDA device(s) are visible "
                             f"(CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES', 'unset')!r})")
    elif device_type != "cpu":
        raise ValueError(f"fit_parallel: device type must be 'cuda' or 'cpu', found {device_type!r}")
    if cores is not None and cores < 1:
        raise ValueError(f"fit_parallel: cores must be at least 1, found {cores}")
    cpu_sets = None
    if pin_cpus:
        if not hasattr(os, "sched_setaffinity"):
            raise ValueError("fit_parallel: pinning the ranks to CPUs (--pin-cpus) needs Linux's CPU affinity")
        allowed = sorted(os.sched_getaffinity(0))[:cores]
        near = [gpu_local_cpus(rank) for rank in range(processes)] if device_type == "cuda" else None
        cpu_sets = rank_cpu_sets(processes, allowed, near, core_of(allowed))
    output_dir, capture_dir = Path(output_dir), Path(capture_dir)
    with output_lock(output_dir, "fit"):
        # Refused here, before any process starts; rank 0 then writes these.
        claim_files(output_dir, OUTPUT_FILES + [TENSORBOARD_DIR] * tensorboard, "fit", (capture_dir,), overwrite)
        store = dist.TCPStore("127.0.0.1", 0, processes, is_master=True, timeout=timedelta(seconds=timeout_s),
                              wait_for_workers=False)
        args = (store.port, processes, device_type, str(capture_dir), str(output_dir), preset_name, variant,
                LOG_INTERVAL_S if progress_s is None else progress_s, tensorboard, rank_hooks, timeout_s,
                None if cores is None and "OMP_NUM_THREADS" in os.environ
                else rank_threads(processes, cores or host_cores()), cpu_sets)
        try:
            start_processes(_rank_main, args=args, nprocs=processes, join=True, start_method="spawn")
        except (ProcessRaisedException, ProcessExitedException) as err:
            # The first rank that failed names the cause; the others fail after it, of the broken connection.
            if store.check([FIRST_FAILURE]):
                raise RuntimeError(f"fit {store.get(FIRST_FAILURE).decode()}") from None
            if isinstance(err, ProcessExitedException):
                raise RuntimeError(f"fit rank {err.error_index} of {processes} ended with exit code {err.exit_code}"
                                   + (f" (signal {err.signal_name})" if err.signal_name else "")) from None
            lines = [line for line in str(err).strip().splitlines() if line.strip()]
            raise RuntimeError(f"fit rank {err.error_index} of {processes}: {lines[-1] if lines else err}") from None
    return output_dir / "avatar.pt"


def _rank_main(rank: int, port: int, world: int, device_type: str, capture_dir: str, output_dir: str, preset_name: str,
               variant: str, progress_s: float, tensorboard: bool, rank_hooks, timeout_s: float,
               threads: int | None, cpu_sets: list[list[int]] | None = None) -> None:
    """One rank of fit_parallel: joins the group, fits (`threads` intra-op threads where given, or pinned to its
    `cpu_sets` entry; on the CPU the preset's fit.cpu_threads replaces them where set), leaves."""
    if cpu_sets is not None:
        pin_rank(cpu_sets[rank])
    elif threads is not None:
        torch.set_num_threads(threads)
    timeout = timedelta(seconds=timeout_s)
    store = dist.TCPStore("127.0.0.1", port, world, is_master=False, timeout=timeout)
    if device_type == "cuda":
        device = torch.device("cuda", rank)
        torch.cuda.set_device(device)
        dist.init_process_group("nccl", store=store, rank=rank, world_size=world, timeout=timeout, device_id=device)
        control = dist.new_group(backend="gloo", timeout=timeout)
    else:
        device = torch.device("cpu")
        dist.init_process_group("gloo", store=store, rank=rank, world_size=world, timeout=timeout)
        control = dist.group.WORLD
    hooks = rank_hooks(rank) if rank_hooks is not None else RankHooks()
    parallel = Parallel(rank, world, device, control, hooks.clock, hooks.on_reducer)
    try:
        fit_rank(Path(capture_dir), Path(output_dir), preset_name, variant, parallel, hooks.on_iteration, hooks.phase,
                 progress_s, tensorboard)
    except Exception as err:  # not KeyboardInterrupt: the spawned ranks get SIGINT when the starting process ends
        if store.add("failures", 1) == 1:  # before this process ends, so before another rank sees it gone
            store.set(FIRST_FAILURE, f"rank {rank} of {world}: {type(err).__name__}: {err}")
        raise  # the process ends without destroying the group: NCCL's teardown may wait on the failed collective
    dist.destroy_process_group()
