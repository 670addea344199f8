"""Gaussian rasterization: gsplat on CUDA, a pure-PyTorch tile compositor on the CPU.

`render_gaussians` renders one set of Gaussians (colour, alpha, expected depth; differentiable);
`render_timesteps` several sets, each into its own cameras (one gsplat call for all).
"""
from .api import RasterizerConfig, RenderError, RenderResult, render_gaussians, render_timesteps

__all__ = ["RasterizerConfig", "RenderError", "RenderResult", "render_gaussians", "render_timesteps"]
