"""Decoder conditioning: Fourier time embedding gamma(t) and the normalised level-of-detail input.

Implements Eq. 6 (F = ceil(log2 T) pairs sin/cos(pi 2^(f-1) t~), t~ = (t-1)/(T-1)) and l~ of Eq. 7;
both normalised inputs are 0 when T = 1 or L = 1 (then gamma has no entries).
"""
from __future__ import annotations

import math

import torch


def num_frequencies(num_timesteps: int) -> int:
    return math.ceil(math.log2(num_timesteps)) if num_timesteps > 1 else 0


def time_embedding(timesteps: torch.Tensor, num_timesteps: int) -> torch.Tensor:
    """(K,) 0-based timestep indices -> (K, 2F) features [sin..., cos...]."""
    count = num_frequencies(num_timesteps)
    t = timesteps.to(torch.get_default_dtype()) / max(num_timesteps - 1, 1)
    freqs = math.pi * 2.0 ** torch.arange(count, dtype=t.dtype, device=t.device)
    angles = t[:, None] * freqs
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


def lod_input(level: int, num_levels: int) -> float:
    """0-based level -> l~ in [0, 1] (coarsest 0, finest 1)."""
    return level / (num_levels - 1) if num_levels > 1 else 0.0
