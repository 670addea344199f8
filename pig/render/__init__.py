"""Gaussian rasterization: gsplat on CUDA, a pure-PyTorch tile compositor on the CPU.

`render_gaussians` is the one entry point (colour, alpha, expected depth; differentiable).
"""
from .api import RasterizerConfig, RenderError, RenderResult, render_gaussians

__all__ = ["RasterizerConfig", "RenderError", "RenderResult", "render_gaussians"]
