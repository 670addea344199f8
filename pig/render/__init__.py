"""Gaussian rasterization: gsplat on CUDA, a pure-PyTorch tile compositor on the CPU."""
