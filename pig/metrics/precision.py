"""The arithmetic of the evaluation's metric networks (LPIPS's backbone, FID's Inception): `float32`, the reference,
or `float16` / `bfloat16` under autocast, every distance and statistic of the features in float32.

Issue 39 allows the lower precisions only within its parity bounds against a float32 run of the same views
(benchmarks/NOTES.md, "Lower-precision metric networks"); PSNR and SSIM never leave float32.
"""
from __future__ import annotations

import contextlib

import torch

PRECISIONS = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def check_precision(precision: str, what: str) -> str:
    if precision not in PRECISIONS:
        raise ValueError(f"{what} precision must be one of {sorted(PRECISIONS)}, found {precision!r}")
    return precision


def network_arithmetic(device_type: str, precision: str):
    """The context a metric network runs in: none for `float32` (an enclosing autocast, such as the fit's bf16
    LPIPS term, stays in force), else autocast to `precision` on `device_type`."""
    if precision == "float32":
        return contextlib.nullcontext()
    return torch.autocast(device_type, PRECISIONS[precision])


def widened(features: torch.Tensor) -> torch.Tensor:
    """A lowered network's output in float32 (float64 stays float64), before any distance or statistic."""
    return features.to(torch.promote_types(features.dtype, torch.float32))
