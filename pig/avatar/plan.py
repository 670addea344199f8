"""The fits a set of tables needs, and an estimate of their GPU time: each fit's iterations, then the render and
evaluate passes of its held-out splits, scheduled onto a number of GPUs in the workflow's order (fits first).

Each fit's iterations (and `fit.time_budget_s`) come from the preset after its variant's overrides; its time per
iteration is the one given for fits with or without the LPIPS term of Eq. 15, as the preset sets `weight_lpips`.
A fit with avatar.pt is done; one with a checkpoint.pt (a killed run) resumes at the checkpoint's iteration. A
held-out split is done once its metrics/{split}.json exists; with renders/{split}/ only its evaluation is left.
"""
from __future__ import annotations

import heapq
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import torch

from pig.avatar.config import AvatarConfig
from pig.avatar.fit_config import FitConfig
from pig.avatar.variants import variant_overrides
from pig.config import load_section

# Measured on an H100 with the `paper` preset's speed levers (benchmarks/NOTES.md, "Fit"): 62.1 ms/it in run20
# (benchmarks/gpu_runs/run20); with the `mmlphuman` LPIPS term 78.2 ms/it in run23 (against 55.7 without it in the
# same process, benchmarks/gpu_runs/run23/lpips/lpips.txt; run20's 62.1 plus that 22.5 would be 84.6).
MS_PER_ITERATION = 62.0
MS_PER_ITERATION_LPIPS = 78.2
# THuman4's frame (1330 x 1150), at which the per-view rates below were measured; other sizes scale by pixels.
REFERENCE_MEGAPIXELS = 1330 * 1150 / 1e6
HELD_OUT = ("novel_view", "novel_pose")


@dataclass
class ProtocolRates:
    """Costs of a fit's held-out splits on one GPU and of a subject's preprocessing on the CPU. The defaults: one
    H100, the `paper` preset, THuman4's protocol at a tenth (benchmarks/NOTES.md, "Evaluation", run26: render 800
    views of 200 frames in 29.6 s and 4800 of 50 frames in 49.2 s, evaluate 800 view scores in 24.6 s and 4800 in
    76.0 s, each pair solved for a cost per frame (render; start-up included) or per pass (evaluate) and one per
    view), and preprocess at 74 views a second on 16 threads (run7, "Data", "Preprocess throughput and resume")."""

    render_ms_per_frame: float = 27.9  # posing one frame at one LOD
    render_ms_per_view: float = 9.09  # rasterising and encoding one view at one LOD, at REFERENCE_MEGAPIXELS
    evaluate_s_per_split: float = 14.3  # one evaluate pass's start and FID statistics
    evaluate_ms_per_view: float = 12.85  # one view scored at one LOD (PSNR, SSIM, LPIPS-VGG, FID), reference size
    preprocess_views_per_s: float = 74.0  # raw views of REFERENCE_MEGAPIXELS a second

    def __post_init__(self):
        bad = {name: value for name, value in vars(self).items() if not value > 0}
        if bad:
            raise ValueError(f"rates must be positive, found {bad}")


@dataclass
class SplitSize:
    frames: int
    views: int  # cameras x frames
    megapixels: float  # of a view after preprocessing, the mean over the split's views


@dataclass
class Protocol:
    """One subject's held-out splits and capture as the plan counts them: nominal sizes, so no data is needed."""

    splits: dict[str, SplitSize]  # novel_view, novel_pose
    capture_views: int  # the views preprocess writes (every split's)
    raw_megapixels: float  # of a raw view that preprocess reads, the mean


@dataclass
class PlannedFit:
    subject: str
    variant: str
    iterations: int  # the preset's, after the variant's overrides
    lpips: bool  # whether the fit has the LPIPS term (weight_lpips > 0)
    ms_per_iteration: float
    levels: int  # LODs rendered and scored, after the variant's overrides
    done_iterations: int  # from a checkpoint.pt; all of them when avatar.pt exists
    fit_s: float  # GPU seconds of the fit left, at ms_per_iteration and within fit.time_budget_s
    state: str  # "to run", "resumes at N", "done"
    split_s: dict[str, float] | None  # GPU seconds of each split left, render + evaluate; None without sizes
    splits_left: list[str] = field(default_factory=list)  # held-out splits not yet scored

    @property
    def protocol_s(self) -> float | None:
        """GPU seconds of render + evaluate left; None without the dataset's sizes."""
        return None if self.split_s is None else sum(self.split_s.values())


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


def split_seconds(size: SplitSize, levels: int, rates: ProtocolRates, rendered: bool = False) -> float:
    """GPU seconds of one held-out split at `levels` LODs: its render (unless `rendered`), then one evaluate pass."""
    scale = size.megapixels / REFERENCE_MEGAPIXELS
    render_ms = levels * (size.frames * rates.render_ms_per_frame + size.views * scale * rates.render_ms_per_view)
    evaluate_ms = levels * size.views * scale * rates.evaluate_ms_per_view
    return (0.0 if rendered else render_ms / 1000) + rates.evaluate_s_per_split + evaluate_ms / 1000


def plan_fits(preset: dict, runs: list[tuple[str, str]], results: Path, ms_per_iteration: float = MS_PER_ITERATION,
              ms_per_iteration_lpips: float = MS_PER_ITERATION_LPIPS, protocol: Protocol | None = None,
              rates: ProtocolRates | None = None) -> list[PlannedFit]:
    """One PlannedFit per (subject, variant) in `runs`, whose outputs live in results/{subject}/{variant}/; its
    render and evaluate from `protocol` at `rates` (ProtocolRates() when None), or None without a protocol."""
    if not (ms_per_iteration > 0 and ms_per_iteration_lpips > 0):
        raise ValueError(f"times per iteration must be positive, found {ms_per_iteration} and {ms_per_iteration_lpips}")
    rates = rates or ProtocolRates()
    planned = []
    for subject, variant in runs:
        overrides = variant_overrides(preset, variant)
        cfg = load_section(preset, "fit", FitConfig, overrides.get("fit"))
        levels = load_section(preset, "avatar", AvatarConfig, overrides.get("avatar")).levels
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
        fit_s = max(0.0, min((cfg.iterations - done) * ms / 1000, budget_s - spent_s))
        left = [split for split in HELD_OUT if not (folder / "metrics" / f"{split}.json").exists()]
        split_s = None if protocol is None else {
            split: split_seconds(protocol.splits[split], levels, rates, (folder / "renders" / split).is_dir())
            for split in left}
        planned.append(PlannedFit(subject, variant, cfg.iterations, lpips, ms, levels, done, fit_s, state,
                                  split_s, left))
    return planned


def preprocess_seconds(subjects: list[str], results: Path, protocol: Protocol, rates: ProtocolRates) -> tuple[int, float]:
    """(subjects whose capture is still to preprocess, CPU wall seconds for them, one after the other): a capture
    is done once results/{subject}/capture/report.json exists; the cost scales with the raw views' pixels."""
    left = [s for s in dict.fromkeys(subjects) if not (results / s / "capture" / "report.json").exists()]
    per_subject = protocol.capture_views * protocol.raw_megapixels / REFERENCE_MEGAPIXELS / rates.preprocess_views_per_s
    return len(left), len(left) * per_subject


def makespan_s(fits: list[tuple[float, list[float]]], gpus: int) -> float:
    """Wall seconds of `fits` [(fit seconds, [seconds of each of its splits' render and evaluate]), ...] on `gpus`
    devices as the workflow runs them: every fit before any render or evaluate (the fit rule's priority), the
    longest first onto the device that frees first; then each split, once its fit has ended, onto the device that
    frees first, in the order their fits end (the longer split first among those of one moment)."""
    if gpus < 1:
        raise ValueError(f"expected at least one GPU, found {gpus}")
    free = [0.0] * gpus  # a heap of the times the devices free
    ready = []  # (when a split may start, minus its seconds)
    for fit_s, splits in sorted(fits, key=lambda fit: -fit[0]):
        end = 0.0
        if fit_s > 0:
            end = heapq.heappop(free) + fit_s
            heapq.heappush(free, end)
        ready += [(end, -seconds) for seconds in splits if seconds > 0]
    for at, minus_seconds in sorted(ready):
        heapq.heappush(free, max(heapq.heappop(free), at) - minus_seconds)
    return max(free)


def format_plan(planned: list[PlannedFit], gpus: list[int], preprocess: tuple[int, float] | None = None) -> str:
    """The plan as a text table and totals: GPU-hours left (fits, render + evaluate) and, on each count of
    `gpus` devices, wall hours; `preprocess` (subjects, CPU seconds) adds a line when given."""
    header = (f"{'subject':<12} {'variant':<14} {'iterations':>10} {'LPIPS':>5} {'ms/it':>6} {'LODs':>4} "
              f"{'fit state':<18} {'fit h':>6} {'splits left':>11} {'r+e h':>6}")
    lines = [header, "-" * len(header)]
    for fit in planned:
        protocol = "n/a" if fit.protocol_s is None else f"{fit.protocol_s / 3600:.2f}"
        lines.append(f"{fit.subject:<12} {fit.variant:<14} {fit.iterations:>10} {'on' if fit.lpips else 'off':>5} "
                     f"{fit.ms_per_iteration:>6.1f} {fit.levels:>4} {fit.state:<18} {fit.fit_s / 3600:>6.2f} "
                     f"{len(fit.splits_left):>11} {protocol:>6}")
    fits_h = sum(fit.fit_s for fit in planned) / 3600
    to_fit = sum(fit.state != "done" for fit in planned)
    splits = sum(len(fit.splits_left) for fit in planned)
    lines.append(f"{to_fit} of {len(planned)} fits to run, {splits} of {len(HELD_OUT) * len(planned)} held-out "
                 "splits to render and evaluate")
    if any(fit.protocol_s is None for fit in planned):
        lines.append(f"GPU-hours: fits {fits_h:.2f}; render + evaluate not counted (no sizes for this dataset: "
                     "see `pig doctor`); compilation and the fits' held-out probes not counted")
    else:
        protocol_h = sum(fit.protocol_s for fit in planned) / 3600
        lines.append(f"GPU-hours: fits {fits_h:.2f}, render + evaluate {protocol_h:.2f}, total "
                     f"{fits_h + protocol_h:.2f} (compilation and the fits' held-out probes not counted)")
    if preprocess is not None:
        lines.append(f"preprocess: {preprocess[0]} subject(s) to preprocess, {preprocess[1] / 3600:.2f} h on the CPU, "
                     "one after the other; a subject's fits start once its capture is written")
    fits = [(fit.fit_s, list((fit.split_s or {}).values())) for fit in planned]
    if gpus:
        lines.append("wall time, as the workflow orders the jobs: the fits first, the longest first onto the device "
                     "that frees first, then each split's render and evaluate once its fit has ended:")
        lines.extend(f"  on {count} GPU(s): {makespan_s(fits, count) / 3600:.2f} h" for count in gpus)
    return "\n".join(lines)


def plan_tables(preset: dict, runs: list[tuple[str, str]], results: Path, ms_per_iteration: float,
                ms_per_iteration_lpips: float, protocol: Protocol | None, rates: ProtocolRates,
                gpus: list[int]) -> str:
    """The plan of `runs` as format_plan prints it, preprocessing included where the protocol is known."""
    planned = plan_fits(preset, runs, results, ms_per_iteration, ms_per_iteration_lpips, protocol, rates)
    preprocess = None if protocol is None else preprocess_seconds([s for s, _ in runs], results, protocol, rates)
    return format_plan(planned, gpus, preprocess)
