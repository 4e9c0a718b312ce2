"""Distribution metrics: Fréchet distance between feature sets (FGD / FED / FMD when
the features come from the motion autoencoder) and diversity (Div)."""

from __future__ import annotations

import numpy as np
from scipy import linalg

from ...errors import DiffshegError


def _as_features(features: np.ndarray, what: str) -> np.ndarray:
    x = np.asarray(features, dtype=np.float64)
    if x.ndim != 2 or len(x) < 2:
        raise DiffshegError(
            f"{what}: expected at least two feature vectors as an (N, F) array, got shape {x.shape}; "
            "evaluate more (or longer) clips")
    if not np.isfinite(x).all():
        raise DiffshegError(f"{what}: features contain NaN or infinite values")
    return x


def gaussian_stats(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of (N, F) features."""
    x = _as_features(features, "features")
    return x.mean(axis=0), np.atleast_2d(np.cov(x, rowvar=False))


def frechet_distance(features_a: np.ndarray, features_b: np.ndarray) -> float:
    """|mu_a - mu_b|^2 + Tr(S_a + S_b - 2 (S_a S_b)^(1/2)) (DiffSHEG eq. 9)."""
    a = _as_features(features_a, "first feature set")
    b = _as_features(features_b, "second feature set")
    if a.shape[1] != b.shape[1]:
        raise DiffshegError(
            f"feature sets differ in width ({a.shape[1]} vs {b.shape[1]}): use one autoencoder for both")
    mu_a, cov_a = gaussian_stats(a)
    mu_b, cov_b = gaussian_stats(b)
    covmean = linalg.sqrtm(cov_a @ cov_b)
    if not np.isfinite(covmean).all():
        eps = 1e-6 * np.eye(len(cov_a))
        covmean = linalg.sqrtm((cov_a + eps) @ (cov_b + eps))
    covmean = np.real(covmean)
    diff = mu_a - mu_b
    value = diff @ diff + np.trace(cov_a) + np.trace(cov_b) - 2.0 * np.trace(covmean)
    return float(max(value, 0.0))


def diversity(samples: np.ndarray) -> float:
    """Mean pairwise L1 distance between samples (DiffSHEG eq. 11), averaged per element
    so that it does not grow with clip length or channel count."""
    x = np.asarray(samples, dtype=np.float64)
    if len(x) < 2:
        raise DiffshegError(f"diversity needs at least two samples, got {len(x)}")
    flat = x.reshape(len(x), -1)
    total, pairs = 0.0, 0
    for i in range(len(flat) - 1):
        total += np.abs(flat[i + 1 :] - flat[i]).mean(axis=1).sum()
        pairs += len(flat) - 1 - i
    return float(total / pairs)
