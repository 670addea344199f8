"""Avatar checkpoints: the model spec + weights, and for resuming the optimiser, RNG and log state.

Only tensors and plain Python values are stored, so `torch.load(weights_only=True)` reads them and loading
never runs code. A resume is refused unless the capture, the preset sections the fit uses, the variant and
the LPIPS term's state match. Written atomically (temporary name, then rename); `load_avatar` is the render stage's entry, and
`loss_terms` reads the record of which loss terms of Eq. 15 the fit had (pig.avatar.losses.lpips_term).
"""
from __future__ import annotations

import hashlib
import io
import pickle
import zipfile
from dataclasses import MISSING, fields
from pathlib import Path

import numpy as np
import torch

from pig._io import atomic_path
from pig.data.capture_record import require_same_capture
from pig.data.splits import brief

from .averaging import WeightAverage
from .build import build_avatar
from .losses import LPIPS_STATES

FORMAT_VERSION = 2  # 1 held numpy arrays, which only an unrestricted (code-running) unpickler reads
AVATAR_KEYS = ("version", "spec", "model")
TRAINING_KEYS = (*AVATAR_KEYS, "optimizers", "generator", "torch_rng", "iteration", "wall_s", "log", "settings")
# Settings that may change between runs of one fit: run length, logging and checkpoint cadence, view loading (and
# whether its threads compute the loss's band: the same pixels), CPU threads, memory bands, replaying the same CG
# kernels as a CUDA graph, which rank of a data-parallel fit solves what (as the number of ranks: free).
FREE_SETTINGS = {"fit": {"iterations", "eval_every", "probe_every", "checkpoint_minutes", "view_cache", "prefetch",
                         "loader_workers", "log_every", "host_band", "cpu_threads", "shard_solves"},
                 "rasterizer": {"max_pairs"}, "precond": {"cg_graphs"}}
SPEC_SECTIONS = ("avatar", "field", "precond")  # preset sections recorded in the spec


class CheckpointError(ValueError):
    """A checkpoint file is unreadable, of another format, or belongs to another fit."""


def save_checkpoint(path: Path, model, spec: dict, optimizers: list, generator: torch.Generator, iteration: int,
                    wall_s: float, log_rows: list[dict], settings: dict[str, dict], loss_terms: dict[str, dict],
                    average: WeightAverage | None = None) -> None:
    """Write everything a resume needs; `spec` (see `build_avatar`) holds the capture's fingerprint under
    "capture", `settings` the other preset sections the fit uses ({"fit": {...}, "rasterizer": {...}}),
    `loss_terms` the records of the fit's loss terms ({"lpips": a record of `lpips_term`}) and `average` the
    fit's weight average, if it keeps one."""
    state = _plain({
        "version": FORMAT_VERSION, "spec": _stored_spec(spec), "model": _weights(model),
        "optimizers": [opt.state_dict() for opt in optimizers], "generator": generator.get_state(),
        "torch_rng": torch.get_rng_state(), "iteration": iteration, "wall_s": wall_s, "log": log_rows,
        "settings": settings, "loss_terms": loss_terms,
        "average": average.state_dict() if average is not None else None,
    }, "state")
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _stored_spec(spec: dict) -> dict:
    """The spec with the body model's npz bytes as a uint8 tensor (written as raw storage; Python bytes are
    pickled, 16x slower and a third larger) and the SMPL-X parameters as tensors."""
    return {**spec, "body_model_npz": torch.frombuffer(bytearray(spec["body_model_npz"]), dtype=torch.uint8),
            "params": {key: torch.from_numpy(np.asarray(value)) for key, value in spec["params"].items()}}


def _loaded_spec(stored: dict) -> dict:
    """Inverse of `_stored_spec`."""
    return {**stored, "body_model_npz": stored["body_model_npz"].numpy().tobytes(),
            "params": {key: value.numpy() for key, value in stored["params"].items()}}


def _weights(model) -> dict:
    """The state dict without the body model's buffers, which the spec's body model file rebuilds."""
    return {k: v for k, v in model.state_dict().items() if not k.startswith("body_model.")}


def _load_weights(model, weights: dict, path: Path) -> None:
    """Load `weights` into `model`; refuses tensors of another dtype than the model's (load_state_dict would cast
    them silently) and NaN or infinite values (a diverged fit, which would render as blank images)."""
    if not isinstance(weights, dict) or not all(isinstance(t, torch.Tensor) for t in weights.values()):
        raise CheckpointError(f"{path}: the checkpoint's weights are not a mapping of name -> tensor")
    expected = model.state_dict()
    for key, tensor in weights.items():
        if key in expected and tensor.dtype != expected[key].dtype:
            raise CheckpointError(f"{path}: weight {key!r} is {tensor.dtype}, the avatar's spec builds it as "
                                  f"{expected[key].dtype}; the file was altered or written by another program")
    broken = {key: int((~torch.isfinite(t)).sum()) for key, t in weights.items() if t.is_floating_point()}
    broken = {key: count for key, count in broken.items() if count}
    if broken:
        shown = ", ".join(f"{key} ({count})" for key, count in list(broken.items())[:3]) + (
            ", ..." if len(broken) > 3 else "")
        raise CheckpointError(f"{path}: {sum(broken.values())} NaN or infinite weights ({shown}): the fit diverged; "
                              "it is not an avatar to render or score; refit with lower learning rates (fit.lr_*)")
    try:
        missing, unexpected = model.load_state_dict(weights, strict=False)
    except RuntimeError as err:  # shape mismatches, reported over several lines
        raise CheckpointError(f"{path}: checkpoint does not match the model ({' '.join(str(err).split())})") from err
    missing = [k for k in missing if not k.startswith("body_model.")]
    if missing or unexpected:
        raise CheckpointError(f"{path}: checkpoint does not match the model (missing {missing[:5]}, unexpected {unexpected[:5]})")


def _plain(value, where: str):
    """`value` with numpy arrays as tensors and numpy scalars as Python numbers; refuses anything else
    that `torch.load(weights_only=True)` could not read back."""
    if isinstance(value, dict):
        return {key: _plain(item, f"{where}[{key!r}]") for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        items = [_plain(item, f"{where}[{i}]") for i, item in enumerate(value)]
        return items if isinstance(value, list) else tuple(items)
    if isinstance(value, np.ndarray):
        return torch.from_numpy(value.copy())
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (torch.Tensor, str, bytes, bool, int, float)):
        return value
    raise TypeError(f"checkpoint {where}: a {type(value).__name__}; only tensors and plain Python values are stored")


def _require_file(path: Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f"{path}: avatar checkpoint not found (run the fit stage: python -m pig.stages.fit)")
    if not path.is_file():
        raise CheckpointError(f"{path}: not a file; expected an avatar checkpoint of the fit stage")


def _read(path: Path, keys: tuple[str, ...], data: bytes | None = None) -> dict:
    """The checkpoint's state, read without running code; a one-line `CheckpointError` naming the file otherwise.
    With `data`, the state is read from those bytes of the file (`path` names it in messages)."""
    path = Path(path)
    if data is None:
        _require_file(path)
    source = path if data is None else io.BytesIO(data)
    rerun = "delete it and re-run the fit stage (python -m pig.stages.fit)"
    if (path.stat().st_size if data is None else len(data)) == 0:
        raise CheckpointError(f"{path}: empty file, not an avatar checkpoint; {rerun}")
    # The zip archive's CRCs catch truncation and flipped bytes that torch.load would read silently.
    try:
        with zipfile.ZipFile(source) as archive:
            damaged = archive.testzip()
    except (zipfile.BadZipFile, ValueError, NotImplementedError, EOFError, OverflowError) as err:
        raise CheckpointError(f"{path}: corrupt, truncated or not an avatar checkpoint ({_first_line(err)}); {rerun}") from err
    if damaged is not None:
        raise CheckpointError(f"{path}: corrupt avatar checkpoint (member {damaged} fails its CRC check); {rerun}")
    if data is not None:
        source.seek(0)
    try:
        state = torch.load(source, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        raise CheckpointError(f"{path}: not loaded: it holds Python objects that only a code-running load could restore, "
                              "so it is an avatar checkpoint of an older format (version 1) or not a pig checkpoint; "
                              f"{rerun}, which writes format version {FORMAT_VERSION}") from err
    except (RuntimeError, ValueError, LookupError, EOFError) as err:
        raise CheckpointError(f"{path}: corrupt or not an avatar checkpoint ({_first_line(err)}); {rerun}") from err
    if not isinstance(state, dict) or "version" not in state:
        raise CheckpointError(f"{path}: not an avatar checkpoint (no format version); {rerun}")
    if state["version"] != FORMAT_VERSION:
        raise CheckpointError(f"{path}: avatar checkpoint of format version {state['version']}, this pig reads "
                              f"version {FORMAT_VERSION}; use the pig that wrote it, or {rerun}")
    missing = [key for key in keys if key not in state]
    if missing:
        raise CheckpointError(f"{path}: avatar checkpoint without {missing}; {rerun}")
    return state


def _first_line(err: Exception) -> str:
    """The first sentence of an exception's message (torch's go on for several lines)."""
    text = str(err).strip().splitlines()
    return text[0].split(". ")[0] if text else type(err).__name__


def load_avatar(path: str | Path, device: str | torch.device = "cpu", capture=None):
    """The fitted `AvatarModel` of a checkpoint (avatar.pt), on `device`, in eval mode. With a loaded `Capture`,
    refuses an avatar fitted on another capture (by fingerprint) or whose training frame ids are not that
    capture's train split, before building the model."""
    return _build(_read(Path(path), AVATAR_KEYS), Path(path), device, capture)


def read_avatar(path: str | Path, device: str | torch.device = "cpu", capture=None) -> tuple:
    """(model, loss-term records, SHA-256) of a checkpoint as `load_avatar` and `loss_terms` give them, from one
    read of the file: the hash is that of the bytes the model was built from, even if a fit renames a new
    checkpoint into place meanwhile."""
    path = Path(path)
    _require_file(path)
    with open(path, "rb") as handle:
        data = handle.read()
    state = _read(path, AVATAR_KEYS, data)
    return _build(state, path, device, capture), _loss_terms(state, path), hashlib.sha256(data).hexdigest()


def _build(state: dict, path: Path, device, capture):
    if capture is not None:
        _require_capture(path, state["spec"], capture)
    try:
        model = build_avatar(_loaded_spec(state["spec"]))
    except (AttributeError, KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"{path}: avatar spec unusable ({type(err).__name__}: {err})") from err
    _load_weights(model, state["model"], path)
    return model.to(device).eval()


def _require_capture(path: Path, spec: dict, capture) -> None:
    fingerprint = spec.get("capture") if isinstance(spec, dict) else None
    require_same_capture(path, fingerprint if isinstance(fingerprint, dict) else {}, spec.get("capture_dir"), capture)
    frames = spec.get("frame_ids")
    train = [int(f) for f in capture.split["train"]["frames"]]
    if frames != train:
        shown = brief(frames) if isinstance(frames, list) else repr(frames)
        raise CheckpointError(f"{path}: the avatar's training frame ids {shown} are not the train frames "
                              f"{brief(train)} of {capture.root}, the capture it was fitted on; the file was altered")


def loss_terms(path: str | Path) -> dict[str, dict]:
    """The records of the loss terms a checkpoint's fit had ({"lpips": {"weight", "net", "state", "detail"}}),
    read without building the model; state "unknown" for a file written before they were recorded."""
    path = Path(path)
    return _loss_terms(_read(path, AVATAR_KEYS), path)


def _loss_terms(state: dict, path: Path) -> dict[str, dict]:
    if "loss_terms" not in state:  # written before the loss terms were recorded
        return {"lpips": {"weight": None, "net": None, "state": "unknown", "detail": ""}}
    terms = state["loss_terms"]
    lpips = terms.get("lpips") if isinstance(terms, dict) else None
    if not isinstance(lpips, dict) or lpips.get("state") not in LPIPS_STATES:
        raise CheckpointError(f"{path}: loss-term record unreadable (expected 'lpips' with a state among {LPIPS_STATES}, "
                              f"found {terms!r}); re-run the fit stage (python -m pig.stages.fit)")
    return terms


def _section_defaults() -> dict[str, dict]:
    """Default values of the recorded preset sections' keys."""
    from pig.avatar.config import AvatarConfig
    from pig.avatar.fit_config import FitConfig
    from pig.field.latent_grid import FieldConfig
    from pig.field.precondition import PrecondConfig
    from pig.render import RasterizerConfig

    classes = {"avatar": AvatarConfig, "field": FieldConfig, "precond": PrecondConfig, "fit": FitConfig,
               "rasterizer": RasterizerConfig}
    return {name: {f.name: f.default for f in fields(cls) if f.default is not MISSING} for name, cls in classes.items()}


def _mismatch(state: dict, spec: dict, settings: dict[str, dict], terms: dict[str, dict],
              old_terms: dict[str, dict]) -> list[str]:
    """What differs between the fit a checkpoint's state belongs to and the fit of `spec`, `settings` and loss
    `terms`: the capture's parts, preset sections (with their keys), the variant and the LPIPS term's state
    (its weight files may have appeared or gone since); empty when it may resume."""
    differs = []
    old_capture, new_capture = state["spec"].get("capture", {}), spec["capture"]
    parts = sorted(key for key in old_capture.keys() | new_capture.keys() if old_capture.get(key) != new_capture.get(key))
    if parts:
        differs.append(f"the capture differs ({', '.join(parts)})")
    sections = [(name, state["spec"].get(name, {}), spec[name]) for name in SPEC_SECTIONS]
    sections += [(name, state["settings"].get(name, {}), values) for name, values in settings.items()]
    defaults = _section_defaults()
    for name, old, new in sections:
        # A key that one side lacks was added to pig since that fit began, which then ran with its default.
        default = defaults.get(name, {})
        keys = sorted(key for key in old.keys() | new.keys()
                      if key not in FREE_SETTINGS.get(name, ())
                      and old.get(key, default.get(key)) != new.get(key, default.get(key)))
        if keys:
            differs.append(f"preset section '{name}' differs in {', '.join(keys)}")
    if state["spec"].get("variant") != spec["variant"]:
        differs.append(f"the variant differs ({state['spec'].get('variant')!r}, now {spec['variant']!r})")
    if old_terms["lpips"]["state"] != terms["lpips"]["state"]:
        differs.append(f"the LPIPS term differs ({old_terms['lpips']['state']!r}, now {terms['lpips']['state']!r})")
    return differs


def load_training_state(path: Path, model, optimizers: list, generator: torch.Generator, spec: dict,
                        settings: dict[str, dict], loss_terms: dict[str, dict],
                        average: WeightAverage | None = None) -> tuple[int, float, list[dict]]:
    """Restore weights, optimisers, RNG and the weight `average` from a checkpoint of the same fit (capture,
    preset sections, variant, LPIPS term: see `_mismatch`); returns (iteration, wall seconds so far, log rows)."""
    state = _read(path, TRAINING_KEYS)
    differs = _mismatch(state, spec, settings, loss_terms, _loss_terms(state, path))
    if differs:
        raise CheckpointError(f"{path}: checkpoint of another fit, not resumed: {'; '.join(differs)}; "
                              "delete it to start the fit over, or point --output elsewhere")
    _load_weights(model, state["model"], path)
    for opt, opt_state in zip(optimizers, state["optimizers"]):
        opt.load_state_dict(opt_state)  # moves the moments onto the parameters' device
    generator.set_state(state["generator"])
    torch.set_rng_state(state["torch_rng"])
    if average is not None and state.get("average") is not None:  # the settings match, so the fit kept one
        try:
            average.load_state_dict(state["average"])
        except (KeyError, TypeError, ValueError) as err:
            raise CheckpointError(f"{path}: weight average unreadable ({err}); delete it to start the fit over") from err
    return state["iteration"], state["wall_s"], state["log"]
