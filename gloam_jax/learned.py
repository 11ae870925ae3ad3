"""The learned parts of Generalized LOAM and what they do to a cloud.

Both MLPs are 6 -> 4 -> 3 with a ReLU on the hidden layer and a linear output (the paper
says only "the ReLU activation function is used"; Algorithm 1 clamps eigenvalues at eps
because raw outputs may be zero or negative, and the association features are distances in
an unbounded space, so neither output is rectified). 43 parameters each: 6x4 + 4 + 4x3 + 3
(the paper counts 46).

* :class:`FeatureConversionMLP`: PCA features f (6,) -> association features f_bar (3,),
  concatenated with xyz for the nearest-neighbour search (Eq. 3 of the paper).
* :class:`EigenvalueEstimationMLP`: f (6,) -> raw eigenvalues (3,) for Algorithm 1
  (:func:`gloam_jax.covariance.learned_values`).

:class:`Learned` holds the parts a registration uses (a pytree; None keeps plain GICP's step)
and :func:`attributes` turns k-NN eigendecompositions and PCA features into the covariances
and association features that GICP consumes. The model file around the MLPs (PCA, backbone,
provenance) is :mod:`gloam_jax.models`.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from gloam_jax import covariance as cov
from gloam_jax import geometry as geo
from gloam_jax.errors import InputError
from gloam_jax.features.novelty import FeatureNovelty

FEATURE_DIM = 6  # PCA output, the MLPs' input
HIDDEN_DIM = 4
OUTPUT_DIM = 3
DEFAULT_EPS = 1e-3  # Algorithm 1's eigenvalue floor, on unit-norm eigenvalue vectors


class MLP(NamedTuple):
    """6 -> 4 (ReLU) -> 3 (linear): w1 (6, 4), b1 (4,), w2 (4, 3), b2 (3,)."""

    w1: Array
    b1: Array
    w2: Array
    b2: Array

    @classmethod
    def init(cls, key: Array) -> MLP:
        """Uniform in +-1/sqrt(fan_in) (weights and biases), as torch.nn.Linear."""
        return cls(*_init_params(key))

    def __call__(self, f: Array) -> Array:
        """Outputs (..., 3) of features (..., 6): one point or a batch."""
        hidden = jax.nn.relu(geo.matmul(f[..., None, :], self.w1)[..., 0, :] + self.b1)
        return geo.matmul(hidden[..., None, :], self.w2)[..., 0, :] + self.b2

    def constant(self, output: Array) -> MLP:
        """This MLP with zero output weights and bias ``output`` (3,): it outputs ``output``
        for every input, yet its output weights keep a gradient (the hidden layer is kept)."""
        b2 = jnp.asarray(output, self.b2.dtype)
        return self._replace(w2=jnp.zeros_like(self.w2), b2=b2)


@jax.jit
def _init_params(key: Array) -> tuple[Array, ...]:
    # Jitted: drawn eagerly, each random op would compile on its own.
    shapes = ((FEATURE_DIM, HIDDEN_DIM), (HIDDEN_DIM,), (HIDDEN_DIM, OUTPUT_DIM), (OUTPUT_DIM,))
    fan_ins = (FEATURE_DIM, FEATURE_DIM, HIDDEN_DIM, HIDDEN_DIM)
    keys = jax.random.split(key, len(shapes))
    return tuple(
        jax.random.uniform(k, s, jnp.float32, -1.0, 1.0) / np.sqrt(f)
        for k, s, f in zip(keys, shapes, fan_ins, strict=True)
    )


class FeatureConversionMLP(MLP):
    """PCA features (..., 6) -> association features (..., 3) (Sec. III-C)."""


class EigenvalueEstimationMLP(MLP):
    """PCA features (..., 6) -> raw eigenvalues (..., 3) for Algorithm 1 (Sec. III-D)."""


def plane_output(eps: float | Array) -> Array:
    """The eigenvalue MLP output (3,) that Algorithm 1 turns into GICP's plane (eps, 1, 1),
    scaled by 1/sqrt(2 + eps^2) like every covariance, which leaves the registration as it is."""
    return jnp.stack([jnp.asarray(eps, jnp.float32), jnp.float32(1.0), jnp.float32(1.0)])


# Which learned parts each method uses: (data association, covariance estimation).
METHODS = {"gicp": (False, False), "gicp_da": (True, False), "gicp_ce": (False, True),
           "gloam": (True, True)}  # fmt: skip


def check_method(method: str) -> tuple[bool, bool]:
    """(data association, covariance estimation) of ``method``; InputError if unknown."""
    if method not in METHODS:
        raise InputError(None, f"unknown method '{method}' (choose from {', '.join(METHODS)})")
    return METHODS[method]


class Head(NamedTuple):
    """The net backbone's last layer, fine-tuned in training: weight (H, D), bias (D,)."""

    weight: Array
    bias: Array


class Learned(NamedTuple):
    """The learned parts a registration uses, as a pytree; None keeps plain GICP's step.

    ``eps`` is Algorithm 1's fixed floor and ``max_thickness`` an optional bound on its
    planes (:func:`gloam_jax.covariance.learned_values`), not trained weights:
    :func:`attributes` stops their gradients, so a trainer may carry a whole Learned as its
    parameters. ``head`` is set only while training fine-tunes the backbone's last layer: the
    batch then recomputes the scans' PCA features from it (:mod:`gloam_jax.training.head`);
    odometry never reads it. ``novelty``, when set, clamps the MLPs' input features to the
    region of the training features (also gradient-stopped)."""

    conversion: FeatureConversionMLP | None = None  # data association in [xyz, f] space
    eigenvalue: EigenvalueEstimationMLP | None = None  # covariances by Algorithm 1
    eps: float | Array = DEFAULT_EPS
    head: Head | None = None
    max_thickness: float | Array | None = None  # at least eps, so that GICP's plane fits
    novelty: FeatureNovelty | None = None

    def as_gicp(self) -> Learned:
        """These parts set to register as plain GICP with the plane regulariser: constant
        association features (xyz-nearest association) and the eigenvalue MLP at
        :func:`plane_output` (GICP's covariances up to one common scale)."""
        parts = self
        if self.conversion is not None:
            parts = parts._replace(conversion=self.conversion.constant(jnp.zeros(OUTPUT_DIM)))
        if self.eigenvalue is not None:
            parts = parts._replace(eigenvalue=self.eigenvalue.constant(plane_output(self.eps)))
        return parts

    def for_method(self, method: str) -> Learned:
        """The parts that ``method`` (a key of :data:`METHODS`) uses; the others None."""
        da, ce = check_method(method)
        return self._replace(
            conversion=self.conversion if da else None, eigenvalue=self.eigenvalue if ce else None
        )


def without_gicp_constants(parts: Learned, regularizer: str) -> Learned:
    """``parts`` less each MLP that registers exactly as plain GICP's own step does: a
    conversion MLP with zero output weights (equal features for all points: xyz-nearest
    association) and, under the ``plane`` regulariser, an eigenvalue MLP whose constant output
    Algorithm 1 turns into a multiple of GICP's plane (:func:`plane_output`). A model exported
    as the fall-back to GICP (:meth:`Learned.as_gicp`) then runs GICP's path itself, bit for
    bit and without features, instead of its covariances scaled by 1/sqrt(2 + eps^2).
    Reads concrete weights (host side), not traced ones."""
    if parts.conversion is not None and not np.any(np.asarray(parts.conversion.w2)):
        parts = parts._replace(conversion=None)
    eig = parts.eigenvalue
    if eig is not None and regularizer == "plane" and not np.any(np.asarray(eig.w2)):
        values = np.maximum(np.sort(np.asarray(eig.b2, np.float64)), float(parts.eps))
        plane = np.array([cov.PLANE_EPS, 1.0, 1.0])
        if np.allclose(values / values[2], plane, rtol=1e-6, atol=0.0):
            parts = parts._replace(eigenvalue=None)
    return parts


def attributes(
    values: Array, vectors: Array, pca_features: Array, learned: Learned, regularizer: str
) -> tuple[Array, Array]:
    """Covariances (..., 3, 3) and association features (..., F) of points whose k-NN
    covariances have ascending eigenvalues (..., 3) and eigenvectors (..., 3, 3), with PCA
    features (..., 6) (any width when ``learned`` uses none).

    Plain GICP regularises the eigenvalues (``regularizer``) and has no features (F = 0); a
    learned eigenvalue MLP replaces the regulariser (Algorithm 1), a conversion MLP gives the
    features of data association (F = 3). With ``learned.novelty``, both MLPs see features
    clamped to the region they were trained on (:meth:`FeatureNovelty.clamp`).
    """
    f = pca_features.astype(vectors.dtype)
    eps, cap, novelty = jax.lax.stop_gradient((learned.eps, learned.max_thickness, learned.novelty))
    if novelty is not None:
        f = novelty.clamp(f)
    if learned.eigenvalue is None:
        covs = cov.recompose(vectors, cov.EIGENVALUE_RULES[regularizer](values))
    else:
        raw = learned.eigenvalue(f)
        covs = cov.recompose(vectors, cov.learned_values(raw, eps, cap).astype(vectors.dtype))
    if learned.conversion is None:
        return covs, jnp.zeros((*vectors.shape[:-2], 0), vectors.dtype)
    return covs, learned.conversion(f)


@partial(jax.jit, static_argnames=("regularizer",))
def cloud_attributes(
    points: Array, neighbours: Array, pca_features: Array, learned: Learned, regularizer: str
) -> tuple[Array, Array, Array, Array]:
    """:func:`attributes` of points (N, 3) from their k-NN indices (N, k), and the surface
    normals (N, 3) and planarity (N,) of their neighbourhoods (:func:`covariance.surface`)."""
    values, vectors = cov.eigendecompose(cov.knn_covariances(points, neighbours))
    return (*attributes(values, vectors, pca_features, learned, regularizer),
            *cov.surface(values, vectors))  # fmt: skip
