"""Where a fit iteration's time goes on the host and on its GPU, from a torch.profiler trace of a few iterations
(benchmarks/fit_multi_gpu.py --kernel-profile): the device's busy time (the union of its kernels' intervals, so that
kernels overlapping on several streams count once), NCCL's part of it, the host's time in the step's operators, the
kernels launched, and the costliest kernels.

The trace is read from the profiler's Chrome-trace export (`trace_rows`), a public format that torch 2.11 and 2.13
write alike (the private event API differs: 2.11's events have no activity_type, run31), as rows (activity, name,
start ns, end ns, thread, correlation id, linked correlation id: `chrome_trace_rows`); everything after that is plain
arithmetic on them (`split_trace`, `summarise`), which tests/test_fit_multi_gpu.py checks against a brute-force count
on synthetic traces.
"""
from __future__ import annotations

import json
import os
import tempfile
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Iterable, NamedTuple

ITERATION = "pig_kernel_profile_iteration"  # the annotation around each profiled iteration, on the fit's main thread
BACKWARD_OP = "autograd::engine::evaluate_function"  # the prefix of the autograd engine's ops (its own thread on a GPU)


class Row(NamedTuple):
    activity: str  # kineto's activity type: "cpu_op", "user_annotation", "kernel", "cuda_runtime", ...
    name: str
    start: int  # ns, one clock for host and device events
    end: int
    thread: int | str  # the trace's thread id (a name for the profiler's own rows)
    correlation: int
    linked: int  # a runtime call's link to the operator that made it (0: none)


def trace_rows(profiler) -> list[Row]:
    """The rows of a stopped torch.profiler.profile's trace, through its Chrome-trace export."""
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "trace.json")
        profiler.export_chrome_trace(path)
        with open(path) as file:
            return chrome_trace_rows(json.load(file)["traceEvents"])


def chrome_trace_rows(events: list[dict]) -> list[Row]:
    """Rows of a Chrome trace's complete events ("ph": "X"; ts and dur in microseconds). An operator's correlation
    is its "External id"; a runtime call's correlation is its "correlation" (shared with the kernel it launched) and
    its link is the "External id" of the operator that made it."""
    rows = []
    for event in events:
        if event.get("ph") != "X" or "cat" not in event:
            continue
        args = event.get("args", {})
        start = round(event["ts"] * 1000)
        external = int(args.get("External id", 0))
        runtime = event["cat"] == "cuda_runtime"
        rows.append(Row(event["cat"], event["name"], start, start + round(event.get("dur", 0) * 1000),
                        event.get("tid", 0), int(args.get("correlation", 0)) if runtime else external,
                        external if runtime else 0))
    return rows


def union_length(intervals: Iterable[tuple[float, float]]) -> float:
    """The length of the union of half-open intervals [start, end) (overlaps counted once, empty ones ignored)."""
    total, reach = 0.0, None
    for start, end in sorted((s, e) for s, e in intervals if e > s):
        if reach is None or start > reach:
            total += end - start
            reach = end
        elif end > reach:
            total += end - reach
            reach = end
    return total


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
    the step's host operators (main and autograd threads) and the blocking runtime calls made from them."""

    windows: list[tuple[int, int]]
    kernels: list[tuple[int, int, str]] = field(default_factory=list)
    host_ops: list[tuple[int, int]] = field(default_factory=list)
    waits: list[tuple[int, int]] = field(default_factory=list)


def split_trace(rows: list[Row]) -> Trace:
    """The Trace of profiler rows. The step's threads: the one that annotated the iterations (ITERATION) and those
    that ran the autograd engine's ops (on a GPU the backward runs on a thread of its own); the view loader's and
    NCCL's threads are left out. A runtime call's thread is that of the operator it is linked to (the profiler
    numbers runtime calls' threads otherwise)."""
    windows = sorted((r.start, r.end) for r in rows if r.activity == "user_annotation" and r.name == ITERATION)
    main = {r.thread for r in rows if r.activity == "user_annotation" and r.name == ITERATION}
    step_threads = main | {r.thread for r in rows if r.activity == "cpu_op" and r.name.startswith(BACKWARD_OP)}
    op_thread = {r.correlation: r.thread for r in rows if r.activity == "cpu_op"}
    return Trace(
        windows=windows,
        kernels=[(r.start, r.end, r.name) for r in rows if r.activity == "kernel"],
        host_ops=[(r.start, r.end) for r in rows if r.activity == "cpu_op" and r.thread in step_threads],
        waits=[(r.start, r.end) for r in rows if r.activity == "cuda_runtime" and is_host_wait(r.name)
               and op_thread.get(r.linked) in step_threads])


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
    return summary


def bus_bandwidth_gbs(nbytes: float, ms: float, ranks: int) -> float:
    """An all-reduce's bus bandwidth in GB/s (NCCL's definition, nccl-tests' PERFORMANCE.md): the bytes over the
    time, times 2 (ranks - 1) / ranks, what each link carries in a ring."""
    return nbytes / (ms * 1e-3) * 2 * (ranks - 1) / ranks / 1e9 if ms > 0 and ranks > 1 else 0.0
