"""Per-point covariances from k nearest neighbours, and their eigenvalue regularisers.

A covariance is ``V diag(lambda) V^T`` with eigenvalues ascending. Regularisers replace the
eigenvalues and keep the eigenvectors:

* ``plane``: (eps, 1, 1), GICP's plane-to-plane model (Segal et al.), eps along the normal;
* ``raw_eps``: the measured eigenvalues, clamped below at eps (m^2);
* :func:`learned` (Generalized LOAM, Algorithm 1): eigenvalues from the Eigenvalue Estimation
  MLP, sorted ascending, clamped below at eps, scaled to unit L2 norm. It needs the MLP's
  output, so it is not in :data:`REGULARIZERS`.

Eigenvectors depend on the points only and sit under ``stop_gradient``: the eigendecomposition
has no usable derivative where eigenvalues repeat, and learned models only need gradients
with respect to the eigenvalues they produce.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

PLANE_EPS = 1e-3


def knn_covariances(points: Array, neighbours: Array) -> Array:
    """Sample covariance of each point's neighbourhood: (N, 3), (N, k) int -> (N, 3, 3)."""
    nb = points[neighbours]  # (N, k, 3)
    centred = nb - jnp.mean(nb, axis=1, keepdims=True)
    return jnp.einsum("nki,nkj->nij", centred, centred) / neighbours.shape[1]


def eigendecompose(covariances: Array) -> tuple[Array, Array]:
    """Ascending eigenvalues (N, 3) and eigenvectors as columns (N, 3, 3), without gradients."""
    values, vectors = jnp.linalg.eigh(jax.lax.stop_gradient(covariances))
    return values, vectors


def recompose(vectors: Array, values: Array) -> Array:
    """``V diag(values) V^T``: (N, 3, 3), (N, 3) -> (N, 3, 3)."""
    return jnp.einsum("nij,nj,nkj->nik", vectors, values, vectors)


def plane(covariances: Array, eps: float = PLANE_EPS) -> Array:
    """GICP's regulariser: eigenvalues replaced by (eps, 1, 1)."""
    _, vectors = eigendecompose(covariances)
    values = jnp.broadcast_to(jnp.array([eps, 1.0, 1.0], vectors.dtype), vectors.shape[:-1])
    return recompose(vectors, values)


def raw_eps(covariances: Array, eps: float = PLANE_EPS) -> Array:
    """Measured eigenvalues, clamped below at eps: keeps lines and spheres as they are."""
    values, vectors = eigendecompose(covariances)
    return recompose(vectors, jnp.maximum(values, eps))


def learned(covariances: Array, eigenvalues: Array, eps: float | Array) -> Array:
    """Algorithm 1 of Generalized LOAM: k-NN eigenvectors, MLP eigenvalues.

    ``eigenvalues`` (N, 3) is the Eigenvalue Estimation MLP's raw output. It is sorted
    ascending (the smallest goes along the normal), clamped below at ``eps`` > 0 (no rank drop;
    before the scaling, so all-zero outputs stay finite) and divided by its L2 norm, then
    recomposed with the eigenvectors of ``covariances`` (N, 3, 3) -> (N, 3, 3).
    Differentiable with respect to ``eigenvalues`` (and ``eps``), not the covariances.
    """
    _, vectors = eigendecompose(covariances)
    values = jnp.maximum(jnp.sort(eigenvalues, axis=-1), eps)
    values = values / jnp.linalg.norm(values, axis=-1, keepdims=True)
    return recompose(vectors, values.astype(vectors.dtype))


REGULARIZERS = {"plane": plane, "raw_eps": raw_eps}
