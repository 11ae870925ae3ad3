"""Keep the learned parts inside the feature region they were trained on.

The MLPs were fitted only where the training scans put PCA features. A point whose features
fall outside that cloud (another sensor's density, a scene unlike any trained on) would get
an output extrapolated linearly from nothing. :class:`FeatureNovelty` measures each point's
squared Mahalanobis distance ``d2`` to the training features' mean and covariance and
:meth:`FeatureNovelty.clamp` pulls features beyond ``radius2`` (a quantile of the training
points' own ``d2``) back along the ray to the mean, onto that boundary, before the MLPs see
them (:func:`gloam_jax.learned.attributes`).

Blending such points towards GICP's plane instead was measured worse
(experiments/novelty_clamp): GICP's planes are thinner than the learned ones, so the blended
points outweighed the rest of the scan.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from gloam_jax.errors import InputError

DEFAULT_QUANTILE = 0.99  # of the training points' d2: the region the MLPs are trusted in


class FeatureNovelty(NamedTuple):
    """Training features' mean (C,) and whitening factor (C, C), ``d2 = |(f - mean) @ factor|^2``,
    and the squared distance ``radius2`` (scalar) beyond which features are clamped."""

    mean: Array | np.ndarray
    factor: Array | np.ndarray
    radius2: Array | float

    def squared_distance(self, f: Array) -> Array:
        """``d2`` (...,) of features (..., C)."""
        z = (f - jnp.asarray(self.mean, f.dtype)) @ jnp.asarray(self.factor, f.dtype)
        return jnp.sum(z * z, axis=-1)

    def clamp(self, f: Array) -> Array:
        """Features (..., C), those beyond ``radius2`` moved towards the mean onto it."""
        radius2 = jnp.asarray(self.radius2, f.dtype)
        d2 = self.squared_distance(f)[..., None]
        mean = jnp.asarray(self.mean, f.dtype)
        # Features inside pass bit for bit (mean + (f - mean) would round them).
        return jnp.where(d2 > radius2, mean + (f - mean) * jnp.sqrt(radius2 / d2.clip(radius2)), f)


def fit_novelty(
    features: np.ndarray | Sequence[np.ndarray], *, quantile: float = DEFAULT_QUANTILE
) -> FeatureNovelty:
    """Fit on the training points' PCA features, (N, C) or a list of per-scan (N_i, C)."""
    parts = [features] if isinstance(features, np.ndarray) else list(features)
    x = np.concatenate([np.asarray(p, np.float64) for p in parts]) if parts else np.zeros((0, 0))
    x = x[np.all(np.isfinite(x), axis=1)] if x.ndim == 2 else x
    if x.ndim != 2 or len(x) <= x.shape[1]:
        raise InputError(None, f"novelty needs more finite rows than columns, got {x.shape}")
    if not 0 < quantile < 1:
        raise InputError(None, f"novelty quantile must be in (0, 1), got {quantile}")
    mean = x.mean(axis=0)
    covariance = np.cov(x, rowvar=False) + 1e-9 * np.eye(x.shape[1])
    # covariance^-1 = factor factor^T with factor = inverse of the Cholesky factor, transposed.
    factor = np.linalg.inv(np.linalg.cholesky(covariance)).T
    d2 = np.sum(((x - mean) @ factor) ** 2, axis=1)
    return FeatureNovelty(mean, factor, float(np.quantile(d2, quantile)))
