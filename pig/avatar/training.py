"""Fitting an avatar to a preprocessed capture: the optimisation of Section 3.5, resumable and logged.

Eq. 15 per iteration on one random LOD, V views x K timesteps, with the per-group optimisers of Section 3.3
(Eqs. 4-5); writes avatar.pt, train_log.csv and train_log.png. `fit` is the library entry of the fit stage
(pig.stages.fit) and of the benchmarks.

Speed levers (preset section `fit`, each off in the CPU presets; benchmarks/NOTES.md, "Fit", measures each):
`precision` (decoders in TF32 or bf16 autocast, float32 master weights), `compile` (torch.compile of the
decoder MLPs and of the L1 + SSIM loss, with SSIM's blur as shifted sums that compile into one kernel),
`compile_posing` (torch.compile of the body model, transport and splat assembly of a training step),
`compile_mode` (those regions and the LPIPS network's replayed as CUDA graphs with "reduce-overhead"),
`batched_render` (one rasterizer call and one loss evaluation for all timesteps and views), `lpips_bf16_head`,
`lpips_compile` and `lpips_crop_sliced` (the LPIPS term's, pig.metrics.lpips.TrainingLPIPS), `fused_adam`
(torch's fused Adam kernels instead of a loop over tensors), `log_every` (loss terms read back to the host
every N iterations, not every one), `host_band` (the loss's silhouette band computed by the view loader threads
with OpenCV, not on the training device). The KNN solve's host synchronisations are `precond.cg_check_every`, none
with `precond.cg_lagged` (benchmarks/host_syncs_cpu.py lists a step's).
"""
from __future__ import annotations

import csv
import io
import math
import os
import sys
import time
from contextlib import AbstractContextManager, closing, contextmanager, nullcontext
from dataclasses import asdict, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from pig.avatar.averaging import WeightAverage
from pig.avatar.batches import Sampler, TrainingBatch, TrainingBatches, ViewSource, host_to_device
from pig.avatar.build import body_model_npz, build_avatar, build_optimizers
from pig.avatar.checkpoint import load_training_state, save_checkpoint
from pig.avatar.config import AvatarConfig
from pig.avatar.distributed import Parallel, ShardedSampler, SilentProgress, SolveShards, lpips_shares, shard_loss
from pig.avatar.fit_config import FitConfig
from pig.avatar.fit_progress import TENSORBOARD_DIR, FitProgress, tensorboard_writer
from pig.avatar.losses import apply_band, band_radius, boundary_band, image_loss, lpips_term, lpips_views
from pig.avatar.probe import Probe
from pig.avatar.train_plot import plot_train_log
from pig.avatar.training_clock import TrainingClock
from pig.avatar.variants import variant_overrides
from pig.body.params import SmplxParams
from pig.config import DEFAULT_PRESET, ConfigError, load_preset, load_section, resolve_device
from pig.data.capture import Capture
from pig.data.raw import CaptureError
from pig.field.latent_grid import FieldConfig
from pig.field.precondition import PrecondConfig
from pig.metrics.lpips import TrainingLPIPS
from pig.metrics.psnr import psnr
from pig.metrics.ssim import gaussian_window
from pig.progress import LOG_INTERVAL_S
from pig.render.api import RasterizerConfig, render_gaussians, render_timesteps
from pig._io import write_text
from pig._outputs import claim_files, output_lock

# lpips_term: the LPIPS term's state on every row (pig.avatar.losses.LPIPS_STATES; "on" is the paper's loss).
# train_s: training seconds, wall time less held-out evaluations, train_log.png redraws, checkpoint writes and
# compilation (pig.avatar.training_clock: what the time budget counts; the x axis of the error-against-time plots);
# logs written before it existed lack the column. compile_s: the seconds of compilation left out of train_s so far. heldout_psnr: of the weight
# average once it has started (fit.average_decay), else of the weights of that iteration; heldout_psnr_iterate: of that
# iteration's own weights while an average is evaluated (what the average buys), else empty. probe_psnr: the cheap
# held-out PSNR of pig.avatar.probe (fit.probe_every; mask boxes, not frames: lower than heldout_psnr), of the weights
# heldout_psnr is of. eval_s: seconds this row's held-out evaluations and the redraw of train_log.png took.
LOG_COLUMNS = ["iteration", "wall_s", "train_s", "lod", "loss", "l1", "ssim", "lpips", "lpips_term", "heldout_psnr",
               "heldout_psnr_iterate", "probe_psnr", "eval_s", "data_wait_ms", "compile_s"]
EVALUATION_COLUMNS = ["heldout_psnr", "heldout_psnr_iterate", "probe_psnr", "eval_s"]  # "" in rows without one
# With a weight average (fit.average_decay) avatar.pt holds the average and ITERATE_FILE the last iterate, which the
# average is compared with (benchmarks/fit_gpu.py --evaluate-iterate); a fit without one leaves no ITERATE_FILE.
ITERATE_FILE = "avatar_iterate.pt"
OUTPUT_FILES = ["avatar.pt", ITERATE_FILE, "checkpoint.pt", "train_log.csv", "train_log.png"]
# train_log.png is redrawn at the start, at each full held-out evaluation (the end's included), and at a probe when
# this long has passed since the last draw: a draw costs more than a probe (benchmarks/NOTES.md, "Workflow").
REDRAW_S = 120.0
class FitDiverged(ValueError):
    """The fit's loss or weights became NaN or infinite: there is no avatar to write."""


def _diverged(what: str, iteration: int, state_path: Path) -> FitDiverged:
    kept = (f"{state_path} keeps the last finite weights; delete it to start over" if state_path.exists()
            else "no checkpoint was written")
    return FitDiverged(f"fit diverged at iteration {iteration}: {what}; stopped without writing avatar.pt ({kept}); "
                       "lower the learning rates (fit.lr_*, precond) or check the capture")


def lr_factor(progress: float, iteration: int, warmup: int, final: float) -> float:
    """Multiplier of every base learning rate: warm-up over `warmup` iterations, then exp decay to `final` at
    `progress` 1 (progress in [0, 1] is the fraction of the run done)."""
    ramp = min(1.0, (iteration + 1) / warmup) if warmup > 0 else 1.0
    return ramp * final ** min(max(progress, 0.0), 1.0)


def perturb_params(params: SmplxParams, sigma: float, seed: int) -> SmplxParams:
    """Zero-mean Gaussian noise of std `sigma` on the global + body joint angles and on the betas."""
    if sigma <= 0:
        return params
    rng = np.random.default_rng(seed)
    pose = params.full_pose.copy()
    pose[:, :22] += rng.normal(scale=sigma, size=pose[:, :22].shape)
    betas = params.betas + rng.normal(scale=sigma, size=params.betas.shape)
    return SmplxParams(pose, betas, params.expression.copy(), params.transl.copy())


def evaluations_due(cfg: FitConfig, iteration: int) -> tuple[bool, bool]:
    """(the full held-out evaluation, the probe) due after `iteration` of a fit with `cfg`, 0 being the start: the
    full one at multiples of `eval_every` and at the end, and at the start unless the fit probes; the probe at
    multiples of `probe_every` (the start included) and at the end. A resumed fit keeps the same iterations."""
    last = iteration == cfg.iterations
    probe = cfg.probe_every > 0 and (iteration % cfg.probe_every == 0 or last)
    if iteration == 0:
        return not cfg.probe_every, probe
    return iteration % cfg.eval_every == 0 or last, probe


def _write_log(path: Path, rows: list[dict]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=LOG_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, buffer.getvalue())


class HeldOut:
    """Novel-view cameras on a few training frames: PSNR at the finest LOD, black background, masked truth.
    The views are read when evaluated, at most `chunk` at a time."""

    def __init__(self, capture: Capture, model, source: ViewSource, count: int, chunk: int):
        split = capture.split["novel_view"]
        frames = [f for f in split["frames"] if f in model.frame_ids]
        picks = [frames[int(i)] for i in np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round())] if frames else []
        seen_by = {f: [c for c in split["cameras"] if capture.has(c, f)] for f in picks}
        self.steps = [(model.timestep_of_frame(f), cams) for f, cams in seen_by.items() if cams]
        self.source, self.chunk = source, chunk

    @torch.no_grad()
    def psnr(self, model, raster: RasterizerConfig) -> float:
        if not self.steps:
            return math.nan
        values = []
        black = torch.zeros(3, device=self.source.device)
        for step, cameras in self.steps:
            g = model(torch.tensor([step]), model.num_levels - 1)
            for first in range(0, len(cameras), self.chunk):
                [batches] = self.source.views(self.source.stage([(step, cameras[first:first + self.chunk])]))
                for vb in batches:
                    out = render_gaussians(g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0], vb.viewmats, vb.Ks,
                                           vb.width, vb.height, black, backend=raster.backend, max_pairs=raster.max_pairs)
                    truth = vb.images * vb.masks[..., None]
                    values += psnr(out.color.clamp(0, 1).permute(0, 3, 1, 2), truth.permute(0, 3, 1, 2)).tolist()
        return float(np.mean(values))


@contextmanager
def _matmul_precision(precision: str):
    """TF32 matmuls while fitting with precision "tf32"; the process's setting comes back afterwards."""
    before = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = precision == "tf32"
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = before


class LossTerms:
    """Eq. 15 of renders (B, H, W, 3) against their views; L1 + SSIM compiled with `compiled`, LPIPS in bf16
    autocast with precision "bf16", in the form and with the levers of `cfg` (FitConfig.lpips_*). `at` tells it the
    iteration and the run's progress, which the LPIPS term's schedule and random windows follow."""

    def __init__(self, cfg: FitConfig, background: torch.Tensor, lpips, compiled: bool):
        self.cfg, self.background = cfg, background
        self.lpips = None if lpips is None else TrainingLPIPS(lpips, cfg.precision == "bf16", cfg.lpips_bf16_head,
                                                                cfg.lpips_compile, cfg.compile_mode)
        weights = (cfg.weight_l1, cfg.weight_ssim, 0.0)
        blur = "shift" if compiled else "conv"
        window = gaussian_window(torch.float32, background.device)  # made once, outside the compiled graph
        l1_ssim = lambda render, target, band: image_loss(render, target, band, background, weights, None, blur, window)
        self._l1_ssim = torch.compile(l1_ssim, mode=cfg.compile_mode) if compiled else l1_ssim
        self.at(0, 0.0)

    def at(self, iteration: int, progress: float) -> None:
        """The iteration about to be computed and the run's progress in [0, 1]; the random windows of an iteration
        come from (seed, iteration), so a resumed fit draws the same ones."""
        self.progress = progress
        self._windows = np.random.default_rng([self.cfg.seed, iteration, 27])  # a stream apart from the view sampler's

    def band_radius(self, height: int) -> int:
        return band_radius(height, self.cfg.band_radius_px, self.cfg.band_reference_height)

    def draw(self, views: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The LPIPS term's random choices for a loss evaluation of `views` views: the views it sees (sorted; None:
        all, `lpips_views`) and their windows (n, 2) uniforms (None: no windows, `lpips_patches_from`)."""
        pick = None
        if 0 < self.cfg.lpips_views < views:
            pick = np.sort(self._windows.choice(views, self.cfg.lpips_views, replace=False))
        windows = self.cfg.lpips_form == "mmlphuman" and self.progress >= self.cfg.lpips_patches_from
        return pick, self._windows.random((views if pick is None else len(pick), 2)) if windows else None

    @property
    def lpips_active(self) -> bool:
        """Whether the LPIPS term is computed at this iteration."""
        return self.lpips is not None and self.cfg.weight_lpips > 0 and self.progress >= self.cfg.lpips_start

    def __call__(self, render: torch.Tensor, images: torch.Tensor, masks: torch.Tensor, height: int,
                 band: torch.Tensor | None = None, share=None) -> dict[str, torch.Tensor]:
        """`band`: the views' silhouette band where the loader computed it (`host_band`), else from `masks`.
        `share` (pig.avatar.distributed.LossShare): these views are a part of the iteration's in a data-parallel
        fit; every term is then their part of the iteration's mean, with the LPIPS term's views and windows those
        of the whole iteration's draw."""
        if band is None:
            band = boundary_band(masks, self.band_radius(height))
        terms = dict(self._l1_ssim(render, images, band))
        if share is not None:
            terms = {key: value * share.weight for key, value in terms.items()}
        if self.lpips is not None and self.cfg.weight_lpips > 0:
            if not self.lpips_active:  # MMLPHuman's late start: logged as 0, nothing computed
                terms["lpips"] = torch.zeros((), device=render.device)
                return terms
            if share is None:
                rows, offsets = self.draw(render.shape[0])
                count = None
            else:
                rows, offsets, count = share.lpips_rows, share.lpips_offsets, share.lpips_count
                if rows is not None and len(rows) == 0:  # none of the iteration's LPIPS views is among these
                    terms["lpips"] = torch.zeros((), device=render.device)
                    return terms
            if rows is not None and len(rows) < render.shape[0]:
                pick = host_to_device(rows, render.device)
                render, images, masks, band = (t[pick] for t in (render, images, masks, band))
            x, y = (apply_band(im, band, self.background).permute(0, 3, 1, 2) for im in (render, images))
            offsets = None if offsets is None else host_to_device(offsets, x.device)
            terms["lpips"] = lpips_views(self.lpips, x, y, masks, self.background, self.cfg.lpips_form, self.cfg.lpips_crop,
                                         offsets, self.cfg.lpips_crop_sliced, count)
            terms["total"] = terms["total"] + self.cfg.weight_lpips * terms["lpips"]
        return terms


def iteration_loss(model, batch: TrainingBatch, loss: LossTerms, raster: RasterizerConfig, background: torch.Tensor,
                   batched: bool, phase: Callable[[str], AbstractContextManager]) -> dict[str, torch.Tensor]:
    """Eq. 15 averaged over the views of one iteration's batch (each view weighs the same)."""
    with phase("model"):
        g = model(batch.timestep_tensor(background.device), batch.lod)
    uniform = batch.uniform() if batched else None
    if uniform is not None:
        viewmats, Ks, images, masks, width, height, bands = uniform
        with phase("render"):
            out = render_timesteps(g.means, g.quats, g.scales, g.opacities, g.sh, viewmats, Ks, width, height, background,
                                   backend=raster.backend, max_pairs=raster.max_pairs)
        with phase("loss"):
            return loss(out.color.flatten(0, 1), images, masks, height, bands)
    # A loss evaluation per view batch, each its views' part of the iteration's mean; the LPIPS term's views and
    # windows drawn once for the iteration, as the evaluation of all views above draws them.
    place, total = batch.places()
    parts = [(k, np.array([place[(k, cam)] for cam in vb.cameras]), vb)
             for k, step_batches in enumerate(batch.views) for vb in step_batches]
    share_of = lpips_shares(loss, total, [(positions, vb.masks) for _, positions, vb in parts], lambda count: count)
    totals: dict[str, torch.Tensor] = {}
    for k, positions, vb in parts:
        with phase("render"):
            out = render_gaussians(g.means[k], g.quats[k], g.scales[k], g.opacities[k], g.sh[k], vb.viewmats, vb.Ks,
                                   vb.width, vb.height, background, backend=raster.backend, max_pairs=raster.max_pairs)
        with phase("loss"):
            for key, value in loss(out.color, vb.images, vb.masks, vb.height, vb.bands, share_of(positions)).items():
                totals[key] = totals.get(key, 0) + value
    return totals


def fit(capture_dir: Path, output_dir: Path, preset_name: str = DEFAULT_PRESET, variant: str = "pig",
        device: torch.device | str = "cpu", on_iteration: Callable[[int], None] | None = None,
        phase: Callable[[str], AbstractContextManager] | None = None, overwrite: bool = False,
        threads: int | None = None, progress_s: float = LOG_INTERVAL_S, tensorboard: bool = False,
        clock: Callable[[], float] = time.perf_counter) -> Path:
    """Fit (or resume fitting) and write `output_dir`/avatar.pt; returns its path.

    `threads`: torch CPU threads of a CPU fit in place of the preset's `fit.cpu_threads`. A progress line
    (pig.avatar.fit_progress) goes to stderr every `progress_s` seconds and at each held-out evaluation, which
    also redraws train_log.png; `tensorboard` adds TensorBoard scalars under `output_dir`/tensorboard/.

    One process on `device`; pig.avatar.parallel_fit.fit_parallel fits on several GPUs at once.

    Files of the same names in `output_dir` (OUTPUT_FILES) are replaced only when it is a fit output folder,
    or with `overwrite`.

    `on_iteration(i)` is called after iteration i (1-based) is complete and checkpointed if due.
    `phase(name)` wraps each part of an iteration ("sample": waiting for the iteration's views, "model",
    "render", "loss", "backward", "step", and in a data-parallel fit "reduce", the wait for the gradients'
    all-reduce, and with `fit.shard_solves` "solve_forward" and "solve_backward", the solves this rank owns
    ("solve_forward.own", "solve_backward.own", inside them) and the wait for the others' broadcasts,
    pig.avatar.distributed.SolveShards; render and loss once per view batch, or once
    with `batched_render`): a hook for profilers (benchmarks/fit_gpu.py). The wait for the views is also logged
    (train_log.csv's data_wait_ms) and its mean printed at the end. `clock` (seconds) times the fit: its training
    seconds (train_s, what `fit.time_budget_s` counts; pig.avatar.training_clock), the checkpoint cadence and the
    plot redraws.
    """
    callers_threads = torch.get_num_threads()
    callers_deterministic = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    callers_fill = torch.utils.deterministic.fill_uninitialized_memory
    try:
        with output_lock(Path(output_dir), "fit"):  # two fits into one folder: the second is refused, naming the first
            return _fit(Path(capture_dir), Path(output_dir), preset_name, variant,
                        resolve_device(str(device), "--device"), on_iteration, phase or (lambda name: nullcontext()),
                        overwrite, threads, progress_s, tensorboard, clock)
    finally:
        torch.set_num_threads(callers_threads)
        torch.use_deterministic_algorithms(callers_deterministic[0], warn_only=callers_deterministic[1])
        torch.utils.deterministic.fill_uninitialized_memory = callers_fill


def use_deterministic_kernels(device: torch.device, requested: bool) -> None:
    """Deterministic torch kernels for a CPU fit always, on a GPU when `requested` (fit.deterministic).

    On the CPU the one kernel that differed between runs (measured: benchmarks/NOTES.md, "Fit", "Bit-identical CPU fits") is
    index_put_ with accumulate, the backward of advanced indexing (the transport's vertex gathers): with more than
    one thread it adds into shared vertices with atomics, in whatever order the threads reach them; in
    deterministic mode it adds serially. Deterministic mode also fills many ops' new outputs with NaN before the op
    writes them (a guard against kernels that read uninitialised memory): on the CPU that fill is left out, ~0.95x a
    step with the same weights (benchmarks/NOTES.md, "The first run"; tests/test_reproducible.py checks them)."""
    if device.type == "cpu":
        torch.use_deterministic_algorithms(True)
        torch.utils.deterministic.fill_uninitialized_memory = False
    elif requested:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # cuBLAS's deterministic workspace
        torch.use_deterministic_algorithms(True, warn_only=True)


def fit_rank(capture_dir: Path, output_dir: Path, preset_name: str, variant: str, parallel: Parallel,
             on_iteration: Callable[[int], None] | None, phase: Callable[[str], AbstractContextManager] | None,
             progress_s: float, tensorboard: bool) -> Path:
    """One process of a data-parallel fit (pig.avatar.parallel_fit.fit_parallel, which claimed `output_dir`); its
    clock is `parallel.clock`, rank 0's deciding for all."""
    return _fit(capture_dir, output_dir, preset_name, variant, parallel.device, on_iteration,
                phase or (lambda name: nullcontext()), False, None, progress_s, tensorboard, parallel.clock, parallel)


def _fit(capture_dir: Path, output_dir: Path, preset_name: str, variant: str, device: torch.device,
         on_iteration: Callable[[int], None] | None, phase: Callable[[str], AbstractContextManager],
         overwrite: bool, threads: int | None, progress_s: float, tensorboard: bool, now: Callable[[], float],
         parallel: Parallel | None = None) -> Path:
    preset = load_preset(preset_name)
    overrides = variant_overrides(preset, variant)
    unknown = sorted(set(overrides) - {"avatar", "fit", "field", "precond", "rasterizer"})
    if unknown:
        raise ConfigError(f"{preset['_path']}: variant {variant!r} overrides unknown section(s) {unknown}")
    avatar_cfg = load_section(preset, "avatar", AvatarConfig, overrides.get("avatar"))
    fit_cfg = load_section(preset, "fit", FitConfig, overrides.get("fit"))
    if threads is not None:
        fit_cfg = replace(fit_cfg, cpu_threads=threads)
    field_cfg = load_section(preset, "field", FieldConfig, overrides.get("field"))
    precond_cfg = load_section(preset, "precond", PrecondConfig, overrides.get("precond"))
    raster = load_section(preset, "rasterizer", RasterizerConfig, overrides.get("rasterizer"))
    if device.type == "cpu" and fit_cfg.cpu_threads > 0:
        torch.set_num_threads(fit_cfg.cpu_threads)
    use_deterministic_kernels(device, fit_cfg.deterministic)
    lead = parallel is None or parallel.lead  # evaluates, logs and writes
    if parallel is None:
        claim_files(output_dir, OUTPUT_FILES + [TENSORBOARD_DIR] * tensorboard, "fit", (capture_dir,), overwrite)
    state_path = output_dir / "checkpoint.pt"
    avatar_path = output_dir / "avatar.pt"
    log_path = output_dir / "train_log.csv"

    capture = Capture.load(capture_dir, cache_mb=0)  # the view source caches decoded views
    train = capture.split["train"]
    # Per timestep, the cameras with an image and mask of its frame (a missing raw frame has none).
    seen_by = tuple(tuple(c for c in train["cameras"] if capture.has(c, f)) for f in train["frames"])
    if not any(seen_by):
        raise CaptureError(f"{capture_dir}: no image and mask of the train split (cameras {train['cameras']}) under "
                           "images/ and masks/; rerun preprocess")
    index = [capture.frames.index(f) for f in train["frames"]]
    params = perturb_params(capture.params.select(index), fit_cfg.sigma_body, fit_cfg.seed)
    spec = {
        "avatar": asdict(avatar_cfg), "field": asdict(field_cfg), "precond": asdict(precond_cfg),
        "body_model_npz": body_model_npz(Path(capture_dir) / "body_model.npz"),
        "params": asdict(params), "frame_ids": [int(f) for f in train["frames"]], "variant": variant,
        "capture": capture.fingerprint(), "capture_dir": str(capture_dir.resolve()),  # the folder: for messages
    }
    settings = {"fit": asdict(fit_cfg), "rasterizer": asdict(raster)}  # the other sections a resume must match
    torch.manual_seed(fit_cfg.seed)
    model = build_avatar(spec).to(device)
    model.decoder.set_precision(fit_cfg.precision, compiled=fit_cfg.compile, mode=fit_cfg.compile_mode)
    if fit_cfg.compile_posing:
        model.compile_posing(fit_cfg.compile_mode)
    optimizers = build_optimizers(model, fit_cfg.lr_decoders, fit_cfg.lr_refine, precond_cfg, fused=fit_cfg.fused_adam)
    base_lrs = [[group["lr"] for group in opt.param_groups] for opt in optimizers]  # the schedule scales these
    average = WeightAverage(optimizers, fit_cfg.average_decay) if fit_cfg.average_decay > 0 else None
    generator = torch.Generator().manual_seed(fit_cfg.seed)  # kept in checkpoints; batches come from (seed, iteration)
    lpips, lpips_record = lpips_term(fit_cfg, device, notify=lead)
    loss_terms = {"lpips": lpips_record}
    # Delayed and ramped grid preconditioning: the grid's lambdas are grid_lambda_scale(i) of the preset's during
    # iteration i (plain steps before `grid_delay`, then the ramp's stages; 1 throughout without either, and form
    # 'none' has no lambdas to schedule). A checkpoint stores the grid under the lambdas of the iteration before it;
    # the final avatar.pt always under the preset's.
    lambda_scale = precond_cfg.grid_lambda_scale if precond_cfg.form != "none" else lambda iteration: 1.0
    grid_lambdas = precond_cfg.grid_lambdas(len(model.grid.levels))
    scaled_lambdas = lambda scale: [scale * lam for lam in grid_lambdas]
    grid_scale = lambda_scale(0)
    if grid_scale != 1.0:
        model.grid.set_lambdas(scaled_lambdas(grid_scale))

    def set_grid_scale(scale: float) -> None:
        nonlocal grid_scale
        grid_scale = scale
        model.grid.set_lambdas(scaled_lambdas(scale))
        # moments of the weaker smoothing's gradients would damp the new steps for ~1/(1 - beta2) iterations
        for level in model.grid.levels:
            optimizers[0].state.pop(level.param, None)
        if average is not None:  # the grid's tensors were re-based: an average across the switch means nothing
            average.restart()

    start, wall_before, train_before, compile_before, rows = 0, 0.0, 0.0, 0.0, []
    if state_path.exists():
        start, wall_before, rows = load_training_state(state_path, model, optimizers, generator, spec, settings, loss_terms,
                                                       average)
        if lead:
            print(f"fit: resuming {state_path} at iteration {start}", file=sys.stderr)
        # The checkpoint's own row (a save logs one) holds the training seconds so far; older logs lack them.
        train_before = float(rows[-1].get("train_s") or wall_before) if rows else wall_before
        compile_before = float(rows[-1].get("compile_s") or 0.0) if rows else 0.0
        if start > 0 and lambda_scale(start - 1) != grid_scale:  # the stored grid's meaning: its lambdas then
            grid_scale = lambda_scale(start - 1)
            model.grid.set_lambdas(scaled_lambdas(grid_scale), keep_values=False)
    if parallel is not None:
        parallel.check_replicas(model, f"at iteration {start}")

    background = torch.as_tensor(capture.background, dtype=torch.float32, device=device)
    loss = LossTerms(fit_cfg, background, lpips, fit_cfg.compile)

    def checkpoint(path: Path, iteration: int, clock: TrainingClock) -> None:
        broken = [name for name, t in model.state_dict().items() if t.is_floating_point() and not t.isfinite().all()]
        if broken:  # never written: the last checkpoint stays the last finite one
            raise _diverged(f"NaN or infinite weights in {broken[:3]}", iteration, state_path)
        with clock.excluding("checkpoint"):
            save_checkpoint(path, model, spec, optimizers, generator, iteration, clock.wall(), rows, settings, loss_terms,
                            average)
            _write_log(log_path, rows)

    with ViewSource(capture, train["frames"], device, fit_cfg.view_cache, fit_cfg.loader_workers,
                    loss.band_radius if fit_cfg.host_band else None) as source, \
            _matmul_precision(fit_cfg.precision), \
            closing(FitProgress(str(output_dir), fit_cfg.iterations, start, progress_s,
                                tensorboard_writer(output_dir / TENSORBOARD_DIR) if tensorboard else None)
                    if lead else SilentProgress()) as report:
        sampler = Sampler(fit_cfg.seed, model.num_levels, seen_by, fit_cfg.timesteps, fit_cfg.views)
        if parallel is not None:  # each rank stages only its part of an iteration's views
            sampler = ShardedSampler(sampler, parallel.rank, parallel.world)
        batches = TrainingBatches(source, sampler, fit_cfg.iterations, fit_cfg.prefetch)
        held_out = HeldOut(capture, model, source, fit_cfg.eval_frames, fit_cfg.views)
        probe = (Probe(capture, model, source, fit_cfg.probe_views, fit_cfg.probe_scale)
                 if fit_cfg.probe_every and lead else None)

        last_draw = -math.inf

        def evaluate_held_out(row: dict, full: bool, probing: bool, shown: list[dict]) -> float:
            """The held-out evaluations due into `row`, then train_log.png redrawn from `shown` (to watch the fit)
            where due (REDRAW_S); returns the seconds both took, also the row's eval_s."""
            nonlocal last_draw
            t0 = now()
            averaged = average is not None and average.started
            if full and averaged:
                row["heldout_psnr_iterate"] = held_out.psnr(model, raster)
            with average.applied() if averaged else nullcontext():
                if full:
                    row["heldout_psnr"] = held_out.psnr(model, raster)
                if probing:
                    row["probe_psnr"] = probe.psnr(model, raster)
            if full or now() - last_draw >= REDRAW_S:
                plot_train_log(output_dir / "train_log.png", shown, str(output_dir))
                last_draw = now()
            row["eval_s"] = round(now() - t0, 3)
            return row["eval_s"]

        if start == 0:
            rows = [{"iteration": 0, "wall_s": 0.0, "train_s": 0.0, "lod": "", "loss": "", "l1": "", "ssim": "", "lpips": "",
                     "lpips_term": lpips_record["state"], **dict.fromkeys(EVALUATION_COLUMNS, ""), "data_wait_ms": "",
                     "compile_s": 0.0}]
            if lead:
                evaluate_held_out(rows[0], *evaluations_due(fit_cfg, 0), rows)
            report.record(rows[0])
            report.print_line(0, 0.0)

        reducer = None if parallel is None else parallel.reduce_gradients(model)
        shards = (SolveShards(model, parallel.rank, parallel.world) if parallel is not None and fit_cfg.shard_solves
                  else None)  # each preconditioned solve on one rank
        clock = TrainingClock(wall_before, train_before, now)
        last_save = now()
        waits = []
        window: dict[str, torch.Tensor] = {}  # loss terms summed on the device since the last logged row
        window_waits: list[float] = []

        def window_row(iteration: int, lod) -> dict:
            """The log row of the iterations since the last one (means), and a fresh window. Reading the loss back
            waits for the device: once per logged row."""
            nonlocal window, window_waits
            count = max(len(window_waits), 1)
            if parallel is not None:
                window = parallel.sum_terms(window)
            row = {"iteration": iteration, "wall_s": round(clock.wall(), 3), "train_s": round(clock.training(), 3),
                   "compile_s": round(compile_before + clock.excluded["compilation"], 3), "lod": lod,
                   "lpips_term": lpips_record["state"], **dict.fromkeys(EVALUATION_COLUMNS, ""),
                   "data_wait_ms": round(1000 * float(np.mean(window_waits or [0.0])), 3),
                   **{key: window[name].item() / count if name in window else "" for key, name in
                      (("loss", "total"), ("l1", "l1"), ("ssim", "ssim"), ("lpips", "lpips"))}}
            window, window_waits = {}, []
            return row

        def fraction_done(i: int) -> tuple[float, float]:
            """(training seconds so far, the run's fraction done before iteration i: iterations or time budget)."""
            trained = clock.training()
            if fit_cfg.time_budget_s is None:
                return trained, i / fit_cfg.iterations
            return trained, max(i / fit_cfg.iterations, trained / fit_cfg.time_budget_s)

        iteration = start
        for i in range(start, fit_cfg.iterations):
            trained, done = fraction_done(i)
            stop = fit_cfg.time_budget_s is not None and trained >= fit_cfg.time_budget_s
            if parallel is not None:  # rank 0's clock decides for every rank
                stop, done = parallel.decide(stop, done, sampler.picks(i).share.digest, i)
            if stop:
                break
            if (scale := lambda_scale(i)) != grid_scale:
                set_grid_scale(scale)
            factor = lr_factor(done, i, fit_cfg.lr_warmup, fit_cfg.lr_final)
            anchor_factor = factor * precond_cfg.anchor_lr_scale(i)
            for opt, lrs in zip(optimizers, base_lrs):
                for group, lr in zip(opt.param_groups, lrs):
                    group["lr"] = lr * (anchor_factor if group.get("name") == "anchors" else factor)
            loss.at(i, done)
            if fit_cfg.compile_mode == "reduce-overhead":  # the last step's graph outputs may be overwritten from here
                torch.compiler.cudagraph_mark_step_begin()
            with phase("sample"):
                batch = batches.get(i)
            waits.append(batch.wait_s)
            window_waits.append(batch.wait_s)
            with clock.iteration():  # a step that compiles a graph counts as compilation, not training
                if parallel is None:
                    terms = iteration_loss(model, batch, loss, raster, background, fit_cfg.batched_render, phase)
                else:
                    if shards is not None:
                        with phase("solve_forward"):
                            shards.solve_forward(phase)
                    terms = shard_loss(model, batch, loss, raster, background, phase, parallel)
                with phase("backward"):
                    for opt in optimizers:
                        opt.zero_grad(set_to_none=True)
                    terms["total"].backward()
                if reducer is not None:
                    with phase("reduce"):
                        reducer.finish()
                if shards is not None:
                    with phase("solve_backward"):
                        shards.solve_backward(phase)
                with phase("step"):
                    for opt in optimizers:
                        opt.step()
                    if average is not None and done >= fit_cfg.average_start:
                        average.update()
            for key, value in terms.items():
                window[key] = window.get(key, 0) + value.detach()

            iteration = i + 1
            full, probing = evaluations_due(fit_cfg, iteration)
            evaluate = full or probing
            save = iteration < fit_cfg.iterations and now() - last_save > 60 * fit_cfg.checkpoint_minutes
            if parallel is not None:
                save = bool(parallel.shared(save)[0])
            if evaluate or save or iteration % fit_cfg.log_every == 0:
                row = window_row(iteration, batch.lod)
                if not math.isfinite(row["loss"]):  # read back anyway: a diverged fit stops here, not at the end
                    raise _diverged(f"the training loss is {row['loss']}", iteration, state_path)
                if evaluate and lead:
                    with clock.excluding("evaluation"):
                        evaluate_held_out(row, full, probing, rows + [row])
                rows.append(row)
                report.record(row)
            report.step(iteration, min(fraction_done(iteration)[1], 1.0), evaluate)
            if save:
                if parallel is not None:
                    parallel.check_replicas(model, f"at iteration {iteration}")
                if lead:
                    checkpoint(state_path, iteration, clock)
                last_save = now()
            if on_iteration is not None:
                on_iteration(iteration)
        else:
            iteration = fit_cfg.iterations
        if rows[-1]["iteration"] != iteration:  # stopped by the time budget between logged rows
            rows.append(window_row(iteration, ""))
        if lead and rows[-1]["heldout_psnr"] == "":  # the fit ends with an evaluation, wherever the budget stopped it
            with clock.excluding("evaluation"):
                evaluate_held_out(rows[-1], True, probe is not None and rows[-1].get("probe_psnr", "") == "", rows)
            report.record(rows[-1])
        report.finish(iteration)
    if waits and lead:
        per_iteration = (clock.training() - train_before) / len(waits)
        print(f"fit: data wait {1000 * np.mean(waits):.1f} ms per iteration on average ({100 * np.mean(waits) / per_iteration:.1f} % "
              f"of {1000 * per_iteration:.0f} ms) over {len(waits)} iterations; {source.decoded} views decoded, "
              f"{source.hits} from the cache, at most {source.peak_held} decoded views held", file=sys.stderr)
    if clock.excluded and lead:
        print("fit: left out of the training seconds: " + ", ".join(f"{kind} {seconds:.1f} s" for kind, seconds in
                                                                    sorted(clock.excluded.items())), file=sys.stderr)

    if grid_scale != 1.0:  # stopped before the ramp's end: store the grid under the preset's lambdas
        set_grid_scale(1.0)
    if parallel is not None:
        reducer.close()
        if shards is not None:
            shards.close()
        parallel.check_replicas(model, f"at the end (iteration {iteration})")
        if not lead:
            return avatar_path
    iterate_path = output_dir / ITERATE_FILE
    if average is not None and average.started:
        checkpoint(iterate_path, iteration, clock)
    else:  # an earlier fit's iterate in this fit's folder would not belong to this avatar.pt
        iterate_path.unlink(missing_ok=True)
    with average.applied() if average is not None else nullcontext():  # avatar.pt holds the weights evaluated
        checkpoint(avatar_path, iteration, clock)
    state_path.unlink(missing_ok=True)
    return avatar_path
