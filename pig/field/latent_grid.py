"""Multi-resolution latent grid over the canonical bounding box: the mean over levels of trilinear lookups.

Implements Eq. 1, z(x~) = (1/G) sum_g z_g(x~), with each level preconditioned per Eq. 4.

Layout: level g is a (d, R, R, R) tensor; `volume[:, i, j, k]` is the feature of the vertex with x
index i, y index j, z index k, at normalised coordinate -1 + 2 i / (R - 1) (vertices on the box
corners: grid_sample with align_corners=True). The box is `bbox_min - margin .. bbox_max + margin`
(margin in canonical units, metres), each axis mapped separately to [-1, 1], so cells are anisotropic
on a non-cubic box, as in the paper. Points outside the box read the feature at the nearest border
point (clamping); their gradient along the clamped axes is zero. Lookups are differentiable with
respect to the features and the query points.

Each level is a PreconditionedTensor with the lattice system (I + lambda_g L_g) of its grid; use
`volumes()` once per step and pass the result to every `forward(points, volumes)` of that step.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from .lattice_solve import LatticeSystem
from .precondition import Form, PrecondConfig, PreconditionedTensor


@dataclass
class FieldConfig:
    """Preset section `field`: the latent grid's levels, width, box margin and initialisation."""

    resolutions: list[int] = field(default_factory=lambda: [8, 24, 40, 56, 72, 88])
    features: int = 16
    margin: float = 0.1
    # Zero start: the preconditioner smooths updates only, so initial noise would stay unsmoothed.
    init_std: float = 0.0


def normalize_points(points: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Map the box [lo, hi] to [-1, 1] per axis."""
    return 2.0 * (points - lo) / (hi - lo) - 1.0


def sample_volume(volume: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup of `volume` (d, X, Y, Z) at normalised `coords` (N, 3) -> (N, d), border-clamped."""
    # grid_sample reads the last coordinate along the first spatial axis, so reverse (x, y, z).
    grid = coords.flip(-1).reshape(1, 1, 1, -1, 3).to(volume.dtype)
    out = F.grid_sample(volume[None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(volume.shape[0], -1).T


class LatentGrid(nn.Module):
    """G cubic grids of `features` channels over the canonical box; `forward(points)` -> (N, features)."""

    def __init__(
        self,
        resolutions: list[int],
        features: int,
        bbox_min,
        bbox_max,
        margin: float = 0.1,
        *,
        lambdas: list[float] | None = None,
        form: Form = "none",
        grid_solver: str = "matmul",
        init_std: float = 0.0,
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        if not resolutions or min(resolutions) < 1 or features < 1:
            raise ValueError(f"LatentGrid: expected resolutions >= 1 and features >= 1, found {resolutions}, {features}")
        lo = torch.as_tensor(bbox_min, dtype=torch.float32).reshape(3) - margin
        hi = torch.as_tensor(bbox_max, dtype=torch.float32).reshape(3) + margin
        if not bool((hi > lo).all()):
            raise ValueError(f"LatentGrid: empty box after margin: min {lo.tolist()}, max {hi.tolist()}")
        if form != "none" and (lambdas is None or len(lambdas) != len(resolutions)):
            raise ValueError(f"LatentGrid: form {form!r} needs one lambda per level, found {lambdas}")
        self.register_buffer("box_min", lo)
        self.register_buffer("box_max", hi)
        self.resolutions = list(resolutions)
        self.features = features
        levels = []
        for g, res in enumerate(self.resolutions):
            init = torch.randn(features, res, res, res, generator=generator) * init_std
            system = None if form == "none" else LatticeSystem((res, res, res), lambdas[g], grid_solver)
            levels.append(PreconditionedTensor(init, system, form))
        self.levels = nn.ModuleList(levels)

    @classmethod
    def from_config(cls, field_cfg: FieldConfig, precond: PrecondConfig, bbox_min, bbox_max, generator=None) -> "LatentGrid":
        return cls(
            field_cfg.resolutions,
            field_cfg.features,
            bbox_min,
            bbox_max,
            field_cfg.margin,
            lambdas=precond.grid_lambdas(len(field_cfg.resolutions)),
            form=precond.form,
            grid_solver=precond.grid_solver,
            init_std=field_cfg.init_std,
            generator=generator,
        )

    @torch.no_grad()
    def set_lambdas(self, lambdas: list[float], keep_values: bool = True) -> None:
        """Smooth level g's updates by (I + lambdas[g] L_g) from now on (forms "substitute" and "filter").

        `keep_values`: every level keeps its current x (the substitution form re-bases: origin = x, u = 0).
        Without it the stored parameters keep their meaning under the new systems, as a state dict written
        under them needs."""
        if len(lambdas) != len(self.levels):
            raise ValueError(f"LatentGrid: expected {len(self.levels)} lambdas, found {lambdas}")
        for level, res, lam in zip(self.levels, self.resolutions, lambdas):
            if level.form == "none":
                raise ValueError("LatentGrid: a grid without preconditioning (form 'none') has no lambdas to set")
            value = level().detach() if keep_values else None
            level.system = LatticeSystem((res, res, res), lam, level.system.method)
            if value is not None:
                level.set_value(value)

    def volumes(self) -> list[torch.Tensor]:
        """The current level tensors x_g (d, R, R, R), differentiable (runs the substitution solves)."""
        return [level() for level in self.levels]

    def normalize(self, points: torch.Tensor) -> torch.Tensor:
        """Canonical points (N, 3) -> box coordinates in [-1, 1]^3 (outside the box: beyond)."""
        return normalize_points(points, self.box_min.to(points.dtype), self.box_max.to(points.dtype))

    def forward(self, points: torch.Tensor, volumes: list[torch.Tensor] | None = None) -> torch.Tensor:
        """Mean over levels of the trilinear features at canonical `points` (N, 3) -> (N, features)."""
        if points.ndim != 2 or points.shape[-1] != 3:
            raise ValueError(f"LatentGrid: expected points of shape (N, 3), found {tuple(points.shape)}")
        volumes = self.volumes() if volumes is None else volumes
        coords = self.normalize(points)
        return sum(sample_volume(v, coords) for v in volumes) / len(volumes)
