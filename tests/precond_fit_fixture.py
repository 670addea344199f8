"""A real fit (pig.avatar.training.fit) of the `paper` preset's preconditioning, observed step by step.

The preset's `precond` and `field` sections are the `paper` preset's as they stand (the grid's six levels of 8..88
cells and 16 features, lambdas, rates, the KNN graph, the CG solver); what a CPU test cannot afford is shrunk: the
anchors, decoders and views (`avatar`, `fit`), and the speed levers that compile (`fit.compile`, `compile_posing`,
`precision`, `precond.cg_compile`) are off. The fit builds its model and optimisers itself; `observe_fit` wraps
`build_optimizers` to see them, and records per step what each preconditioned tensor's loss gradient dL/dx was,
what the optimiser saw (its parameter's gradient), the rate it stepped with, and x after the step.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest
import torch

import pig.avatar.training as training
from pig.config import derive_preset


def paper_test_preset(path: Path, iterations: int, precond: dict | None = None) -> str:
    """The `paper` preset with CPU-test sizes (see the module docstring), written to `path`; returns its path."""
    return str(derive_preset(
        path, "paper",
        avatar=dict(num_anchors=1200, levels=2, sh_degree=1, hidden_layers=2, hidden_width=32, refine_hidden_layers=2,
                    refine_hidden_width=16),
        fit=dict(iterations=iterations, views=2, timesteps=2, weight_lpips=0.0, eval_every=10**6, eval_frames=1,
                 checkpoint_minutes=10**6, compile=False, compile_posing=False, precision="float32",
                 lpips_compile=False, view_cache=64, loader_workers=1, prefetch=1, cpu_threads=1),
        precond=dict(cg_compile=False, **(precond or {}))))


@dataclass
class FitRecord:
    model: torch.nn.Module = None
    optimizers: list = None
    names: dict = field(default_factory=dict)  # preconditioned tensor module -> "grid<g>" / "anchors"
    x0: dict = field(default_factory=dict)  # name -> x before the first step
    # Per step {"dx", "grad", "lr", "x", "param"}, each {name: ...}: dL/dx, the optimised variable's gradient, the
    # rate, x and that variable after the step.
    steps: list = field(default_factory=list)
    systems: dict = field(default_factory=dict)  # name -> the system object at build time


class _Built(Exception):
    """Stops a fit once its model and optimisers are built (`observe_fit(..., build_only=True)`)."""


def observe_fit(capture: Path, out: Path, preset: str, variant: str = "pig", build_only: bool = False,
                device: str = "cpu", gradients_only: bool = False) -> FitRecord:
    """Run the fit and return what it did to its grid levels and anchors, step by step; with `build_only`, stop
    before its first step (the record holds the model and optimisers as the fit built them, no steps);
    `gradients_only`: per step only dL/dx and the rates (a long fit's record in a bounded memory)."""
    record = FitRecord()
    pending: dict[str, torch.Tensor] = {}
    real_build = training.build_optimizers

    def build(model, *args, **kwargs):
        optimizers = real_build(model, *args, **kwargs)
        record.model, record.optimizers = model, optimizers
        for g, level in enumerate(model.grid.levels):
            record.names[level] = f"grid{g}"
        if model.anchors is not None:
            record.names[model.anchors] = "anchors"
        for module, name in record.names.items():
            record.systems[name] = module.system
            with torch.no_grad():
                record.x0[name] = module().detach().to("cpu", torch.float64).clone()
            # The fit's gradients are float32: kept so where memory is bounded, else in float64 for the references.
            dtype = torch.float32 if gradients_only else torch.float64
            module.register_forward_hook(_keep_gradient_of_x(name, pending, dtype))
        field_opt = optimizers[0]
        params = {module.param: name for module, name in record.names.items()}
        module_of = {module.param: module for module in record.names}

        def before_step(opt, args, kwargs):
            lrs = {params[p]: group["lr"] for group in opt.param_groups for p in group["params"]}
            grads = {params[p]: p.grad.detach().to("cpu", torch.float64).clone() for p in params
                     if p.grad is not None and (module_of[p].form == "none" or not gradients_only)}
            # Form "none": x is the parameter itself, so dL/dx is its gradient (no hook on a leaf needed).
            dx = {name: pending.pop(name, grads.get(name)) for name in params.values()}
            record.steps.append({"dx": dx, "lr": lrs} if gradients_only else {"dx": dx, "grad": grads, "lr": lrs})

        def after_step(opt, args, kwargs):
            if gradients_only:
                return
            with torch.no_grad():
                for key, value in (("x", lambda m: m()), ("param", lambda m: m.param)):
                    record.steps[-1][key] = {name: value(module).detach().to("cpu", torch.float64).clone()
                                             for module, name in record.names.items()}

        field_opt.register_step_pre_hook(before_step)
        field_opt.register_step_post_hook(after_step)
        if build_only:
            raise _Built
        return optimizers

    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.setattr(training, "build_optimizers", build)
        try:
            training.fit(capture, out, preset, variant=variant, device=device)
        except _Built:
            pass
    return record


def _keep_gradient_of_x(name: str, pending: dict, dtype: torch.dtype):
    def hook(module, args, x):
        if x.requires_grad and module.form != "none":  # a training step's x (evaluations run without gradients)
            x.register_hook(lambda grad: pending.__setitem__(name, grad.detach().to("cpu", dtype).clone()))
    return hook
