"""Preconditioned parameters: a tensor whose updates are filtered by (I + lambda L)^-2, in two application forms.

Implements the dual-level update rules of Eqs. 4-5 (grid levels: lattice L_g; anchors: KNN L_knn).

Forms (`PrecondConfig.form`, preset section `precond`):
- "filter": the stored parameter is x; backward replaces dL/dx by (I + lambda L)^-2 dL/dx, then the
  optimizer steps x. Under plain gradient descent this is Eqs. 4-5 verbatim.
- "substitute": the stored parameter is u = (I + lambda L) (x - x0) (Large Steps, taken relative to the
  initial value x0, the buffer `origin`); forward solves x = x0 + (I + lambda L)^-1 u and backward solves
  the same symmetric system, so dL/du = (I + lambda L)^-1 dL/dx and a gradient step on u moves x by
  -lr (I + lambda L)^-2 dL/dx: again Eqs. 4-5 under gradient descent. u starts at exactly 0, so x0 comes
  back exactly for any lambda. Storing u = (I + lambda L) x instead (the predecessor's choice; the same
  gradient path, since only u's increments reach the optimiser) rounded A x0 to float32 and shifted the
  recovered initial anchors (100k) by up to 5 mm at lambda = 1e6 and 1.1 m at lambda = 1e8.
  An all-zero start (the latent grid's default) stores no origin. A state dict without `origin` (written
  before origins existed) loads as x0 = 0, which is what it meant.
- "none": a plain parameter (the no-preconditioning ablation).
The forms differ under Adam, whose per-element scaling sits between the two solves; UniformAdam
(pig.field.optim) keeps one scale per tensor and so keeps the filter. The default, "substitute" with
Adam at the paper's learning rates, is the one the toy fits of benchmarks/precond.py chose
(benchmarks/NOTES.md, "Preconditioning").

Use: `p = PreconditionedTensor(x0, system, form)`; `p()` returns x (differentiable); optimise
`p.param`; `p.set_value(x)` overwrites x; `p.bake()` freezes the current x as a plain tensor. Call
`p()` once per optimisation step and reuse the result: every call runs the solves. A data-parallel fit may
take the solves out of the autograd pass (`defer_gradient`, `give`, `solve_offset`, `precondition_gradient`) to
run each on one rank (pig.avatar.distributed.SolveShards); the math is the same. A system is any
object with `solve(b, slot) -> A^-1 b` and `apply(x) -> A x` (LatticeSystem, FactorizedSystem,
CGSystem); `slot` names the warm start an iterative solver reuses.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import torch
from torch import nn

from pig.config import ConfigError

from .knn_graph import knn_laplacian
from .knn_solve import CGSystem, FactorizedSystem

Form = Literal["filter", "substitute", "none"]
FORMS = ("filter", "substitute", "none")


class LinearSystem(Protocol):
    def solve(self, b: torch.Tensor, slot: str | None = None) -> torch.Tensor: ...

    def apply(self, x: torch.Tensor) -> torch.Tensor: ...


@dataclass
class PrecondConfig:
    """Preset section `precond`: how the latent grid and the anchors are preconditioned and optimised."""

    form: Form = "substitute"
    optimizer: Literal["adam", "uniform_adam", "sgd"] = "adam"
    grid_lr: float = 1e-2  # level g (0 = coarsest) uses grid_lr * grid_lr_growth ** g
    grid_lr_growth: float = 1.5
    grid_lambda: float = 2.0  # level g uses grid_lambda * grid_lambda_growth ** g
    grid_lambda_growth: float = 1.25
    grid_solver: Literal["matmul", "fft"] = "matmul"
    anchor_lr: float = 2e-5
    anchor_lambda: float = 8.0
    knn_k: int = 8
    knn_solver: Literal["factorized", "cg"] = "factorized"
    cg_tol: float = 1e-5
    cg_max_iter: int = 200
    cg_check_every: int = 1  # CG tests its residual (a host synchronisation) every this many iterations
    cg_compile: bool = False  # CG iterations compiled with torch.compile (speed lever, pig/field/knn_solve.py)
    cg_graphs: bool = False  # on CUDA, each block of cg_check_every iterations replayed as one CUDA graph (speed lever)
    # CG without a blocking read (speed lever, off until the GPU measures it): each solve runs a number of blocks of
    # cg_check_every iterations chosen from the same slot's previous solve, whose residuals reach the host without
    # the host waiting (pig/field/knn_solve.py, CGSystem._solve_lagged); the iterations differ from the checked CG's.
    cg_lagged: bool = False
    # Iterations before the grid's Sobolev preconditioning starts (0: from the first, as the paper). Until then the
    # grid levels take plain steps (lambda 0), so features local to the loose garment form early; at the switch each
    # level keeps its values and its optimiser state restarts (pig.avatar.training). The anchors are not delayed;
    # form 'none' has nothing to delay.
    grid_delay: int = 0
    # Iterations after grid_delay over which the grid's lambdas ramp from 0 to the preset's, in grid_ramp_stages equal
    # steps (0: no ramp). Each stage re-bases the grid and restarts its moments, as grid_delay's switch does, so the
    # stages are few; grid_delay alone is the ramp of one stage.
    grid_ramp: int = 0
    grid_ramp_stages: int = 4
    # Iterations over which the anchors' learning rate ramps linearly from 0, on top of the fit's schedule (0: none,
    # the paper's).
    anchor_warmup: int = 0
    # Adam's eps of the field optimiser ("adam", "uniform_adam"; the decoders keep theirs). The grid's gradients are
    # of its order (1e-9..1e-6 per cell, smaller still after the substitution's solve), so it damps the fine levels'
    # steps (benchmarks/NOTES.md, "Fit", issue 38); 1e-8 is torch's default, which the paper does not change.
    adam_eps: float = 1e-8

    def __post_init__(self):
        for key in ("grid_delay", "grid_ramp", "anchor_warmup"):
            if getattr(self, key) < 0:
                raise ConfigError(f"precond.{key} must be at least 0, found {getattr(self, key)}")
        if self.grid_ramp_stages < 1:
            raise ConfigError(f"precond.grid_ramp_stages must be at least 1, found {self.grid_ramp_stages}")
        if not self.adam_eps > 0:
            raise ConfigError(f"precond.adam_eps must be positive, found {self.adam_eps}")

    def grid_lrs(self, levels: int) -> list[float]:
        return [self.grid_lr * self.grid_lr_growth**g for g in range(levels)]

    def grid_lambdas(self, levels: int) -> list[float]:
        return [self.grid_lambda * self.grid_lambda_growth**g for g in range(levels)]

    def grid_lambda_scale(self, iteration: int) -> float:
        """The fraction of grid_lambdas in effect during `iteration`: 0 before grid_delay, then the ramp's stage
        (k / stages for the k-th of grid_ramp's equal parts, the first plain), 1 from grid_delay + grid_ramp on."""
        since = iteration - self.grid_delay
        if since < 0:
            return 0.0
        if since >= self.grid_ramp:
            return 1.0
        return (since * self.grid_ramp_stages // self.grid_ramp) / self.grid_ramp_stages

    def anchor_lr_scale(self, iteration: int) -> float:
        """The anchors' warm-up factor during `iteration` (1 once anchor_warmup iterations have passed)."""
        return min(1.0, (iteration + 1) / self.anchor_warmup) if self.anchor_warmup else 1.0


class SubstitutionSolve(torch.autograd.Function):
    """x = A^-1 u; the backward pass solves with the same (symmetric) A."""

    @staticmethod
    def forward(ctx, u: torch.Tensor, system: LinearSystem) -> torch.Tensor:
        ctx.system = system
        return system.solve(u.detach(), "forward")

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        return ctx.system.solve(grad, "backward"), None


class FilteredGradient(torch.autograd.Function):
    """Identity in forward; backward returns A^-2 grad (two solves)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, system: LinearSystem) -> torch.Tensor:
        ctx.system = system
        return x.view_as(x)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        return ctx.system.solve(ctx.system.solve(grad, "filter1"), "filter2"), None


class PassGradient(torch.autograd.Function):
    """x - x0 = `offset`, solved elsewhere; the backward passes dL/dx to u unsolved (the deferred gradient)."""

    @staticmethod
    def forward(ctx, u: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        return offset

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        return grad, None


class PreconditionedTensor(nn.Module):
    """Holds the optimised tensor `param` (x, or u = A (x - origin) for "substitute"); `forward()` returns x."""

    def __init__(self, value: torch.Tensor, system: LinearSystem | None, form: Form):
        super().__init__()
        if form not in FORMS:
            raise ValueError(f"PreconditionedTensor: expected form in {FORMS}, found {form!r}")
        if form != "none" and system is None:
            raise ValueError(f"PreconditionedTensor: form {form!r} needs a linear system")
        self.form = form
        self.system = system
        value = value.detach()
        self.param = nn.Parameter(torch.zeros_like(value) if form == "substitute" else value.clone())
        self.register_buffer("origin", _origin_of(value) if form == "substitute" else None)
        # With `defer_gradient` the backward leaves dL/dx unsolved in `param.grad`, for whoever set it to apply
        # `precondition_gradient` (after summing it over ranks); `give` hands the next forward its solved offset.
        self.defer_gradient = False
        self._given: tuple[torch.Tensor, int] | None = None

    def forward(self) -> torch.Tensor:
        if self.form == "substitute":
            if self.defer_gradient:
                offset = PassGradient.apply(self.param, self._take_given())
            else:
                offset = SubstitutionSolve.apply(self.param, self.system)
            return offset if self.origin is None else self.origin + offset
        if self.form == "filter":
            return self.param if self.defer_gradient else FilteredGradient.apply(self.param, self.system)
        return self.param

    def solve_offset(self) -> torch.Tensor:
        """x - x0 = A^-1 u of the substitution form, detached: the forward's solve."""
        return self.system.solve(self.param.detach(), "forward")

    def precondition_gradient(self, grad: torch.Tensor) -> torch.Tensor:
        """The backward's gradient of `param` for dL/dx = `grad`: A^-1 grad ("substitute"), A^-2 grad ("filter")."""
        if self.form == "substitute":
            return self.system.solve(grad, "backward")
        if self.form == "filter":
            return self.system.solve(self.system.solve(grad, "filter1"), "filter2")
        return grad

    def give(self, offset: torch.Tensor) -> None:
        """`offset` = A^-1 u of the current u, solved elsewhere: the next forward returns it instead of solving."""
        self._given = (offset, self.param._version)

    def _take_given(self) -> torch.Tensor:
        """The offset given for u as it is now (once), else solved here: a given one of an older u is never used."""
        given, self._given = self._given, None
        if given is not None and given[1] == self.param._version:
            return given[0]
        return self.solve_offset()

    @torch.no_grad()
    def set_value(self, value: torch.Tensor) -> None:
        """Make x = value; the substitution form moves its origin there and restarts u at 0."""
        value = value.to(self.param)
        if self.form == "substitute":
            self.origin = _origin_of(value)
            self.param.zero_()
        else:
            self.param.copy_(value)

    @torch.no_grad()
    def bake(self) -> None:
        """Store the current x as a plain frozen tensor (form "none"): no solves when only x is needed."""
        value = self().detach().clone()
        self.form = "none"
        self.origin = None
        self.param = nn.Parameter(value, requires_grad=False)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # The state dict says whether there is an origin (a zero start, or one written before origins, has none).
        if self.form == "substitute":
            stored = state_dict.get(prefix + "origin")
            like = self.param
            self.origin = None if stored is None else torch.empty(stored.shape, dtype=like.dtype, device=like.device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return f"form={self.form}, shape={tuple(self.param.shape)}"


def _origin_of(value: torch.Tensor) -> torch.Tensor | None:
    """The substitution origin for an initial value: None for all zeros (x = A^-1 u needs none)."""
    return value.detach().clone() if bool(value.ne(0).any()) else None


def knn_system(points: torch.Tensor, cfg: PrecondConfig) -> FactorizedSystem | CGSystem:
    """I + lambda_knn L_knn on the symmetrised KNN graph of `points` (N, 3), with the configured solver."""
    laplacian = knn_laplacian(points.detach().to("cpu", torch.float64).numpy(), cfg.knn_k)
    if cfg.knn_solver == "factorized":
        return FactorizedSystem(laplacian, cfg.anchor_lambda)
    return CGSystem(laplacian, cfg.anchor_lambda, tol=cfg.cg_tol, max_iter=cfg.cg_max_iter, check_every=cfg.cg_check_every,
                    compiled=cfg.cg_compile, graphs=cfg.cg_graphs, lagged=cfg.cg_lagged)


def precondition_anchors(points: torch.Tensor, cfg: PrecondConfig) -> PreconditionedTensor:
    """Anchor positions (N, 3) as a PreconditionedTensor coupled by the KNN graph of these initial points."""
    system = None if cfg.form == "none" else knn_system(points, cfg)
    return PreconditionedTensor(points, system, cfg.form)


@torch.no_grad()
def bake_preconditioning(model: nn.Module) -> None:
    """Store each preconditioned tensor's current value x in place of its optimised variable, in all of `model`.

    Rendering needs only x; with the substitution form x = (I + lambda L)^-1 u would otherwise be
    solved again for every frame, which is training machinery, not per-frame work."""
    for module in model.modules():
        if isinstance(module, PreconditionedTensor) and module.form != "none":
            module.bake()
