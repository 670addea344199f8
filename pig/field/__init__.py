"""Canonical multi-resolution latent grid and its Laplacian preconditioners."""
