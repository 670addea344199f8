"""Avatar checkpoints: the model spec + weights, and for resuming the optimiser, RNG and log state.

Written atomically (temporary name, then rename); `load_avatar` is the render stage's entry. No paper equation.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from pig.stages._io import atomic_path

from .build import build_avatar

FORMAT_VERSION = 1


def save_checkpoint(path: Path, model, spec: dict, optimizers: list, generator: torch.Generator, iteration: int,
                    wall_s: float, log_rows: list[dict], fit_cfg) -> None:
    state = {
        "version": FORMAT_VERSION, "spec": spec, "model": _weights(model),
        "optimizers": [opt.state_dict() for opt in optimizers], "generator": generator.get_state(),
        "torch_rng": torch.get_rng_state(), "iteration": iteration, "wall_s": wall_s, "log": log_rows,
        "fit": asdict(fit_cfg),
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _weights(model) -> dict:
    """The state dict without the body model's buffers, which the spec's body model file rebuilds."""
    return {k: v for k, v in model.state_dict().items() if not k.startswith("body_model.")}


def _load_weights(model, weights: dict, path: Path) -> None:
    missing, unexpected = model.load_state_dict(weights, strict=False)
    missing = [k for k in missing if not k.startswith("body_model.")]
    if missing or unexpected:
        raise ValueError(f"{path}: checkpoint does not match the model (missing {missing[:5]}, unexpected {unexpected[:5]})")


def _read(path: Path, device) -> dict:
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: avatar checkpoint not found (run the fit stage: python -m pig.stages.fit)")
    state = torch.load(path, map_location=device, weights_only=False)
    if not isinstance(state, dict) or state.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path}: not an avatar checkpoint of format version {FORMAT_VERSION}")
    return state


def load_avatar(path: str | Path, device: str | torch.device = "cpu"):
    """The fitted `AvatarModel` of a checkpoint (avatar.pt), on `device`, in eval mode."""
    state = _read(Path(path), "cpu")
    model = build_avatar(state["spec"])
    _load_weights(model, state["model"], path)
    return model.to(device).eval()


def load_training_state(path: Path, model, optimizers: list, generator: torch.Generator, spec: dict, fit_cfg) -> tuple[int, float, list[dict]]:
    """Restore weights, optimisers and RNG from a checkpoint of the same configuration; returns
    (iteration, wall seconds so far, log rows)."""
    state = _read(path, "cpu")
    for key in ("avatar", "field", "precond", "variant", "frame_ids"):
        if state["spec"][key] != spec[key]:
            raise ValueError(f"{path}: checkpoint was written with a different '{key}' configuration; "
                             "delete it to start over or restore the configuration")
    # Run length, logging, checkpoint cadence and view loading may change between runs; the optimisation may not.
    free = {"iterations", "eval_every", "checkpoint_minutes", "view_cache", "prefetch", "loader_workers"}
    changed = sorted(k for k, v in asdict(fit_cfg).items() if k not in free and state["fit"].get(k) != v)
    if changed:
        raise ValueError(f"{path}: checkpoint was written with different fit settings {changed}; delete it to start over")
    _load_weights(model, state["model"], path)
    for opt, opt_state in zip(optimizers, state["optimizers"]):
        opt.load_state_dict(opt_state)  # moves the moments onto the parameters' device
    generator.set_state(state["generator"])
    torch.set_rng_state(state["torch_rng"])
    return state["iteration"], state["wall_s"], state["log"]
