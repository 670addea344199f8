"""The fits a set of tables needs, and an estimate of their GPU time from iterations and a time per iteration.

Each fit's iterations (and `fit.time_budget_s`) come from the preset after its variant's overrides; its time per
iteration is the one given for fits with or without the LPIPS term of Eq. 15, as the preset sets `weight_lpips`.
A fit with avatar.pt is done; one with a checkpoint.pt (a killed run) resumes at the checkpoint's iteration.
"""
from __future__ import annotations

import heapq
import pickle
from dataclasses import dataclass
from pathlib import Path

import torch

from pig.avatar.fit_config import FitConfig
from pig.avatar.variants import variant_overrides
from pig.config import load_section

# Measured on an H100 with the `paper` preset's speed levers (benchmarks/NOTES.md, "Fit"): 62.1 ms/it in run20
# (benchmarks/gpu_runs/run20); the `mmlphuman` LPIPS term adds 22.5 ms (78.2 against 55.7 ms/it in one process,
# benchmarks/gpu_runs/run23/lpips/lpips.txt).
MS_PER_ITERATION = 62.0
MS_PER_ITERATION_LPIPS = 85.0


@dataclass
class PlannedFit:
    subject: str
    variant: str
    iterations: int  # the preset's, after the variant's overrides
    lpips: bool  # whether the fit has the LPIPS term (weight_lpips > 0)
    ms_per_iteration: float
    done_iterations: int  # from a checkpoint.pt; all of them when avatar.pt exists
    remaining_s: float  # GPU seconds left, at ms_per_iteration and within fit.time_budget_s
    state: str  # "to run", "resumes at N", "done"


def checkpoint_progress(path: Path) -> tuple[int, float]:
    """(iteration, training seconds) stored in a fit's checkpoint.pt, read without loading its tensors."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except (RuntimeError, pickle.UnpicklingError) as err:
        raise ValueError(f"{path}: not a readable fit checkpoint ({err})") from None
    try:
        return int(state["iteration"]), float(state["wall_s"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{path}: expected a fit checkpoint with `iteration` and `wall_s`") from None


def plan_fits(preset: dict, runs: list[tuple[str, str]], results: Path, ms_per_iteration: float = MS_PER_ITERATION,
              ms_per_iteration_lpips: float = MS_PER_ITERATION_LPIPS) -> list[PlannedFit]:
    """One PlannedFit per (subject, variant) in `runs`, whose outputs live in results/{subject}/{variant}/."""
    if not (ms_per_iteration > 0 and ms_per_iteration_lpips > 0):
        raise ValueError(f"times per iteration must be positive, found {ms_per_iteration} and {ms_per_iteration_lpips}")
    planned = []
    for subject, variant in runs:
        cfg = load_section(preset, "fit", FitConfig, variant_overrides(preset, variant).get("fit"))
        lpips = cfg.weight_lpips > 0
        ms = ms_per_iteration_lpips if lpips else ms_per_iteration
        folder = results / subject / variant
        budget_s = cfg.time_budget_s if cfg.time_budget_s is not None else float("inf")
        if (folder / "avatar.pt").exists():
            done, spent_s, state = cfg.iterations, budget_s, "done"
        elif (folder / "checkpoint.pt").exists():
            done, spent_s = checkpoint_progress(folder / "checkpoint.pt")
            state = f"resumes at {done}"
        else:
            done, spent_s, state = 0, 0.0, "to run"
        remaining_s = max(0.0, min((cfg.iterations - done) * ms / 1000, budget_s - spent_s))
        planned.append(PlannedFit(subject, variant, cfg.iterations, lpips, ms, done, remaining_s, state))
    return planned


def makespan_s(durations: list[float], gpus: int) -> float:
    """Wall seconds to run `durations` on `gpus` devices, one job each at a time, longest first onto the device
    that frees first (what a scheduler that starts the longest jobs first achieves)."""
    if gpus < 1:
        raise ValueError(f"expected at least one GPU, found {gpus}")
    loads = [0.0] * gpus
    for duration in sorted(durations, reverse=True):
        heapq.heapreplace(loads, loads[0] + duration)
    return max(loads)


def format_plan(planned: list[PlannedFit], gpus: int) -> str:
    """The plan as a text table and a total: GPU-hours left and, on `gpus` devices, wall hours."""
    header = f"{'subject':<12} {'variant':<14} {'iterations':>10} {'LPIPS':>5} {'ms/it':>6} {'state':<18} {'GPU h':>7}"
    lines = [header, "-" * len(header)]
    for fit in planned:
        lines.append(f"{fit.subject:<12} {fit.variant:<14} {fit.iterations:>10} {'on' if fit.lpips else 'off':>5} "
                     f"{fit.ms_per_iteration:>6.0f} {fit.state:<18} {fit.remaining_s / 3600:>7.2f}")
    left = [fit.remaining_s for fit in planned if fit.state != "done"]
    total_h = sum(left) / 3600
    lines.append(f"{len(left)} of {len(planned)} fits to run: {total_h:.2f} GPU-hours (fits only; compilation, "
                 "held-out evaluations, render and evaluate not counted)")
    if gpus > 0:
        lines.append(f"on {gpus} GPU(s), one fit each at a time: about {makespan_s(left, gpus) / 3600:.2f} h wall")
    return "\n".join(lines)
