"""Where a fit iteration's time goes on the host and on its GPU, from a torch.profiler trace of a few iterations
(benchmarks/fit_multi_gpu.py --kernel-profile): the device's busy time (the union of its kernels' intervals, so that
kernels overlapping on several streams count once), NCCL's part of it, the host's time in the step's operators, the
kernels launched, and the costliest kernels; and the same by phase of the step (`summarise_phases`: the fit's
`phase(name)` windows, annotated PHASE + name, and the kernels launched inside each).

The trace is read from the profiler's Chrome-trace export (`trace_rows`), a public format that torch 2.11 and 2.13
write alike (the private event API differs: 2.11's events have no activity_type, run31), as rows (activity, name,
start ns, end ns, thread, correlation id, linked correlation id: `chrome_trace_rows`); everything after that is plain
arithmetic on them (`split_trace`, `summarise`, `summarise_phases`), which tests/test_fit_multi_gpu.py checks against a
brute-force count on synthetic traces.
"""
from __future__ import annotations

import bisect
import json
import math
import os
import tempfile
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Iterable, NamedTuple

ITERATION = "pig_kernel_profile_iteration"  # the annotation around each profiled iteration, on the fit's main thread
BACKWARD_OP = "autograd::engine::evaluate_function"  # the prefix of the autograd engine's ops (its own thread on a GPU)
PHASE = "pig_phase:"  # the prefix of the annotations around the fit's phases (fit_multi_gpu.RankProbe.phase)
LAUNCHES = ("cuda_runtime", "cuda_driver")  # the host's calls that start device work (Triton's through the driver)
# The rows that carry CUPTI's correlation id: the host's calls and the device activities they started.
CORRELATED = LAUNCHES + ("kernel", "gpu_memcpy", "gpu_memset")


class Row(NamedTuple):
    activity: str  # kineto's activity type: "cpu_op", "user_annotation", "kernel", "cuda_runtime", ...
    name: str
    start: int  # ns, one clock for host and device events
    end: int
    thread: int | str  # the trace's thread id (a name for the profiler's own rows)
    correlation: int  # an operator's External id; a runtime call's and its kernel's CUPTI correlation id
    linked: int  # a runtime call's (or its kernel's) link to the operator that made it (0: none)


def trace_rows(profiler) -> list[Row]:
    """The rows of a stopped torch.profiler.profile's trace, through its Chrome-trace export."""
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "trace.json")
        profiler.export_chrome_trace(path)
        with open(path) as file:
            return chrome_trace_rows(json.load(file)["traceEvents"])


def chrome_trace_rows(events: list[dict]) -> list[Row]:
    """Rows of a Chrome trace's complete events ("ph": "X"; ts and dur in microseconds). An operator's correlation
    is its "External id"; a runtime or driver call's correlation is its "correlation", which the kernel (or copy) it
    launched carries as well, and their link is the "External id" of the operator that made them."""
    rows = []
    for event in events:
        if event.get("ph") != "X" or "cat" not in event:
            continue
        args = event.get("args", {})
        start = round(event["ts"] * 1000)
        external = int(args.get("External id", 0))
        correlated = event["cat"] in CORRELATED
        rows.append(Row(event["cat"], event["name"], start, start + round(event.get("dur", 0) * 1000),
                        event.get("tid", 0), int(args.get("correlation", 0)) if correlated else external,
                        external if correlated else 0))
    return rows


def union_length(intervals: Iterable[tuple[float, float]]) -> float:
    """The length of the union of half-open intervals [start, end) (overlaps counted once, empty ones ignored)."""
    return float(sum(end - start for start, end in merged(intervals)))


def clip(intervals: Iterable[tuple[float, float]], lo: float, hi: float) -> list[tuple[float, float]]:
    """The parts of `intervals` inside [lo, hi)."""
    return [(max(s, lo), min(e, hi)) for s, e in intervals if min(e, hi) > max(s, lo)]


def is_nccl(name: str) -> bool:
    return "nccl" in name.lower()


def is_all_reduce(name: str) -> bool:
    return is_nccl(name) and "allreduce" in name.lower()


def is_host_wait(name: str) -> bool:
    """A CUDA runtime call that blocks the host until the device catches up (cudaStreamSynchronize, ...)."""
    return "Synchronize" in name


@dataclass
class Trace:
    """A trace cut to what the summary needs: the profiled iterations' windows on the main thread, every kernel,
    the step's host operators (main and autograd threads) and the blocking runtime calls made from them; each
    phase's windows on the main thread, and the kernels launched from the step's threads, with their launch's
    start: (launch, start, end, name)."""

    windows: list[tuple[int, int]]
    kernels: list[tuple[int, int, str]] = field(default_factory=list)
    host_ops: list[tuple[int, int]] = field(default_factory=list)
    waits: list[tuple[int, int]] = field(default_factory=list)
    phases: dict[str, list[tuple[int, int]]] = field(default_factory=dict)
    launched: list[tuple[int, int, int, str]] = field(default_factory=list)


def split_trace(rows: list[Row]) -> Trace:
    """The Trace of profiler rows. The step's threads: the one that annotated the iterations (ITERATION) and those
    that ran the autograd engine's ops (on a GPU the backward runs on a thread of its own); the view loader's and
    NCCL's threads are left out. A runtime call's thread is that of the operator or annotation it is linked to (the
    profiler numbers runtime calls' threads otherwise), its own where it has none. A kernel's launch is the runtime
    or driver call of its correlation id (the earliest, where both record it)."""
    windows = sorted((r.start, r.end) for r in rows if r.activity == "user_annotation" and r.name == ITERATION)
    main = {r.thread for r in rows if r.activity == "user_annotation" and r.name == ITERATION}
    step_threads = main | {r.thread for r in rows if r.activity == "cpu_op" and r.name.startswith(BACKWARD_OP)}
    op_thread = {r.correlation: r.thread for r in rows if r.activity in ("cpu_op", "user_annotation") and r.correlation}
    phases: dict[str, list[tuple[int, int]]] = defaultdict(list)
    for r in rows:
        if r.activity == "user_annotation" and r.name.startswith(PHASE) and r.thread in main:
            phases[r.name[len(PHASE):]].append((r.start, r.end))
    launch: dict[int, int] = {}
    for r in rows:
        if r.activity in LAUNCHES and op_thread.get(r.linked, r.thread) in step_threads:
            launch[r.correlation] = min(r.start, launch.get(r.correlation, r.start))
    return Trace(
        windows=windows,
        kernels=[(r.start, r.end, r.name) for r in rows if r.activity == "kernel"],
        host_ops=[(r.start, r.end) for r in rows if r.activity == "cpu_op" and r.thread in step_threads],
        waits=[(r.start, r.end) for r in rows if r.activity == "cuda_runtime" and is_host_wait(r.name)
               and op_thread.get(r.linked) in step_threads],
        phases={name: sorted(spans) for name, spans in phases.items()},
        launched=[(launch[r.correlation], r.start, r.end, r.name) for r in rows
                  if r.activity == "kernel" and r.correlation in launch])


def summarise(trace: Trace, top: int = 8) -> dict:
    """Per-iteration means (ms) over the trace's windows: wall; GPU busy (the kernels' union); NCCL kernels' union;
    the other kernels' union (compute); NCCL alone (busy less compute: communication that nothing overlaps); the
    NCCL all-reduces' union; the host's time in the step's operators not blocked in a runtime wait, and that wait;
    kernels started; and the `top` kernels by total time (ms and launches per iteration). A kernel or an operator
    that spans two windows counts in each for its part."""
    if not trace.windows:
        raise ValueError("kernel profile: no profiled iteration in the trace (no annotation named " + ITERATION + ")")
    ns = 1e-6  # ns -> ms
    count = len(trace.windows)
    sums: dict[str, float] = defaultdict(float)
    by_name: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    spans = [(s, e) for s, e, _ in trace.kernels]
    nccl = [(s, e) for s, e, n in trace.kernels if is_nccl(n)]
    compute = [(s, e) for s, e, n in trace.kernels if not is_nccl(n)]
    reduce = [(s, e) for s, e, n in trace.kernels if is_all_reduce(n)]
    for lo, hi in trace.windows:
        busy = union_length(clip(spans, lo, hi))
        sums["wall_ms"] += (hi - lo) * ns
        sums["gpu_busy_ms"] += busy * ns
        sums["nccl_ms"] += union_length(clip(nccl, lo, hi)) * ns
        computing = union_length(clip(compute, lo, hi))
        sums["compute_ms"] += computing * ns
        sums["nccl_alone_ms"] += (busy - computing) * ns
        sums["all_reduce_ms"] += union_length(clip(reduce, lo, hi)) * ns
        waits = clip(trace.waits, lo, hi)
        waiting = union_length(waits)
        sums["host_ms"] += (union_length(clip(trace.host_ops, lo, hi) + waits) - waiting) * ns
        sums["host_wait_ms"] += waiting * ns
        for s, e, name in trace.kernels:
            if lo <= s < hi:
                sums["kernels"] += 1
                by_name[name][0] += (e - s) * ns
                by_name[name][1] += 1
    summary = {key: value / count for key, value in sums.items()}
    summary.setdefault("kernels", 0.0)
    summary["iterations"] = count
    summary["gpu_idle"] = 1 - summary["gpu_busy_ms"] / summary["wall_ms"] if summary["wall_ms"] > 0 else 0.0
    ranked = sorted(by_name.items(), key=lambda item: (-item[1][0], item[0]))[:top]
    summary["top_kernels"] = [[name, ms / count, launches / count] for name, (ms, launches) in ranked]
    summary["phases"] = summarise_phases(trace)
    return summary


def merged(intervals: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    """The union of intervals as disjoint sorted ones (empty ones dropped)."""
    out: list[tuple[int, int]] = []
    for start, end in sorted((s, e) for s, e in intervals if e > s):
        if out and start <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], end))
        else:
            out.append((start, end))
    return out


def holds(spans: list[tuple[int, int]], t: int) -> bool:
    """Whether one of `spans` (disjoint, sorted: merged's) holds instant t."""
    at = bisect.bisect_right(spans, (t, math.inf)) - 1
    return at >= 0 and t < spans[at][1]


def summarise_phases(trace: Trace) -> dict[str, dict[str, float]]:
    """Per phase (nested ones on their own), means per profiled iteration: the host's wall time in the phase's
    windows (host_ms), the blocking CUDA waits of the step's threads inside them (host_wait_ms), the kernels
    launched inside them (a kernel counts in every phase whose window holds its launch's start, whichever of the
    step's threads launched it: the backward's launches come from the autograd thread while the main thread's
    `backward` window is open), those kernels' summed time (kernel_ms), their union (gpu_busy_ms, wherever it lies:
    the device may run them after the window closes) and their NCCL kernels' union (nccl_ms); the phases in the
    order they first begin."""
    count = len(trace.windows)
    ns = 1e-6  # ns -> ms
    out = {}
    for name, windows in sorted(trace.phases.items(), key=lambda item: (item[1][0][0], item[0])):  # in step order
        spans = merged(windows)
        kernels = [(s, e, n) for t, s, e, n in trace.launched if holds(spans, t)]
        out[name] = {
            "host_ms": sum(e - s for s, e in spans) * ns / count,
            "host_wait_ms": sum(union_length(clip(trace.waits, s, e)) for s, e in spans) * ns / count,
            "launches": len(kernels) / count,
            "kernel_ms": sum(e - s for s, e, _ in kernels) * ns / count,
            "gpu_busy_ms": union_length((s, e) for s, e, _ in kernels) * ns / count,
            "nccl_ms": union_length((s, e) for s, e, n in kernels if is_nccl(n)) * ns / count}
    return out


def phase_verdict(phase: dict[str, float]) -> str:
    """What bounds a phase (summarise_phases' entry): "wait" where blocking CUDA waits fill half its host window or
    more (the host waits for the device: its work, or a collective's other ranks); else "host" where its kernels' union
    is under half the window (the device idles between launches), "GPU" at 75 % or more, "mixed" between; "-" for an
    empty window."""
    host = phase["host_ms"]
    if host <= 0:
        return "-"
    if phase["host_wait_ms"] >= 0.5 * host:
        return "wait"
    busy = phase["gpu_busy_ms"] / host
    return "host" if busy < 0.5 else "GPU" if busy >= 0.75 else "mixed"


def bus_bandwidth_gbs(nbytes: float, ms: float, ranks: int) -> float:
    """An all-reduce's bus bandwidth in GB/s (NCCL's definition, nccl-tests' PERFORMANCE.md): the bytes over the
    time, times 2 (ranks - 1) / ranks, what each link carries in a ring."""
    return nbytes / (ms * 1e-3) * 2 * (ranks - 1) / ranks / 1e9 if ms > 0 and ranks > 1 else 0.0
