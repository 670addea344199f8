"""Small avatars for unit tests: 3 timesteps (frames 10-12) on a given body model, a 4^3 + 6^3 x 4 latent grid."""
from dataclasses import asdict

import torch

from pig.avatar.build import build_avatar
from pig.avatar.config import AvatarConfig
from pig.body.params import SmplxParams
from pig.field.latent_grid import FieldConfig
from pig.field.precondition import PrecondConfig


def small_avatar(body_model_npz: bytes, params: SmplxParams, refine: bool = True, **avatar):
    """An avatar of `params` (3 timesteps) with decoder outputs starting at gain 0.1 and `avatar` config fields
    (sizes, variant switches); `refine` turns every part of the body refiner on or off. Seeded: the same call builds
    the same weights."""
    cfg = AvatarConfig(**{"output_init_gain": 0.1, "refine_shape": refine, "refine_body": refine, "refine_face": refine,
                          "refine_hands": refine, **avatar})
    spec = dict(avatar=asdict(cfg), field=asdict(FieldConfig(resolutions=[4, 6], features=4)), precond=asdict(PrecondConfig()),
                body_model_npz=body_model_npz, params=asdict(params), frame_ids=[10, 11, 12], variant="pig")
    torch.manual_seed(0)
    return build_avatar(spec)
