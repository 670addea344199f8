"""A fit's training seconds: what `fit.time_budget_s`, the learning-rate schedule's time fraction and the
error-against-time plots count, so that fits compared at equal time are compared at equal training.

Training seconds are wall time less the held-out evaluations, the train_log.png redraws, the checkpoint writes and
compilation. Compilation is lazy (torch.compile builds a graph at its first call, one per LOD and per backward; the
CG blocks are captured as CUDA graphs at theirs), so it is measured where it happens: an iteration during which a
graph was compiled or captured counts whole as compilation. That leaves out of the training seconds one step's own
work per compiled graph as well (tens of milliseconds against minutes of compilation), the same for every variant.
"""
from __future__ import annotations

import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Callable, Iterator

from pig import cuda_graphs

EXCLUDED = ("evaluation", "checkpoint", "compilation")


def compile_events() -> int:
    """How many compilation steps torch.compile (Dynamo's timed phases, forward and lazily compiled backward
    graphs alike) and CUDA graph captures have run in this process so far: it grows while anything compiles."""
    dynamo = sys.modules.get("torch._dynamo.utils")  # imported by any torch.compile; none ran if it is absent
    compiled = sum(len(times) for times in dynamo.compilation_time_metrics.values()) if dynamo is not None else 0
    return compiled + cuda_graphs.captures


class TrainingClock:
    """Wall and training seconds of a fit, resumed from `wall_before` / `train_before` of earlier runs.
    `clock` and `events` (a count that grows while code compiles) are injectable for tests."""

    def __init__(self, wall_before: float = 0.0, train_before: float = 0.0,
                 clock: Callable[[], float] = time.perf_counter, events: Callable[[], int] = compile_events):
        self.clock, self.events = clock, events
        self.wall_before, self.train_before = wall_before, train_before
        self.excluded: dict[str, float] = defaultdict(float)  # this run's seconds by kind (EXCLUDED)
        self.started = clock()

    def wall(self) -> float:
        return self.wall_before + self.clock() - self.started

    def training(self) -> float:
        return self.train_before + self.clock() - self.started - sum(self.excluded.values())

    @contextmanager
    def excluding(self, kind: str) -> Iterator[None]:
        """Seconds inside are not training, counted under `kind`."""
        assert kind in EXCLUDED, kind
        t0 = self.clock()
        try:
            yield
        finally:
            self.excluded[kind] += self.clock() - t0

    @contextmanager
    def iteration(self) -> Iterator[None]:
        """One training step: counted as compilation if anything compiled during it."""
        t0, before = self.clock(), self.events()
        try:
            yield
        finally:
            if self.events() != before:
                self.excluded["compilation"] += self.clock() - t0
