"""An exponential moving average of the optimised tensors, evaluated and saved in place of the last iterate.

A short fit ends with learning rates that are still large, so its last iterate carries the noise of its last few
steps: the held-out PSNR moves by tenths of a dB between neighbouring evaluations, and between two runs of one
seed (benchmarks/NOTES.md, "Fit"). Averaging the weights over the last few hundred steps removes most of it.
"""
from __future__ import annotations

from contextlib import contextmanager

import torch
from torch.optim.swa_utils import get_ema_multi_avg_fn


class WeightAverage:
    """EMA with `decay` of the tensors that `optimizers` update, started by the first `update()` (a copy)."""

    def __init__(self, optimizers: list[torch.optim.Optimizer], decay: float):
        if not 0 < decay < 1:
            raise ValueError(f"WeightAverage: decay must lie in (0, 1), found {decay}")
        self.params = [p for opt in optimizers for group in opt.param_groups for p in group["params"]]
        self._lerp = get_ema_multi_avg_fn(decay)
        self.averages: list[torch.Tensor] | None = None  # None until started
        self.updates = 0

    @property
    def started(self) -> bool:
        return self.averages is not None

    @torch.no_grad()
    def update(self) -> None:
        if self.averages is None:
            self.averages = [p.detach().clone() for p in self.params]
        else:
            self._lerp(self.averages, [p.detach() for p in self.params], self.updates)
        self.updates += 1

    def restart(self) -> None:
        """Forget the average (the tensors changed meaning, e.g. a preconditioner re-based them)."""
        self.averages, self.updates = None, 0

    @contextmanager
    @torch.no_grad()
    def applied(self):
        """The model holds the averages inside the block (copies in place: compiled graphs keep their inputs) and its
        own weights again after it; without an average it is left as it is."""
        if self.averages is None:
            yield
            return
        own = [p.detach().clone() for p in self.params]
        for p, average in zip(self.params, self.averages):
            p.copy_(average)
        try:
            yield
        finally:
            for p, value in zip(self.params, own):
                p.copy_(value)

    def state_dict(self) -> dict:
        return {"averages": self.averages, "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        averages = state["averages"]
        if averages is not None:
            shapes = [tuple(p.shape) for p in self.params]
            if [tuple(a.shape) for a in averages] != shapes:
                raise ValueError(f"WeightAverage: stored averages of shapes {[tuple(a.shape) for a in averages][:4]}..., "
                                 f"the optimised tensors have {shapes[:4]}...")
            averages = [a.to(p) for a, p in zip(averages, self.params)]
        self.averages, self.updates = averages, int(state["updates"])
