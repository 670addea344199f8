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

from pig.metrics.precision import check_precision, network_arithmetic, widened
from pig.metrics.weights import INCEPTION_FILE, WeightsMissing, locate

# Below this many images per set the FID is still computed, but flagged: with 2048 feature dimensions its
# O(1/N) bias dominates small sets, so values compare only at equal N. 2000 is THuman4's novel-view set.
DEFAULT_MIN_IMAGES = 2000
INCEPTION_SIZE = 299


class FeatureStatistics:
    """Running mean (D,) and covariance (D, D) of feature batches in float64; memory O(D^2 + chunk_rows D),
    whatever the number of images (at D = 2048 and 512 rows: 40 MiB kept, under 90 MiB while merging).

    The sums live on the device of the first batch (numpy arrays: the CPU), so the evaluation keeps a GPU's
    features on the GPU: no copy back and no wait per batch. Batches are buffered up to `chunk_rows` rows (each
    O(D^2) merge then serves many images), centred on their own mean and merged with the pairwise update of Chan,
    Golub and LeVeque (1979): M2 = M2_a + M2_b + (n_a n_b / n) d d^T, d = mean_b - mean_a. A plain sum of outer
    products would lose all precision for features whose mean is large against their spread.
    """

    def __init__(self, chunk_rows: int = 512):
        self.chunk_rows = chunk_rows
        self.count = 0  # feature vectors added
        self._dim: int | None = None
        self._device: torch.device | None = None
        self._pending: list[torch.Tensor] = []
        self._pending_rows = 0
        self._merged = 0
        self._mean: torch.Tensor | None = None
        self._scatter: torch.Tensor | None = None  # sum of outer products of deviations from the mean

    def update(self, features: np.ndarray | torch.Tensor) -> None:
        """Add a batch of features (B, D), a numpy array or a tensor; B may be any size (0 too), D must not
        change, and tensors stay on the device of the first batch."""
        features = torch.as_tensor(features)
        if features.ndim != 2 or (self._dim is not None and features.shape[1] != self._dim):
            expected = "(B, D)" if self._dim is None else f"(B, {self._dim})"
            raise ValueError(f"FeatureStatistics expects {expected} features, found {tuple(features.shape)}")
        if self._device is not None and features.device != self._device:
            raise ValueError(f"FeatureStatistics holds sums on {self._device}, found features on {features.device}")
        if features.shape[0] == 0:
            return
        # A float64 copy: the caller may reuse its buffer.
        features = features.to(torch.float64, copy=True)
        self._dim, self._device = features.shape[1], features.device
        self._pending.append(features)
        self._pending_rows += features.shape[0]
        self.count += features.shape[0]
        if self._pending_rows >= self.chunk_rows:
            self._merge()

    def _merge(self) -> None:
        if not self._pending:
            return
        rows = self._pending_rows
        # The rows centred on their mean, plus one row sqrt(n_a n_b / n) d that gives the cross term in the
        # same product: one (rows + 1, D) buffer and one (D, D) temporary.
        block = torch.cat([*self._pending, self._pending[0].new_zeros(1, self._dim)])
        self._pending, self._pending_rows = [], 0
        batch_mean = block[:rows].mean(0)
        block[:rows] -= batch_mean
        if self._merged == 0:
            self._mean, self._scatter = batch_mean, block.T @ block
        else:
            total = self._merged + rows
            delta = batch_mean - self._mean
            block[rows] = delta * math.sqrt(self._merged * rows / total)
            self._scatter += block.T @ block
            self._mean = self._mean + delta * (rows / total)
        self._merged += rows

    @property
    def mean(self) -> np.ndarray:
        if self.count == 0:
            raise ValueError("a mean needs >= 1 feature vector, have 0")
        self._merge()
        return self._mean.cpu().numpy()

    def covariance(self) -> np.ndarray:
        """Sample covariance, N-1 normalised as the standard tools (np.cov, clean-fid)."""
        if self.count < 2:
            raise ValueError(f"a covariance needs >= 2 feature vectors, have {self.count}")
        self._merge()
        return (self._scatter / (self.count - 1)).cpu().numpy()


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


def small_set_note(images: int, min_images: int = DEFAULT_MIN_IMAGES) -> str:
    """The caveat a FID over fewer than `min_images` images carries ('' when there are enough)."""
    if images >= min_images:
        return ""
    return f"FID over {images} images (< {min_images}): biased high, compare only at equal N"


def fid_from_statistics(fake: FeatureStatistics, real: FeatureStatistics,
                        min_images: int = DEFAULT_MIN_IMAGES) -> tuple[float, str]:
    """(FID, note) of two accumulated feature sets: NaN below 2 images per set, else the value, with the
    small-set caveat below `min_images`."""
    images = min(fake.count, real.count)
    if images < 2:
        return math.nan, f"FID is NaN: needs >= 2 images per set, have {images}"
    return frechet_distance(fake.mean, fake.covariance(), real.mean, real.covariance()), small_set_note(images, min_images)


def resize_for_inception(images: torch.Tensor, rule: str = "antialiased_bilinear") -> torch.Tensor:
    """(B, 3, 299, 299) of (B, 3, H, W): bilinear with half-pixel centres, antialiased (`antialiased_bilinear`,
    this project's rule) or not (`pytorch_fid`, that tool's F.interpolate call); unchanged at 299 x 299."""
    if rule not in ("antialiased_bilinear", "pytorch_fid"):
        raise ValueError(f"FID resize rule must be 'antialiased_bilinear' or 'pytorch_fid', found {rule!r}")
    if images.shape[-2:] == (INCEPTION_SIZE, INCEPTION_SIZE):
        return images
    return F.interpolate(images, size=(INCEPTION_SIZE, INCEPTION_SIZE), mode="bilinear", align_corners=False,
                         antialias=rule == "antialiased_bilinear")


class InceptionFeatures(torch.nn.Module):
    """TorchScript Inception feature extractor: images (B, 3, H, W) in [0, 1] -> (B, D) pool features.

    Images are resized to 299 x 299 (`resize`: see resize_for_inception) and scaled to [0, 255] floats, the input
    clean-fid gives the same network (`model(x, return_features=True)`). Raises `WeightsMissing`. `precision`
    (float32, float16, bfloat16): the network's arithmetic (autocast; the resize stays float32), its features returned
    in float32; `channels_last`: its weights and input in channels-last memory format.
    """

    def __init__(self, weights: str | Path | None = None, resize: str = "antialiased_bilinear",
                 precision: str = "float32", channels_last: bool = False):
        super().__init__()
        self.resize = resize
        self.precision, self.channels_last = check_precision(precision, "FID Inception"), channels_last
        # Not /tmp, where clean-fid drops it: anyone can write there, and the file is code (TorchScript).
        path = locate(INCEPTION_FILE, weights, [], "FID Inception network")
        try:
            self.model = torch.jit.load(str(path), map_location="cpu").eval()
        except Exception as err:  # TorchScript raises RuntimeError or ValueError for foreign files
            raise WeightsMissing(f"{path}: not a loadable TorchScript Inception network ({err})") from None
        if channels_last:
            self.model.to(memory_format=torch.channels_last)

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"InceptionFeatures expects (B, 3, H, W) images, found {tuple(images.shape)}")
        images = resize_for_inception(images, self.resize)
        scaled = images.clamp(0, 1) * 255
        if self.channels_last:
            scaled = scaled.contiguous(memory_format=torch.channels_last)
        with network_arithmetic(scaled.device.type, self.precision):
            features = self.model(scaled, return_features=True)
        if self.precision != "float32":
            features = widened(features)
        return features.reshape(images.shape[0], -1)
