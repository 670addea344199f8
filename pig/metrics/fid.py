"""Frechet Inception Distance: ||mu1 - mu2||^2 + tr(S1 + S2 - 2 (S1 S2)^(1/2)) between feature Gaussians.

The evaluation's FID column (Section 4.2, Heusel et al. 2017). Features come from the TorchScript
Inception (`inception-2015-12-05.pt`) that the StyleGAN metrics and clean-fid load.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from pig.metrics.weights import INCEPTION_FILE, WeightsMissing, locate

# 2048 feature dimensions make the covariance full rank only above 2048 images; below this many
# the estimate is dominated by its O(1/N) bias, so the value is reported missing. The default is
# 2000 so that THuman4's 2000-frame novel-view set (one camera) still gets a value, as in the paper.
DEFAULT_MIN_IMAGES = 2000
INCEPTION_SIZE = 299


def feature_statistics(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and covariance (D, D) in float64 of features (N, D), N-1 normalised as the standard tools."""
    features = np.asarray(features, dtype=np.float64)
    if features.ndim != 2 or features.shape[0] < 2:
        raise ValueError(f"feature_statistics expects (N >= 2, D) features, found {features.shape}")
    return features.mean(0), np.cov(features, rowvar=False)


def _psd_eigenvalues_floor(values: np.ndarray) -> np.ndarray:
    """Eigenvalues of a PSD matrix with those at round-off level (|v| <= n eps max v) set to 0.

    sqrt amplifies round-off: a 1e-16 eigenvalue of a singular covariance would add 1e-8 each.
    """
    tol = values.size * np.finfo(np.float64).eps * max(values.max(initial=0.0), 0.0)
    return np.where(values > tol, values, 0.0)


def _psd_sqrt(matrix: np.ndarray) -> np.ndarray:
    """Symmetric square root of a symmetric PSD matrix."""
    values, vectors = np.linalg.eigh((matrix + matrix.T) / 2)
    return (vectors * np.sqrt(_psd_eigenvalues_floor(values))) @ vectors.T


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """Frechet distance of two Gaussians; exact and stable for singular covariances.

    tr (S1 S2)^(1/2) = sum of the square roots of the eigenvalues of the symmetric PSD matrix
    S1^(1/2) S2 S1^(1/2) (same spectrum as S1 S2), which avoids sqrtm's complex round-off.
    """
    mu1, mu2 = np.asarray(mu1, np.float64), np.asarray(mu2, np.float64)
    sigma1, sigma2 = np.asarray(sigma1, np.float64), np.asarray(sigma2, np.float64)
    root1 = _psd_sqrt(sigma1)
    middle = root1 @ sigma2 @ root1
    cross = np.sqrt(_psd_eigenvalues_floor(np.linalg.eigvalsh((middle + middle.T) / 2))).sum()
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2 * cross)


def fid_from_features(a: np.ndarray, b: np.ndarray, min_images: int = DEFAULT_MIN_IMAGES) -> tuple[float, str]:
    """(FID, reason) of two feature sets (N, D); NaN with the reason when either set is too small."""
    smallest = min(len(a), len(b))
    if smallest < max(min_images, 2):
        return math.nan, f"FID is NaN: needs >= {min_images} images per set, have {smallest}"
    return frechet_distance(*feature_statistics(a), *feature_statistics(b)), ""


class InceptionFeatures(torch.nn.Module):
    """TorchScript Inception feature extractor: images (B, 3, H, W) in [0, 1] -> (B, D) pool features.

    Images are resized to 299 x 299 (bilinear, antialiased) and scaled to [0, 255] floats, the input
    clean-fid gives the same network (`model(x, return_features=True)`). Raises `WeightsMissing`.
    """

    def __init__(self, weights: str | Path | None = None):
        super().__init__()
        path = locate(INCEPTION_FILE, weights, [Path("/tmp")], "FID Inception network")
        try:
            self.model = torch.jit.load(str(path), map_location="cpu").eval()
        except Exception as err:  # TorchScript raises RuntimeError or ValueError for foreign files
            raise WeightsMissing(f"{path}: not a loadable TorchScript Inception network ({err})") from None

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"InceptionFeatures expects (B, 3, H, W) images, found {tuple(images.shape)}")
        if images.shape[-2:] != (INCEPTION_SIZE, INCEPTION_SIZE):
            images = F.interpolate(images, size=(INCEPTION_SIZE, INCEPTION_SIZE), mode="bilinear", antialias=True, align_corners=False)
        features = self.model(images.clamp(0, 1) * 255, return_features=True)
        return features.reshape(images.shape[0], -1)
