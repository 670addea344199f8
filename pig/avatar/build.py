"""Construction of an avatar from a serialisable spec, and its per-group optimisers.

Canonical body (zero pose, the capture's betas) -> anchors (Sec. 3.1), latent grid (Eq. 1) and anchors
preconditioned per Eqs. 4-5, decoders (Eqs. 8-9) and refiner (Eq. 13); the paper's learning rates.
"""
from __future__ import annotations

import functools
import io
import zipfile
from pathlib import Path

import numpy as np
import torch
from numpy.lib import format as npy_format

from pig.body.model import HAND_MEAN_KEYS, NUM_JOINTS, REQUIRED_KEYS, BodyModel, _dense
from pig.body.npz import read_npz, read_npz_bytes
from pig.body.params import SmplxParams
from pig.config import from_dict
from pig.field.latent_grid import FieldConfig, LatentGrid
from pig.field.optim import Adam, build_optimizer, field_param_groups
from pig.field.precondition import PrecondConfig, precondition_anchors

from .anchors import sample_attachment
from .config import AvatarConfig
from .model import AvatarModel


# The arrays of an SMPL-X npz that `BodyModel` reads.
BODY_MODEL_KEYS = (*REQUIRED_KEYS, *HAND_MEAN_KEYS)


def body_model_npz(path: Path) -> bytes:
    """The body model file as npz bytes that load without pickle, for the avatar spec: the file itself when
    it holds plain arrays only (a compressed file stays compressed), else its `BODY_MODEL_KEYS` rewritten.

    SMPL-X files may hold name tables or a sparse J_regressor as pickled objects; the spec keeps only
    plain arrays, so that reading a checkpoint never unpickles."""
    path = Path(path)
    if not _holds_objects(path):
        return path.read_bytes()
    # Pickled members are rebuilt only into arrays and sparse matrices, as `BodyModel.from_file` reads them.
    arrays = {key: _dense(value) for key, value in
              read_npz(path, ValueError, "an SMPL-X model npz", BODY_MODEL_KEYS, pickled=BODY_MODEL_KEYS).items()}
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _holds_objects(path: Path) -> bool:
    """Whether an npz has pickled (object) members, from the members' .npy headers alone."""
    readers = {(1, 0): npy_format.read_array_header_1_0, (2, 0): npy_format.read_array_header_2_0}
    try:
        with zipfile.ZipFile(path) as archive:
            for name in archive.namelist():
                with archive.open(name) as member:
                    reader = readers.get(npy_format.read_magic(member))
                    if reader is None or reader(member)[2].hasobject:  # other header versions: rewrite to be safe
                        return True
    except (zipfile.BadZipFile, ValueError) as err:
        raise ValueError(f"{path}: not a readable npz body model file ({err})") from err
    return False


def canonical_vertices(body_model: BodyModel, betas) -> torch.Tensor:
    """The canonical mesh: the body model at zero pose with the capture's betas, zero expression, no translation."""
    zero = torch.zeros(1, NUM_JOINTS, 3, dtype=body_model.dtype)
    return body_model(zero, torch.as_tensor(betas, dtype=body_model.dtype)[None]).vertices[0]


def build_avatar(spec: dict) -> AvatarModel:
    """spec: {"avatar", "field", "precond": config dicts, "body_model_npz": npz bytes of the body model
    (`body_model_npz`), "params": SmplxParams fields (training frames, in order),
    "frame_ids": training frame ids}; other keys (the variant, the capture's fingerprint) are records.
    Deterministic per spec."""
    cfg = from_dict(AvatarConfig, spec["avatar"], "avatar spec")
    field_cfg = from_dict(FieldConfig, spec["field"], "field spec")
    precond = from_dict(PrecondConfig, spec["precond"], "precond spec")
    source = "body model of the avatar spec"
    arrays = read_npz_bytes(spec["body_model_npz"], source, ValueError, "an npz of the body model's plain arrays",
                            keys=BODY_MODEL_KEYS)
    body_model = BodyModel(arrays, source=source)
    params = SmplxParams(**spec["params"])
    with torch.no_grad():
        canon = canonical_vertices(body_model, params.betas)
    attachment = sample_attachment(canon.double().numpy(), body_model.faces.numpy(), cfg.num_anchors, cfg.levels, cfg.anchor_seed)
    x_init = torch.as_tensor(attachment.x_init, dtype=body_model.dtype)
    grid_rng = torch.Generator().manual_seed(cfg.anchor_seed)
    grid = LatentGrid.from_config(field_cfg, precond, x_init.min(0).values, x_init.max(0).values, grid_rng)
    anchors = precondition_anchors(x_init, precond) if cfg.learn_anchors else None
    return AvatarModel(cfg, body_model, params, spec["frame_ids"], attachment, canon, grid, anchors)


def build_optimizers(model: AvatarModel, lr_decoders: float, lr_refine: float, precond: PrecondConfig,
                     fused: bool = False) -> list[torch.optim.Optimizer]:
    """[field optimiser (grid levels + anchors, per-level rates), Adam for decoders and refiner].

    `fused`: torch's fused Adam (one kernel for all tensors) wherever the step is plain Adam; the same update
    as pig.field.optim.Adam up to float rounding."""
    adam = functools.partial(torch.optim.Adam, fused=True) if fused else Adam
    field_groups = field_param_groups(model.grid, model.anchors, precond)
    if fused and precond.optimizer == "adam":
        field = adam(field_groups, eps=precond.adam_eps)
    else:
        field = build_optimizer(precond.optimizer, field_groups, precond.adam_eps)
    groups = [{"name": "decoders", "params": list(model.decoder.parameters()), "lr": lr_decoders}]
    if model.refiner.net is not None:
        groups.append({"name": "refine", "params": list(model.refiner.parameters()), "lr": lr_refine})
    return [field, adam(groups)]
