"""What a running fit tells: a progress line every few seconds and, on request, TensorBoard scalars.

The line (stderr, so a rule's log and, through the workflow's `tee`, the console) states the iteration, the mean
loss (Eq. 15) of the last logged row, the latest held-out PSNR (and probe PSNR, where the fit probes;
pig.avatar.probe) and an estimate of the time left:
    fit results/synthetic/subject00/pig: iteration 1200/4000 (30.0 %), loss 0.1234, held-out PSNR 24.31 dB
    (iteration 1000), 2.1 it/s, 0:22:13 left
The time left extrapolates this run's wall time (held-out evaluations included) over the part of the run done,
which is the larger of the iteration and time-budget fractions, as the fit's schedule counts it.
TensorBoard (the field's convention; the `tensorboard` extra) gets every logged row's loss terms under `train/`
and every held-out PSNR under `heldout/`, by iteration.
"""
from __future__ import annotations

import sys
import time
from datetime import timedelta
from pathlib import Path
from typing import Callable

from pig.progress import quiet

TENSORBOARD_DIR = "tensorboard"
SCALARS = {"loss": "train/loss", "l1": "train/l1", "ssim": "train/ssim", "lpips": "train/lpips",
           "heldout_psnr": "heldout/psnr", "heldout_psnr_iterate": "heldout/psnr_iterate",
           "probe_psnr": "heldout/probe_psnr"}


def tensorboard_writer(folder: Path):
    """A torch SummaryWriter writing to `folder`; a clear error where the tensorboard package is missing."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise ImportError("the fit's TensorBoard scalars need the tensorboard package: pip install 'pig[tensorboard]' "
                          "(or leave out --tensorboard)") from None
    return SummaryWriter(str(folder))


class FitProgress:
    """Progress lines every `interval_s` seconds (and at each held-out evaluation) of a fit of `total`
    iterations resumed at `start` (0: a new fit), to `stream` (default stderr); `name` heads each line.
    `writer`: a TensorBoard SummaryWriter or None. `--quiet` (pig.progress) silences the lines, not TensorBoard."""

    def __init__(self, name: str, total: int, start: int, interval_s: float, writer=None, stream=None,
                 clock: Callable[[], float] = time.perf_counter):
        self.name, self.total, self.interval_s, self.writer = name, total, interval_s, writer
        self.stream, self.clock = stream, clock
        self.started = self.last_line = clock()
        self.start_iteration, self.start_done = start, start / total
        self.loss = self.psnr = self.psnr_iteration = self.probe = self.probe_iteration = self.printed = None

    def record(self, row: dict) -> None:
        """Take a logged row of train_log.csv (pig.avatar.training.LOG_COLUMNS; "" where a value is absent)."""
        if row.get("loss", "") != "":
            self.loss = float(row["loss"])
        if row.get("heldout_psnr", "") != "":
            self.psnr, self.psnr_iteration = float(row["heldout_psnr"]), int(row["iteration"])
        if row.get("probe_psnr", "") != "":
            self.probe, self.probe_iteration = float(row["probe_psnr"]), int(row["iteration"])
        if self.writer is not None:
            for key, tag in SCALARS.items():
                if row.get(key, "") != "":
                    self.writer.add_scalar(tag, float(row[key]), int(row["iteration"]))

    def step(self, iteration: int, done: float, evaluated: bool = False) -> None:
        """After `iteration` (1-based), with the fraction `done` of the run behind it: print a line when the
        interval has passed or a held-out evaluation just ran."""
        now = self.clock()
        if evaluated or now - self.last_line >= self.interval_s:
            self.print_line(iteration, done, now)

    def finish(self, iteration: int) -> None:
        """The fit ended after `iteration`: its last line, unless that iteration's is out already."""
        if self.printed != iteration:
            self.print_line(iteration, 1.0)

    def print_line(self, iteration: int, done: float, now: float | None = None) -> None:
        now = self.clock() if now is None else now
        self.last_line, self.printed = now, iteration
        if quiet():
            return
        print(self.line(iteration, done, now), file=self.stream or sys.stderr, flush=True)

    def line(self, iteration: int, done: float, now: float) -> str:
        elapsed = now - self.started
        parts = [f"iteration {iteration}/{self.total} ({100 * done:.1f} %)"]
        parts.append(f"loss {self.loss:.4g}" if self.loss is not None else "loss -")
        parts.append(f"held-out PSNR {self.psnr:.2f} dB (iteration {self.psnr_iteration})" if self.psnr is not None
                     else "held-out PSNR -")
        if self.probe is not None:
            parts.append(f"probe PSNR {self.probe:.2f} dB (iteration {self.probe_iteration})")
        iterations = iteration - self.start_iteration
        if iterations > 0 and elapsed > 0:
            parts.append(f"{iterations / elapsed:.3g} it/s")
        progressed = done - self.start_done
        if progressed > 0 and done < 1:
            parts.append(f"{timedelta(seconds=round(elapsed * (1 - done) / progressed))} left")
        elif done >= 1:
            parts.append("done")
        return f"fit {self.name}: " + ", ".join(parts)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
