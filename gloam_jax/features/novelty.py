"""How far a point's PCA features lie from those the MLPs were trained on.

The learned parts are only fitted where the training scans put features. A point whose
features fall outside that cloud (another sensor's density, a scene unlike any trained on)
gets an MLP output extrapolated from nothing. :class:`FeatureNovelty` scores each point by
its squared Mahalanobis distance ``d2`` to the training features' mean and covariance, and
:func:`trust` turns it into a weight in [0, 1]: 1 up to ``inner`` (a quantile of the training
points' own ``d2``), 0 from ``outer`` on, linear between. The registration blends the learned
eigenvalues and association features with plain GICP's by that weight
(:func:`gloam_jax.learned.attributes`), so novel features fall back to GICP's plane.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from gloam_jax.errors import InputError

DEFAULT_QUANTILE = 0.99  # of the training points' d2: the trusted region
DEFAULT_RAMP = 2.0  # outer = ramp * inner: the fall-back is complete at twice that d2


class FeatureNovelty(NamedTuple):
    """Training features' mean (C,) and whitening factor (C, C), ``d2 = |(f - mean) @ factor|^2``;
    squared distances ``inner`` < ``outer`` (scalars) where trust starts and ends falling."""

    mean: Array | np.ndarray
    factor: Array | np.ndarray
    inner: Array | float
    outer: Array | float

    def squared_distance(self, f: Array) -> Array:
        """``d2`` (...,) of features (..., C)."""
        z = (f - jnp.asarray(self.mean, f.dtype)) @ jnp.asarray(self.factor, f.dtype)
        return jnp.sum(z * z, axis=-1)

    def trust(self, f: Array) -> Array:
        """Weight (...,) in [0, 1] of the learned parts at features (..., C)."""
        inner = jnp.asarray(self.inner, f.dtype)
        outer = jnp.asarray(self.outer, f.dtype)
        return jnp.clip((outer - self.squared_distance(f)) / (outer - inner), 0.0, 1.0)


def fit_novelty(
    features: np.ndarray | Sequence[np.ndarray],
    *,
    quantile: float = DEFAULT_QUANTILE,
    ramp: float = DEFAULT_RAMP,
) -> FeatureNovelty:
    """Fit on the training points' PCA features, (N, C) or a list of per-scan (N_i, C)."""
    parts = [features] if isinstance(features, np.ndarray) else list(features)
    x = np.concatenate([np.asarray(p, np.float64) for p in parts]) if parts else np.zeros((0, 0))
    x = x[np.all(np.isfinite(x), axis=1)] if x.ndim == 2 else x
    if x.ndim != 2 or len(x) <= x.shape[1]:
        raise InputError(None, f"novelty needs more finite rows than columns, got {x.shape}")
    if not 0 < quantile < 1:
        raise InputError(None, f"novelty quantile must be in (0, 1), got {quantile}")
    if not ramp > 1:
        raise InputError(None, f"novelty ramp must be above 1, got {ramp}")
    mean = x.mean(axis=0)
    covariance = np.cov(x, rowvar=False) + 1e-9 * np.eye(x.shape[1])
    # covariance^-1 = factor factor^T with factor = inverse of the Cholesky factor, transposed.
    factor = np.linalg.inv(np.linalg.cholesky(covariance)).T
    d2 = np.sum(((x - mean) @ factor) ** 2, axis=1)
    inner = float(np.quantile(d2, quantile))
    return FeatureNovelty(mean, factor, inner, ramp * inner)
