"""Optimisers for the preconditioned field and anchors: Adam, uniform Adam, gradient descent, per-level groups.

The step rules applied after the filters of Eqs. 4-5, with the paper's per-level learning rates (Sec. 4).

`Adam` is standard Adam (bias-corrected moments, eps added to the root of the second moment);
a group with `uniform=True` keeps one scalar second moment per parameter tensor, the running mean of
max_i g_i^2 (the infinity norm, so no element steps further than lr, as with Adam). A uniform scale
leaves the direction of the filtered update untouched, which per-element Adam does not.
`UniformAdam` is `Adam` with `uniform=True` by default. Both run the same code, so measured
differences come from the second moment alone.

Typical use by the fit loop:
    groups = field_param_groups(grid, anchors, precond_cfg)    # [{"name": "grid0", "params": [...], "lr": ...}, ...]
    field_opt = build_optimizer(precond_cfg.optimizer, groups)  # "adam" | "uniform_adam" | "sgd"
    decoder_opt = Adam([{"params": mlp.parameters(), "lr": 1e-3}])
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Iterable

import torch

if TYPE_CHECKING:
    from .latent_grid import LatentGrid
    from .precondition import PrecondConfig, PreconditionedTensor

OPTIMIZERS = ("adam", "uniform_adam", "sgd")


class Adam(torch.optim.Optimizer):
    """Adam; per-group option `uniform` switches to one scalar second moment per tensor (see module docstring)."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8, uniform: bool = False):
        if lr < 0 or eps < 0 or not (0 <= betas[0] < 1 and 0 <= betas[1] < 1):
            raise ValueError(f"Adam: invalid lr={lr}, betas={betas} or eps={eps}")
        super().__init__(params, dict(lr=lr, betas=tuple(betas), eps=eps, uniform=uniform))

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                grad = p.grad
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros((), dtype=p.dtype, device=p.device) if group["uniform"] else torch.zeros_like(p)
                state["step"] += 1
                t = state["step"]
                state["exp_avg"].lerp_(grad, 1 - beta1)
                square = grad.square().max() if group["uniform"] else grad.square()
                state["exp_avg_sq"].mul_(beta2).add_(square, alpha=1 - beta2)
                denom = (state["exp_avg_sq"] / (1 - beta2**t)).sqrt().add_(group["eps"])
                p.addcdiv_(state["exp_avg"], denom, value=-group["lr"] / (1 - beta1**t))
        return loss


class UniformAdam(Adam):
    """Adam with one scalar second moment per parameter tensor (groups may still set uniform=False)."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, lr=lr, betas=betas, eps=eps, uniform=True)


def build_optimizer(kind: str, groups: Iterable[dict], eps: float = 1e-8) -> torch.optim.Optimizer:
    """"adam" -> Adam, "uniform_adam" -> UniformAdam (both with `eps`), "sgd" -> plain gradient descent, over `groups`."""
    groups = list(groups)
    if kind == "adam":
        return Adam(groups, eps=eps)
    if kind == "uniform_adam":
        return UniformAdam(groups, eps=eps)
    if kind == "sgd":
        return torch.optim.SGD(groups, lr=0.0)
    raise ValueError(f"build_optimizer: expected kind in {OPTIMIZERS}, found {kind!r}")


def field_param_groups(grid: "LatentGrid", anchors: "PreconditionedTensor | None", cfg: "PrecondConfig") -> list[dict]:
    """One group per grid level ("grid0" coarsest, lr_g = grid_lr * growth^g) and one "anchors" group."""
    lrs = cfg.grid_lrs(len(grid.levels))
    groups = [{"name": f"grid{g}", "params": [level.param], "lr": lrs[g]} for g, level in enumerate(grid.levels)]
    if anchors is not None:
        groups.append({"name": "anchors", "params": [anchors.param], "lr": cfg.anchor_lr})
    return groups
