"""Preset section `fit`: the optimisation's settings (Section 3.6; speed levers, streaming, schedule, averaging).

Its own module so that the checkpoint (pig.avatar.checkpoint), which records the section's defaults, and the fit
loop (pig.avatar.training), which saves checkpoints, import it without importing each other.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from pig.avatar.losses import LPIPS_FORMS
from pig.config import Bounds, ConfigError
from pig.metrics.lpips import MIN_SIDE

PRECISIONS = ("float32", "tf32", "bf16")
COMPILE_MODES = ("default", "reduce-overhead")


@dataclass
class FitConfig:
    """Preset section `fit`; defaults are the paper's (Section 3.6) with every speed lever off."""

    iterations: Annotated[int, Bounds(ge=1)] = 100_000
    views: Annotated[int, Bounds(ge=1)] = 4  # cameras per timestep per iteration
    timesteps: int = 5  # timesteps per iteration
    lr_decoders: float = 1e-3
    lr_refine: float = 1e-4
    # Learning-rate schedule over the run (every group): linear warm-up from 0 over `lr_warmup` iterations,
    # then exponential decay to `lr_final` times the rate at the end (1.0: constant rates, the paper's).
    # With `time_budget_s` the run's progress is the larger of its iteration and time fractions.
    lr_warmup: int = 0
    lr_final: float = 1.0
    # Weight averaging (pig.avatar.averaging): from progress `average_start` on, an EMA with `average_decay` of the
    # optimised tensors; held-out evaluations and avatar.pt use it. 0: off (the last iterate, the paper's).
    average_decay: float = 0.0
    average_start: float = 0.5
    weight_l1: float = 8.0
    weight_ssim: float = 2.0
    weight_lpips: float = 2.0
    lpips_net: str = "vgg"
    lpips_backbone_weights: str | None = None  # None: the torch hub cache
    lpips_linear_weights: str | None = None
    # "random": a seeded, randomly initialised LPIPS network, no file read; to time the term where the
    # weights are absent (benchmarks only: the loss is not the paper's, and the tables say so).
    lpips_weights: Literal["pretrained", "random"] = "pretrained"
    # What the LPIPS term sees (pig.avatar.losses.lpips_views): "full" frames, or "mmlphuman", MMLPHuman's
    # `lpips_crop`-pixel square of each view's mask box, resized, and random windows of it from progress
    # `lpips_patches_from` on (1: never). The term is 0 before progress `lpips_start` (either form). `lpips_views`:
    # the term on that many views of each loss evaluation, drawn at random (0: all; a different loss, off in `paper`).
    lpips_form: Literal["full", "mmlphuman"] = "full"
    lpips_crop: int = 512
    lpips_start: float = 0.0
    lpips_patches_from: float = 1.0
    lpips_views: int = 0
    band_radius_px: float = 3.0  # silhouette band radius at `band_reference_height` rows (THuman4)
    band_reference_height: int = 1150
    sigma_body: float = 0.0  # robustness study: Gaussian noise on pose (radians) and shape of the input body
    eval_every: Annotated[int, Bounds(ge=1)] = 1000  # held-out novel-view PSNR every this many iterations (and at the end)
    eval_frames: int = 4  # training frames rendered from the novel-view cameras
    # Probes: a cheap held-out PSNR for the error-against-time curve, every `probe_every` iterations and at the start
    # and end (0: off). `probe_views` novel-view (frame, camera) pairs from the middle training frame on, each over
    # its mask box only, rendered at 1/`probe_scale` the resolution against the truth's box-filtered pixels. With
    # probes on, the start gets the probe alone: the full evaluation runs at multiples of `eval_every` and at the end.
    probe_every: int = 0
    probe_views: int = 2
    probe_scale: int = 2
    checkpoint_minutes: float = 5.0
    # Stop after this many seconds of training (the held-out evaluations not counted), before `iterations`
    # if it comes first: the fixed-budget runs of benchmarks/fit_gpu.py. None: no limit.
    time_budget_s: float | None = None
    seed: int = 0
    # Torch threads on the CPU; 0 keeps torch's default. One thread avoids OpenMP spin-waiting when
    # the cores are shared (measured 10x faster under contention, benchmarks/NOTES.md).
    cpu_threads: int = 0
    # Training views are streamed (pig.avatar.batches): `loader_workers` threads decode them `prefetch`
    # iterations ahead of the one trained on, through an LRU cache of `view_cache` decoded views. Host memory
    # holds at most view_cache + (prefetch + 1) x views x timesteps decoded views (4 bytes a pixel), however
    # long the capture. Views are drawn uniformly, so the cache saves decoding only where it holds much of
    # the training set: 256 holds all of the cpu-demo capture's (180) and costs 1.5 GiB at THuman4's
    # 1330 x 1150 (6.1 MB a view), a tenth of the fit rule's mem_mb.
    view_cache: int = 256
    prefetch: int = 2
    loader_workers: int = 4
    # Speed levers (module docstring).
    precision: Literal["float32", "tf32", "bf16"] = "float32"
    compile: bool = False
    # torch.compile's mode for the training step's compiled regions (decoders, posing, L1 + SSIM, LPIPS network):
    # "reduce-overhead" replays each region as CUDA graphs (a graph launch in place of its kernels' launches: the
    # 4-GPU step is bound by its host's launches, benchmarks/NOTES.md, "One fit on several GPUs"), each iteration a
    # new step of torch's CUDA-graph trees. A lever, off until a GPU measures it; no effect on a CPU.
    compile_mode: Literal["default", "reduce-overhead"] = "default"
    compile_posing: bool = False
    batched_render: bool = False
    fused_adam: bool = False
    log_every: int = 1
    host_band: bool = False
    lpips_bf16_head: bool = False
    lpips_compile: bool = False
    lpips_crop_sliced: bool = False
    # A data-parallel fit (`pig fit --gpus N`) solves each preconditioned tensor's systems (Eqs. 4-5) on one rank and
    # broadcasts the result, instead of on every rank (pig.avatar.distributed.SolveShards); the same math. No effect
    # in one process. Off until the GPU scaling table measures it (benchmarks/fit_multi_gpu.py --shard-solves).
    shard_solves: bool = False
    # torch.use_deterministic_algorithms on a GPU fit (a CPU fit always runs so: bit-identical at a fixed thread
    # count). It covers torch's own kernels only, with a warning for those it has no deterministic form of
    # (grid_sample's backward); gsplat's backward sums in a nondeterministic order regardless (docs/gpu.md).
    deterministic: bool = False

    def __post_init__(self):
        for name, least in (("view_cache", 0), ("prefetch", 0), ("loader_workers", 1), ("seed", 0), ("log_every", 1),
                            ("lr_warmup", 0), ("lpips_views", 0), ("probe_every", 0), ("probe_views", 1),
                            ("probe_scale", 1)):
            if getattr(self, name) < least:
                raise ConfigError(f"fit.{name} must be at least {least}, found {getattr(self, name)}")
        if self.precision not in PRECISIONS:
            raise ConfigError(f"fit.precision must be one of {PRECISIONS}, found {self.precision!r}")
        if self.compile_mode not in COMPILE_MODES:
            raise ConfigError(f"fit.compile_mode must be one of {COMPILE_MODES}, found {self.compile_mode!r}")
        if not 0 <= self.average_decay < 1:
            raise ConfigError(f"fit.average_decay must lie in [0, 1), found {self.average_decay}")
        if not 0 <= self.average_start <= 1:
            raise ConfigError(f"fit.average_start must lie in [0, 1], found {self.average_start}")
        if not 0 < self.lr_final <= 1:
            raise ConfigError(f"fit.lr_final must lie in (0, 1], found {self.lr_final}")
        if self.lpips_weights not in ("pretrained", "random"):
            raise ConfigError(f"fit.lpips_weights must be 'pretrained' or 'random', found {self.lpips_weights!r}")
        if self.lpips_weights == "random" and (self.lpips_backbone_weights or self.lpips_linear_weights):
            raise ConfigError("fit.lpips_weights is 'random', which reads no weights file, but fit.lpips_backbone_weights "
                              "or fit.lpips_linear_weights is set; unset them or use 'pretrained'")
        if self.lpips_form not in LPIPS_FORMS:
            raise ConfigError(f"fit.lpips_form must be one of {LPIPS_FORMS}, found {self.lpips_form!r}")
        for name in ("lpips_start", "lpips_patches_from"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"fit.{name} must lie in [0, 1] (a fraction of the run), found {getattr(self, name)}")
        if self.lpips_crop < MIN_SIDE.get(self.lpips_net, 32):
            raise ConfigError(f"fit.lpips_crop must be at least {MIN_SIDE.get(self.lpips_net, 32)} pixels for "
                              f"{self.lpips_net!r}, found {self.lpips_crop}")
        if self.time_budget_s is not None and not self.time_budget_s > 0:
            raise ConfigError(f"fit.time_budget_s must be positive or null, found {self.time_budget_s}")
