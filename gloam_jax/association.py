"""Data association in [xyz, f] space among fixed candidate sets (Eq. 3 of the paper).

Each source point a_i has K candidate target points b_ij (from a k-d tree query in xyz, so
the shapes stay static); the cost of a pair is ``||a - b||^2 + ||fa - fb||^2`` with fa, fb
the Feature Conversion MLP's outputs. :func:`hard` takes the cheapest valid candidate, as the
paper; :func:`soft` spreads a unit weight over the valid candidates with a softmax, so a
training loss sees gradients with respect to the features through the choice as well. With
zero features both reduce to plain nearest-neighbour association in xyz.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from gloam_jax import geometry as geo


def costs(a: Array, b: Array, fa: Array, fb: Array) -> Array:
    """Pair costs (N, K): a (N, 3), b (N, K, 3), fa (N, F), fb (N, K, F)."""
    # Same expression as the xyz-only association (gicp._whitened): with fa = fb = 0 the feature
    # term adds an exact 0, so the argmin is bit-identical.
    d, df = b - a[:, None, :], fb - fa[:, None, :]
    return geo.dot(d, d) + geo.dot(df, df)


def hard(a: Array, b: Array, fa: Array, fb: Array, valid: Array) -> Array:
    """Index (N,) int of the cheapest valid candidate; 0 for rows with none (check ``valid``)."""
    return jnp.argmin(jnp.where(valid, costs(a, b, fa, fb), jnp.inf), axis=1)


def log_soft(
    a: Array, b: Array, fa: Array, fb: Array, valid: Array, temperature: float | Array
) -> Array:
    """Log-weights (N, K) of :func:`soft`: -inf for invalid candidates and for rows without a
    valid one. Finite gradients everywhere (``exp(0.5 * log_soft)`` is a NaN-free square root
    of the weights, which a weighted least-squares residual needs)."""
    logits = jnp.where(valid, -costs(a, b, fa, fb) / temperature, -jnp.inf)
    top = jnp.max(logits, axis=1, keepdims=True)
    # Shift by the row maximum for range; a row with no valid candidate has -inf there.
    top = jax.lax.stop_gradient(jnp.where(jnp.isfinite(top), top, 0.0))
    shifted = jnp.where(valid, logits - top, 0.0)
    total = jnp.sum(jnp.where(valid, jnp.exp(shifted), 0.0), axis=1, keepdims=True)
    log_total = jnp.log(jnp.where(total > 0, total, 1.0))
    return jnp.where(valid, shifted - log_total, -jnp.inf)


def soft(
    a: Array, b: Array, fa: Array, fb: Array, valid: Array, temperature: float | Array
) -> Array:
    """Weights (N, K) ``softmax(-cost / temperature)`` over the valid candidates.

    ``temperature`` is in the cost's units (m^2 plus feature units). Invalid candidates get
    0; rows without a valid candidate are all 0. Finite, with finite gradients, everywhere.
    """
    return jnp.exp(log_soft(a, b, fa, fb, valid, temperature))
