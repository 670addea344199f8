"""Anchor decoders: colour MLP to spherical harmonics and shape MLP to offset, rotation, scale, opacity.

Implements Eqs. 8-9 (Psi_color, Psi_shape on y = [z, gamma(t), l~]) with the output parameterisations
of Section 3.4: unit quaternion residual, log-space scale, opacity in (0, 1).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

SHAPE_OUTPUTS = 3 + 4 + 3 + 1  # offset, rotation residual, log-scale, opacity logit
LOG_SCALE_MIN, LOG_SCALE_MAX = -15.0, 3.0  # 0.3 micrometres .. 20 metres


def mlp(inputs: int, width: int, layers: int, outputs: int, output_gain: float) -> nn.Sequential:
    """`layers` hidden ReLU layers of `width`; the last linear layer is scaled by `output_gain`."""
    modules: list[nn.Module] = []
    size = inputs
    for _ in range(layers):
        modules += [nn.Linear(size, width), nn.ReLU()]
        size = width
    last = nn.Linear(size, outputs)
    with torch.no_grad():
        last.weight.mul_(output_gain)
        last.bias.zero_()
    modules.append(last)
    return nn.Sequential(*modules)


@dataclass
class DecodedAnchors:
    offset: torch.Tensor  # (..., 3) position residual (Eq. 10), in world axes or the anchor's frame (avatar.offset_frame)
    rotation: torch.Tensor  # (..., 4) unit quaternion residual, wxyz (Eq. 11)
    scale: torch.Tensor  # (..., 3) positive
    opacity: torch.Tensor  # (...,) in (0, 1)
    sh: torch.Tensor  # (..., K, 3)


class AnchorDecoder(nn.Module):
    """Psi_color and Psi_shape (or one shared MLP for the `single_mlp` ablation)."""

    def __init__(self, inputs: int, width: int, layers: int, sh_degree: int, *, single_mlp: bool = False,
                 offsets: bool = True, init_opacity: float = 0.5, offset_scale: float = 0.05, output_gain: float = 0.01):
        super().__init__()
        if not 0 < init_opacity < 1:
            raise ValueError(f"init_opacity must lie in (0, 1), got {init_opacity}")
        self.sh_coeffs = (sh_degree + 1) ** 2
        self.offsets = offsets
        self.offset_scale = offset_scale
        self.opacity_bias = math.log(init_opacity / (1 - init_opacity))
        colour_outputs = 3 * self.sh_coeffs
        if single_mlp:
            self.shared = mlp(inputs, width, layers, SHAPE_OUTPUTS + colour_outputs, output_gain)
            self.shape = self.colour = None
        else:
            self.shared = None
            self.shape = mlp(inputs, width, layers, SHAPE_OUTPUTS, output_gain)
            self.colour = mlp(inputs, width, layers, colour_outputs, output_gain)
        self.autocast = False
        self._compiled_mlps = None  # `_run_mlps` compiled by set_precision
        # On the module's device: a tensor made from host data in `forward` would be a blocking copy to a GPU every
        # step, which waits for the device's queue to drain (a host synchronisation). Not in the state dict.
        self.register_buffer("identity", torch.tensor([1.0, 0.0, 0.0, 0.0]), persistent=False)

    def set_precision(self, precision: str, compiled: bool = False, mode: str = "default") -> None:
        """MLPs in "float32", "tf32" (set by the caller through torch.backends) or "bf16" autocast with float32
        weights and outputs; `compiled` compiles them with torch.compile in `mode` (same parameters and state
        dict)."""
        self.autocast = precision == "bf16"
        if compiled and self._compiled_mlps is None:
            # A method of this file, not nn.Module.compile(): Dynamo skips the frames of torch.nn's own modules
            # (nn.Sequential) that Module.compile() hands it, and they ran eagerly without a word (torch 2.13).
            self._compiled_mlps = torch.compile(self._run_mlps, mode=mode)

    def _run_mlps(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(shape, colour) raw MLP outputs, in bf16 autocast when `autocast` is set."""
        with torch.autocast(y.device.type, torch.bfloat16, enabled=self.autocast):
            if self.shared is not None:
                out = self.shared(y)
                return out[..., :SHAPE_OUTPUTS], out[..., SHAPE_OUTPUTS:]
            return self.shape(y), self.colour(y)

    def forward(self, y: torch.Tensor, log_scale_prior: float | torch.Tensor = 0.0) -> DecodedAnchors:
        """y (..., inputs) -> decoded attributes; scale = exp(output + log_scale_prior)."""
        shape, colour = (self._compiled_mlps or self._run_mlps)(y)
        shape, colour = shape.to(y.dtype), colour.to(y.dtype)  # the parameterisations below in the input's precision
        offset = shape[..., 0:3] * self.offset_scale
        if not self.offsets:
            offset = torch.zeros_like(offset)
        quat = shape[..., 3:7] + self.identity.to(shape.dtype)  # residual around the identity rotation
        quat = quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        # Bounded log-scale: a diverging output must not make a splat vanish (0) or cover everything (inf).
        scale = torch.exp((shape[..., 7:10] + log_scale_prior).clamp(LOG_SCALE_MIN, LOG_SCALE_MAX))
        opacity = torch.sigmoid(shape[..., 10] + self.opacity_bias)
        sh = colour.reshape(colour.shape[:-1] + (self.sh_coeffs, 3))
        return DecodedAnchors(offset=offset, rotation=quat, scale=scale, opacity=opacity, sh=sh)
