"""Configuration of the avatar model (preset section `avatar`): anchors, levels, decoders, refinement.

Defaults are the paper's (Section 3.6); the latent grid is configured in section `field` (pig.field).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from pig.config import Bounds


@dataclass
class AvatarConfig:
    num_anchors: Annotated[int, Bounds(ge=1, le=10_000_000)] = 100_000  # at most 100 times the paper's
    levels: int = 4  # nested LOD subsets by halving
    anchor_seed: int = 0
    sh_degree: int = 3
    hidden_layers: int = 5  # colour and shape decoders
    hidden_width: Annotated[int, Bounds(ge=1, le=8192)] = 512
    single_mlp: bool = False  # ablation: one MLP decodes colour and shape together
    offsets: bool = True  # ablation `no_offsets`: no per-timestep position residual (Eq. 10)
    # Axes of the decoded position residual d mu (Eq. 10 leaves them open): `world`, or `local`, the anchor's
    # transported frame (d mu turns with the surface: R d mu, R of Eq. 3), variant `local_offsets`.
    offset_frame: Literal["world", "local"] = "world"
    learn_anchors: bool = True  # ablation `fixed_anchors`: canonical anchors stay at x_init
    refine_hidden_layers: int = 3  # body refinement MLP (Eqs. 12-14)
    refine_hidden_width: int = 32
    refine_shape: bool = True
    refine_body: bool = True  # global orientation and the 21 body joints
    refine_face: bool = True  # jaw and eyes
    refine_hands: bool = True
    init_opacity: float = 0.5
    # Scales are exp(output) times this multiple of the mean anchor spacing of the level.
    scale_prior: float = 1.0
    offset_scale: float = 0.05  # metres per unit of the raw offset output
    output_init_gain: float = 0.01  # last decoder layers start small, so the avatar starts at the prior

    def __post_init__(self):
        if self.sh_degree not in (0, 1, 2, 3):
            raise ValueError(f"avatar.sh_degree must be 0..3, got {self.sh_degree}")
        if self.offset_frame not in ("world", "local"):
            raise ValueError(f"avatar.offset_frame must be 'world' or 'local', got {self.offset_frame!r}")
        if self.levels < 1 or self.num_anchors < 2 ** (self.levels - 1):
            raise ValueError(f"avatar: {self.num_anchors} anchors cannot form {self.levels} nested levels")
