"""PCA of backbone features to six dimensions, fitted once and then frozen.

Fitted with scikit-learn on features gathered from several training scans (optionally
standardised first), then kept as plain arrays, so that it applies in NumPy or inside JAX
code without scikit-learn: ``f = ((x - mean) / scale) @ components.T``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from gloam_jax.errors import InputError

if TYPE_CHECKING:
    from jax import Array

# Columns whose spread is below this count as constant: standardising leaves them alone
# instead of blowing their rounding noise up to unit variance.
_MIN_SCALE = 1e-6


class FeaturePCA(NamedTuple):
    """Frozen PCA: mean (D,), scale (D,), components (C, D), explained_variance_ratio (C,)."""

    mean: np.ndarray
    scale: np.ndarray
    components: np.ndarray
    explained_variance_ratio: np.ndarray

    @property
    def input_dim(self) -> int:
        return self.components.shape[1]

    def affine(self) -> tuple[np.ndarray, np.ndarray]:
        """The projection as one affine map ``x W + bias``: W (D, C), bias (C,), float64."""
        # ((x - mean) / scale) C^T = x W + bias: no (N, D) temporaries.
        return (self.components / self.scale).T, -(self.mean / self.scale) @ self.components.T

    def transform(self, features: np.ndarray | Array) -> np.ndarray | Array:
        """Projected features (..., C) of features (..., D), NumPy or JAX, in their dtype."""
        W, bias = self.affine()
        return features @ W.astype(features.dtype) + bias.astype(features.dtype)


def fit_pca(
    features: np.ndarray | Sequence[np.ndarray],
    n_components: int = 6,
    *,
    standardize: bool = True,
    max_rows: int = 200_000,
    seed: int = 0,
) -> FeaturePCA:
    """Fit the PCA on (N, D) features or a list of per-scan (N_i, D) arrays.

    Rows with NaN or inf are dropped; at most ``max_rows`` rows, drawn without replacement
    with ``seed``, are used (the fit is deterministic).
    """
    parts = [features] if isinstance(features, np.ndarray) else list(features)
    if not parts or any(np.ndim(p) != 2 for p in parts):
        raise InputError(None, "PCA needs (N, D) feature arrays")
    dims = {p.shape[1] for p in parts}
    if len(dims) != 1:
        raise InputError(None, f"PCA features differ in width: {sorted(dims)} columns")
    x = np.concatenate(parts).astype(np.float64)
    x = x[np.all(np.isfinite(x), axis=1)]
    if len(x) > max_rows:
        x = x[np.sort(np.random.default_rng(seed).choice(len(x), max_rows, replace=False))]
    if n_components > min(x.shape):
        raise InputError(
            None,
            f"PCA to {n_components} dimensions needs at least {n_components} rows and "
            f"columns of finite features, got {x.shape}",
        )
    mean = x.mean(axis=0)
    scale = x.std(axis=0) if standardize else np.ones(x.shape[1])
    scale = np.where(scale > _MIN_SCALE, scale, 1.0)
    from sklearn.decomposition import PCA  # only for fitting, which runs once

    pca = PCA(n_components=n_components, svd_solver="full").fit((x - mean) / scale)
    # Fold scikit-learn's own centring (zero up to rounding here) into the stored mean.
    return FeaturePCA(
        mean=mean + scale * pca.mean_,
        scale=scale,
        components=pca.components_.copy(),
        explained_variance_ratio=pca.explained_variance_ratio_.copy(),
    )
