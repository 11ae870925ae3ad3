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

from gloam_jax import geometry as geo

PLANE_EPS = 1e-3


def knn_covariances(points: Array, neighbours: Array) -> Array:
    """Sample covariance of each point's neighbourhood: (N, 3), (N, k) int -> (N, 3, 3)."""
    nb = points[neighbours]  # (N, k, 3)
    centred = nb - jnp.mean(nb, axis=1, keepdims=True)
    return jnp.einsum("nki,nkj->nij", centred, centred) / neighbours.shape[1]


def eigendecompose(covariances: Array) -> tuple[Array, Array]:
    """Ascending eigenvalues (N, 3) and eigenvectors as columns (N, 3, 3), without gradients."""
    return _eigh3(jax.lax.stop_gradient(covariances))


def _eigh3(A: Array) -> tuple[Array, Array]:
    """Closed-form eigendecomposition of symmetric 3x3 matrices (..., 3, 3), ascending.

    XLA's batched ``eigh`` on CPU costs ~1.5 us per matrix, the largest share of a frame's
    preprocessing; this elementwise version fuses. Eigenvalues by the trigonometric method
    (Smith, 1961); the eigenvector of the better-separated extreme eigenvalue from cross
    products of rows of ``A - lambda I``, the second one from the 2x2 problem in its
    orthogonal complement (Eberly's robust ordering), the third by a cross product.
    """
    scale = jnp.maximum(jnp.max(jnp.abs(A), axis=(-2, -1)), jnp.finfo(A.dtype).tiny)
    A = A / scale[..., None, None]  # O(1) entries: no under/overflow in the cubic
    q = jnp.trace(A, axis1=-2, axis2=-1) / 3
    off = A[..., 0, 1] ** 2 + A[..., 0, 2] ** 2 + A[..., 1, 2] ** 2
    diag = jnp.diagonal(A, axis1=-2, axis2=-1) - q[..., None]
    p = jnp.sqrt((jnp.sum(diag**2, axis=-1) + 2 * off) / 6)
    p_safe = jnp.where(p > 0, p, 1.0)
    B = (A - q[..., None, None] * jnp.eye(3, dtype=A.dtype)) / p_safe[..., None, None]
    r = jnp.clip(jnp.linalg.det(B) / 2, -1.0, 1.0)
    phi = jnp.arccos(r) / 3
    high = q + 2 * p * jnp.cos(phi)
    low = q + 2 * p * jnp.cos(phi + 2 * jnp.pi / 3)
    mid = 3 * q - high - low
    # The extreme eigenvalue farther from the middle one has a well-conditioned eigenvector.
    low_first = (mid - low) >= (high - mid)
    first = jnp.where(low_first, low, high)
    v1 = _null_vector(A - first[..., None, None] * jnp.eye(3, dtype=A.dtype))
    u, w = _complement(v1)
    # The remaining two eigenvalues in the plane spanned by (u, w): a symmetric 2x2 problem.
    Au, Aw = jnp.einsum("...ij,...j->...i", A, u), jnp.einsum("...ij,...j->...i", A, w)
    a, b, c = jnp.sum(u * Au, -1), jnp.sum(u * Aw, -1), jnp.sum(w * Aw, -1)
    x0, y0 = b, mid - a  # two candidate eigenvectors for mid: keep the longer
    x1, y1 = mid - c, b
    longer = x0**2 + y0**2 >= x1**2 + y1**2
    x, y = jnp.where(longer, x0, x1), jnp.where(longer, y0, y1)
    norm = jnp.sqrt(x**2 + y**2)
    # Repeated middle eigenvalue: any direction in the plane is an eigenvector.
    x, y = (
        jnp.where(norm > 0, x / jnp.where(norm > 0, norm, 1.0), 1.0),
        jnp.where(norm > 0, y / jnp.where(norm > 0, norm, 1.0), 0.0),
    )
    v2 = x[..., None] * u + y[..., None] * w
    v3 = jnp.cross(v1, v2)
    v_low = jnp.where(low_first[..., None], v1, v3)
    v_high = jnp.where(low_first[..., None], v3, v1)
    values = jnp.stack([low, mid, high], axis=-1) * scale[..., None]
    return values, jnp.stack([v_low, v2, v_high], axis=-1)


def _null_vector(M: Array) -> Array:
    """Unit vector v with M v ~ 0 for a rank-2 symmetric M (..., 3, 3): the longest cross
    product of two rows (any unit vector when M is ~0)."""
    r0, r1, r2 = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    crosses = jnp.stack([jnp.cross(r0, r1), jnp.cross(r0, r2), jnp.cross(r1, r2)], axis=-2)
    n2 = jnp.sum(crosses**2, axis=-1)
    best = jnp.argmax(n2, axis=-1)
    v = jnp.take_along_axis(crosses, best[..., None, None], axis=-2)[..., 0, :]
    n = jnp.sqrt(jnp.take_along_axis(n2, best[..., None], axis=-1))
    fallback = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0], M.dtype), v.shape)
    return jnp.where(n > 0, v / jnp.where(n > 0, n, 1.0), fallback)


def _complement(v: Array) -> tuple[Array, Array]:
    """Two unit vectors completing the unit vector v (..., 3) to an orthonormal basis."""
    # Cross with the axis least aligned with v, so the result is never near zero.
    axis = jnp.eye(3, dtype=v.dtype)[jnp.argmin(jnp.abs(v), axis=-1)]
    u = jnp.cross(v, axis)
    u = u / jnp.linalg.norm(u, axis=-1, keepdims=True)
    return u, jnp.cross(v, u)


def surface(values: Array, vectors: Array) -> tuple[Array, Array]:
    """Surface normals (..., 3), the smallest eigenvectors, and planarity (...,)
    ``(l2 - l1) / l3`` of ascending eigenvalues: near 1 on a plane, near 0 along a line (a
    sparse scan ring) or in a ball, where the normal means little."""
    tiny = jnp.finfo(values.dtype).tiny
    planarity = (values[..., 1] - values[..., 0]) / jnp.maximum(values[..., 2], tiny)
    return vectors[..., :, 0], planarity


def recompose(vectors: Array, values: Array) -> Array:
    """``V diag(values) V^T``: (..., 3, 3), (..., 3) -> (..., 3, 3)."""
    return geo.matmul(vectors * values[..., None, :], jnp.swapaxes(vectors, -1, -2))


def plane_values(values: Array, eps: float = PLANE_EPS) -> Array:
    """GICP's eigenvalues (eps, 1, 1) in place of measured ascending ones (..., 3)."""
    return jnp.broadcast_to(jnp.array([eps, 1.0, 1.0], values.dtype), values.shape)


def raw_eps_values(values: Array, eps: float = PLANE_EPS) -> Array:
    """Measured ascending eigenvalues (..., 3), clamped below at eps: keeps lines and spheres."""
    return jnp.maximum(values, eps)


def learned_values(
    eigenvalues: Array, eps: float | Array, max_thickness: float | Array | None = None
) -> Array:
    """Algorithm 1's eigenvalues from the Eigenvalue Estimation MLP's raw output (..., 3):
    sorted ascending (the smallest goes along the normal), clamped below at ``eps`` > 0 (no
    rank drop; before the scaling, so all-zero outputs stay finite), L2-normalised.

    With ``max_thickness``, the smallest is then held at or below that fraction of the middle
    one: planes no thicker than it (GICP's plane is ``PLANE_EPS`` thick)."""
    values = jnp.maximum(_sort3(eigenvalues), eps)
    if max_thickness is not None:
        values = values.at[..., 0].set(jnp.minimum(values[..., 0], max_thickness * values[..., 1]))
    return values / jnp.sqrt(geo.dot(values, values))[..., None]


def plane(covariances: Array, eps: float = PLANE_EPS) -> Array:
    """GICP's regulariser: eigenvalues replaced by (eps, 1, 1)."""
    values, vectors = eigendecompose(covariances)
    return recompose(vectors, plane_values(values, eps))


def raw_eps(covariances: Array, eps: float = PLANE_EPS) -> Array:
    """Measured eigenvalues, clamped below at eps."""
    values, vectors = eigendecompose(covariances)
    return recompose(vectors, raw_eps_values(values, eps))


def learned(
    covariances: Array,
    eigenvalues: Array,
    eps: float | Array,
    max_thickness: float | Array | None = None,
) -> Array:
    """Algorithm 1 of Generalized LOAM: k-NN eigenvectors of ``covariances`` (N, 3, 3), MLP
    eigenvalues (N, 3) through :func:`learned_values` -> (N, 3, 3).
    Differentiable with respect to ``eigenvalues`` (and ``eps``), not the covariances.
    """
    _, vectors = eigendecompose(covariances)
    values = learned_values(eigenvalues, eps, max_thickness)
    return recompose(vectors, values.astype(vectors.dtype))


def _sort3(x: Array) -> Array:
    """Ascending sort of the last axis of length 3, elementwise (XLA's sort op is a slow
    comparator loop on CPU, and its reductions over 3 wide rows are library calls):
    (..., 3) -> (..., 3)."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    low = jnp.minimum(jnp.minimum(x0, x1), x2)
    high = jnp.maximum(jnp.maximum(x0, x1), x2)
    mid = jnp.clip(x0 + x1 + x2 - low - high, low, high)  # rounding stays in order
    return jnp.stack([low, mid, high], axis=-1)


REGULARIZERS = {"plane": plane, "raw_eps": raw_eps}
"""Regularisers of k-NN covariances (N, 3, 3) -> (N, 3, 3)."""

EIGENVALUE_RULES = {"plane": plane_values, "raw_eps": raw_eps_values}
"""The same regularisers on an eigendecomposition: ascending eigenvalues (N, 3) -> (N, 3),
for callers that decompose once and recompose many times (batch training)."""
