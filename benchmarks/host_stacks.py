"""Where a data-parallel fit's host time goes, from py-spy's sampled Python stacks of every rank.

    python benchmarks/host_stacks.py STACKS.txt [--top 25]

STACKS.txt is py-spy's raw (collapsed) output of a run recorded with its subprocesses and threads, e.g. on the GPU
machine (benchmarks/gpu_runs/host_stacks.sh):

    py-spy record --subprocesses --threads --nonblocking --format raw --rate 200 -o STACKS.txt -- \\
        python3 benchmarks/fit_multi_gpu.py --workdir /tmp/mg_spy --gpus 4 --shard-solves on --iterations 400 --warmup 40

Each line is one stack, root first, frames joined by ";" ("process PID:"CMDLINE"" frames, a "thread (TID): NAME"
frame, then "function (file:line)" frames), and its sample count. A rank is a process started by multiprocessing's
spawn (torch's start_processes), numbered in the order of its process id (the order the ranks were started).
Samples outside the fit (`_fit` of pig/avatar/training.py: imports, start-up), and those that compile
(torch.compile's Dynamo and Inductor frames) or evaluate (the held-out evaluations) are left out: what remains of a
rank's main thread is its training steps and the fit's own set-up (a table splits it by what `_fit` called). py-spy
counts a thread while it runs Python or code called from it, so a sample in a frame that calls into torch's C++ (a
kernel launch, the autograd engine) counts there.

Tables: per rank and thread, the share of the samples; for the ranks' main threads together, what `_fit` called,
and the steps' frames by inclusive share (each frame counted once per sample however often it recurs) of this
project's functions (pig/...), and by self share (the innermost frame) of every function.
"""
from __future__ import annotations

import argparse
import re
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

RANK_MARK = "multiprocessing.spawn import spawn_main"
FIT = "_fit (pig/avatar/training.py)"
# Frames of work that is not a training step's: compilation and the held-out evaluations.
LEFT_OUT = ("torch/_dynamo/convert_frame.py", "torch/_inductor/compile_fx.py", "torch/_inductor/async_compile.py",
            "evaluate_held_out")
# A process frame's command line may hold ";" itself (spawn's `-c "...; spawn_main(...)"`): it ends at the quote
# before the next process or thread frame.
PROCESS = re.compile(r'process (\d+):"(.*?)";(?=process |thread \()')
THREAD = re.compile(r"^thread \((\w+)\): ?(.*)$")
FRAME = re.compile(r"^(.*) \((.*?)(?::\d+)?\)$")


@dataclass
class Sample:
    process: int
    command: str
    thread: str
    frames: list[str]  # "function (file)" from the outermost frame in
    count: int


@dataclass
class Ranks:
    """The samples of the ranks, rank by rank (index: rank), and those left out."""

    samples: list[list[Sample]] = field(default_factory=list)
    left_out: Counter = field(default_factory=Counter)


def parse_line(line: str) -> Sample | None:
    """One raw line as a Sample of its innermost process and its thread; None for a line without a thread."""
    stack, _, count = line.rstrip("\n").rpartition(" ")
    if not stack or not count.isdigit():
        return None
    process, command, thread, frames = -1, "", None, []
    while match := PROCESS.match(stack):
        process, command, stack = int(match.group(1)), match.group(2), stack[match.end():]
    head, _, stack = stack.partition(";")
    if not (match := THREAD.match(head)):
        return None
    thread = match.group(2) or match.group(1)
    for part in filter(None, stack.split(";")):
        if match := FRAME.match(part):
            frames.append(f"{match.group(1)} ({match.group(2)})")
        else:
            frames.append(part)
    return Sample(process, command, thread, frames, int(count))


def read_ranks(text: str) -> Ranks:
    """The ranks' samples of a raw py-spy file, less compilation and evaluation."""
    by_process: dict[int, list[Sample]] = defaultdict(list)
    left_out: Counter = Counter()
    for line in text.splitlines():
        sample = parse_line(line)
        if sample is None or RANK_MARK not in sample.command:
            continue
        reason = next((mark for mark in LEFT_OUT if any(mark in frame for frame in sample.frames)), None)
        if reason is None and sample.thread == "MainThread" and FIT not in sample.frames:
            reason = "outside the fit"
        if reason is not None:
            left_out[reason] += sample.count
            continue
        by_process[sample.process].append(sample)
    return Ranks([by_process[pid] for pid in sorted(by_process)], left_out)


def inclusive(samples: list[Sample], keep) -> Counter:
    """Samples per frame that `keep` accepts, each frame once per sample."""
    counts: Counter = Counter()
    for sample in samples:
        for frame in set(sample.frames):
            if keep(frame):
                counts[frame] += sample.count
    return counts


def own(samples: list[Sample]) -> Counter:
    """Samples per innermost frame."""
    counts: Counter = Counter()
    for sample in samples:
        if sample.frames:
            counts[sample.frames[-1]] += sample.count
    return counts


def print_tables(ranks: Ranks, top: int) -> None:
    print(f"{len(ranks.samples)} ranks; left out (samples): "
          + (", ".join(f"{mark} {n}" for mark, n in ranks.left_out.most_common()) or "none"))
    print("\nSamples per rank and thread (share of the rank's steps' samples)")
    print("| rank | pid | thread | samples | share |")
    print("|---|---|---|---|---|")
    for rank, samples in enumerate(ranks.samples):
        total = sum(s.count for s in samples) or 1
        threads: Counter = Counter()
        for sample in samples:
            threads[sample.thread] += sample.count
        for thread, n in threads.most_common():
            print(f"| {rank} | {samples[0].process} | {thread} | {n} | {100 * n / total:.1f} % |")
    main = [s for samples in ranks.samples for s in samples if s.thread == "MainThread"]
    total = sum(s.count for s in main) or 1
    called: Counter = Counter()
    for sample in main:
        below = sample.frames[sample.frames.index(FIT) + 1:]
        called[below[0] if below else "_fit itself"] += sample.count
    print_frames(f"The ranks' main threads together ({total} samples): what `_fit` called, by share", called, total, top)
    print_frames("The ranks' main threads together: this project's frames by inclusive share",
                 inclusive(main, lambda f: "(pig/" in f or "/pig/" in f), total, top)
    print_frames("The ranks' main threads together: innermost frames by share (time in the frame or in what it calls "
                 "outside Python)", own(main), total, top)


def print_frames(title: str, counts: Counter, total: int, top: int) -> None:
    """A table of the `top` frames of `counts`, each with its share of `total` samples."""
    print(f"\n{title}")
    print("| frame | samples | share |")
    print("|---|---|---|")
    for frame, n in counts.most_common(top):
        print(f"| {frame} | {n} | {100 * n / total:.1f} % |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stacks", type=Path, help="py-spy record --format raw output (--subprocesses --threads)")
    parser.add_argument("--top", type=int, default=25, help="rows of each frame table")
    args = parser.parse_args(argv)
    ranks = read_ranks(args.stacks.read_text())
    if not ranks.samples:
        parser.error(f"{args.stacks}: no rank's samples (expected py-spy --subprocesses --threads output of a "
                     "data-parallel fit)")
    print_tables(ranks, args.top)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
