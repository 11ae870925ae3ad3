"""Generalized ICP in JAX: one round's math, Levenberg-Marquardt via optimistix.

Registration estimates ``T_target_source``. Each outer round gets, from the host's k-d
tree (:mod:`gloam_jax.registration`), the K nearest target points of every transformed
source point (a fixed ``(N, K)`` candidate set); a jitted solve chooses each source point's
partner among its candidates (by distance, in [xyz, f] space when the cloud has association
features) and runs a few Levenberg-Marquardt steps on the increment ``xi = (rho, phi)`` of
``T = retract(xi, T_round)``.

The increment rotates the source about its own origin (the sensor) by ``exp(phi)`` and shifts
it by ``rho``, both in target axes. Unlike a left se(3) increment, which rotates about the
target's origin (kilometres away in a long drive), it keeps rotation and translation
decoupled and the Gauss-Newton matrix ``H`` well scaled wherever the sensor is: its blocks are
the information on the sensor's position (m) and attitude (rad).

The residual of a pair is ``b - T a``, whitened by the Cholesky factor of
``C_b + R C_a R^T`` (Segal et al., 2009), so the squared norm is the Mahalanobis distance.
WhitenedPairs farther apart than ``max_correspondence_distance`` are dropped. Within a round the
pairs, their weights and inliers are fixed, so the round's cost is an exact quadratic form in
``(rho, exp(phi) - I)``, summed once (:func:`round_cost`): LM works on 12 residuals.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax import Array

from gloam_jax import association
from gloam_jax import geometry as geo
from gloam_jax.errors import check_setting, is_int, is_positive

# Candidates found before the points moved at most this share of the correspondence distance
# are fresh: a round may converge on them (registration.align_prepared).
FRESH = 0.1


@dataclass(frozen=True)
class GICPConfig:
    """Registration settings (defaults follow small_gicp's documented ones)."""

    max_correspondence_distance: float = 1.0  # m
    num_candidates: int = 1  # target candidates per source point, chosen among in JAX
    max_iterations: int = 20  # outer rounds, each refreshing the candidate sets
    inner_steps: int = 2  # LM steps per round
    # A round queries the target's tree again only once a source point may have moved this far
    # (m) since the candidates were found; until then it keeps them (0: every round queries).
    # At most FRESH x max_correspondence_distance, where convergence counts them as fresh.
    requery_shift: float = 0.0
    rotation_eps: float = float(np.deg2rad(0.1))  # convergence: rotation update below (rad)
    translation_eps: float = 1e-3  # and translation update below (m)
    adjoint: Literal["unrolled", "implicit"] = "unrolled"  # differentiation through LM
    # A direction is weak (degenerate) when the scene's constraint along it is below this
    # fraction of the strongest one's and fewer than degeneracy_support planar points face it
    # (see registration.conditioning; calibrated in docs/degeneracy.md); rotations count as
    # their sweep at lever_arm metres.
    degeneracy_threshold: float = 4e-3
    degeneracy_support: float = 3.0
    lever_arm: float = 10.0  # m

    def __post_init__(self) -> None:
        for name in ("max_correspondence_distance", "rotation_eps", "translation_eps",
                     "degeneracy_threshold", "degeneracy_support", "lever_arm"):  # fmt: skip
            check_setting(is_positive(v := getattr(self, name)), f"gicp.{name}", "positive", v)
        shift, fresh = self.requery_shift, FRESH * self.max_correspondence_distance
        ok = shift == 0 or (is_positive(shift) and shift <= fresh)
        check_setting(ok, "gicp.requery_shift", f"between 0 and {fresh:g} m", shift)
        for name in ("num_candidates", "max_iterations"):
            check_setting(is_int(v := getattr(self, name), 1), f"gicp.{name}", "an integer >= 1", v)
        # optimistix's LM spends its first step initialising, so one step never moves.
        check_setting(is_int(self.inner_steps, 2), "gicp.inner_steps", "an integer >= 2",
                      self.inner_steps)  # fmt: skip


class Cloud(NamedTuple):
    """Device-side padded cloud: points (P, 3), covariances (P, 3, 3), mask (P,) and the
    association features (P, F) (F = 0 for plain GICP)."""

    points: Array
    covs: Array
    mask: Array
    features: Array


def _inverse_cholesky(C: Array) -> Array:
    """``L^-1`` for ``C = L L^T`` (3x3, written out so XLA fuses it): (..., 3, 3) -> (..., 3, 3),
    lower triangular, so that ``L^-1 r`` whitens a residual of covariance C."""
    l00 = jnp.sqrt(C[..., 0, 0])
    l10 = C[..., 1, 0] / l00
    l20 = C[..., 2, 0] / l00
    l11 = jnp.sqrt(C[..., 1, 1] - l10 * l10)
    l21 = (C[..., 2, 1] - l20 * l10) / l11
    l22 = jnp.sqrt(C[..., 2, 2] - l20 * l20 - l21 * l21)
    m00, m11, m22 = 1 / l00, 1 / l11, 1 / l22
    m10 = -l10 * m00 * m11
    m21 = -l21 * m11 * m22
    m20 = -(l20 * m00 + l21 * m10) * m22
    zero = jnp.zeros_like(m00)
    rows = [[m00, zero, zero], [m10, m11, zero], [m20, m21, m22]]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def candidate_cloud(target: Cloud, candidates: Array, valid: Array) -> Cloud:
    """The (N, K) candidates of N source points as a cloud of (N, K) rows: points (N, K, 3),
    covariances (N, K, 3, 3), mask ``valid`` (N, K), features (N, K, F)."""
    return Cloud(target.points[candidates], target.covs[candidates], valid,
                 target.features[candidates])  # fmt: skip


class Partners(NamedTuple):
    """Each source point's partners: target points (N, J, 3), covariances (N, J, 3, 3) and
    the square roots of their weights (N, J). Hard association: J = 1, weight 1 (0 where a
    point has no candidate); soft: the J = K candidates with softmax weights."""

    points: Array
    covs: Array
    sqrt_weight: Array


def choose_partners(T: Array, source: Cloud, candidates: Cloud, temperature=None) -> Partners:
    """Partners among the (N, K) ``candidates`` (see :func:`candidate_cloud`) at T: the
    cheapest in [xyz, f] space (``temperature`` None) or all of them, softmax-weighted (see
    association.soft)."""
    a = geo.rotate(T[:3, :3], source.points) + T[:3, 3]
    b, fb, valid = candidates.points, candidates.features, candidates.mask
    if temperature is None:
        j = association.hard(a, b, source.features, fb, valid)[:, None]
        return Partners(
            jnp.take_along_axis(b, j[..., None], axis=1),
            jnp.take_along_axis(candidates.covs, j[..., None, None], axis=1),
            jnp.take_along_axis(valid, j, axis=1).astype(a.dtype),
        )
    log_w = association.log_soft(a, b, source.features, fb, valid, temperature)
    return Partners(b, candidates.covs, jnp.exp(0.5 * log_w))


class WhitenedPairs(NamedTuple):
    """A round's pairs, fixed through its LM steps: source points a (N, 3), their partners'
    target points b (N, J, 3), the whitening ``W = sqrt(w) L^-1`` (N, J, 3, 3) of each pair's
    ``C_b + R C_a R^T = L L^T`` at the round's starting rotation R, and which pairs exist
    (N, J)."""

    a: Array
    b: Array
    W: Array
    valid: Array


def make_pairs(R: Array, source: Cloud, partners: Partners) -> WhitenedPairs:
    """The :class:`WhitenedPairs` of ``partners``, weights taken at the rotation R (3, 3)."""
    C = partners.covs + geo.matmul(geo.matmul(R, source.covs), R.T)[:, None]
    W = _inverse_cholesky(C) * partners.sqrt_weight[..., None, None]
    valid = source.mask[:, None] & (partners.sqrt_weight > 0)
    return WhitenedPairs(source.points, partners.points, W, valid)


def _whitened(T: Array, pairs: WhitenedPairs, max_d2) -> tuple[Array, Array, Array]:
    """Whitened, weighted residuals ``W (b - T a)`` (N, J, 3), zero for outliers (pairs
    farther apart than sqrt(max_d2)), the inlier mask (N, J) and the moved points T a (N, 3)."""
    moved = geo.rotate(T[:3, :3], pairs.a) + T[:3, 3]
    r = pairs.b - moved[:, None, :]
    inlier = pairs.valid & (geo.dot(r, r) < max_d2)
    e = geo.rotate(pairs.W, r)
    return jnp.where(inlier[..., None], e, 0.0), inlier, moved


def retract(xi: Array, T0: Array) -> Array:
    """``T0`` rotated by ``exp(phi)`` about its own origin, then shifted by ``rho``, with
    ``xi = (rho, phi)`` (6,) in the axes ``T0`` maps into: (4, 4)."""
    return geo.make_transform(geo.so3_exp(xi[3:]) @ T0[:3, :3], T0[:3, 3] + xi[:3])


_retract_jit = jax.jit(retract)
_so3_log_jit = jax.jit(geo.so3_log)


def increment(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """The ``xi`` (6,) with ``retract(xi, T_from) = T_to``, in float64 on the host."""
    phi = np.asarray(_so3_log_jit(T_to[:3, :3] @ T_from[:3, :3].T), np.float64)
    return np.r_[T_to[:3, 3] - T_from[:3, 3], phi]


def retract_host(xi: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """:func:`retract` in float64 on the host, with an orthonormal rotation: (4, 4)."""
    T = np.array(_retract_jit(np.asarray(xi, np.float64), np.asarray(T0, np.float64)), np.float64)
    u, _, vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = u @ vt
    return T


class RoundCost(NamedTuple):
    """A round's cost as a quadratic form: ``|L^T g - u|^2`` equals the sum of squared
    whitened residuals up to a constant, with ``g = (rho, s vec(exp(phi) - I))`` (12,):
    L (12, 12) lower triangular, u (12,), s the scale of the rotated source points (m)."""

    L: Array
    u: Array
    s: Array


def round_cost(T0, pairs: WhitenedPairs, max_d2) -> RoundCost:
    """The :class:`RoundCost` of the pairs from T0, inliers those closer than sqrt(max_d2).

    With pairs, weights and inliers fixed, a pair's residual is ``r0 - rho - (exp(phi) - I) q``
    (q = R0 a, r0 its residual at T0), linear in ``g``: the cost ``sum |W r|^2`` is exactly
    ``c - 2 h.g + g.G g``. G (12, 12) and h are summed once; LM then works on 12 residuals
    instead of 3N. ``s`` balances G's blocks (rotations move points s metres from the sensor);
    ten machine epsilons of its mean eigenvalue on the diagonal keep the Cholesky factor
    finite (no inliers, coplanar points).
    """
    q = geo.rotate(T0[:3, :3], pairs.a)
    r0 = pairs.b - (q + T0[:3, 3])[:, None, :]
    inlier = pairs.valid & (geo.dot(r0, r0) < max_d2)
    W = jnp.where(inlier[..., None, None], pairs.W, 0.0)
    M = geo.matmul(jnp.swapaxes(W, -1, -2), W)  # the pair's information (N, J, 3, 3)
    count = jnp.sum(inlier, axis=1).astype(q.dtype)
    mean_sq = jnp.sum(count * geo.dot(q, q)) / jnp.maximum(jnp.sum(count), 1.0)
    s = jax.lax.stop_gradient(jnp.sqrt(mean_sq) + 1e-3)
    v = jnp.concatenate([jnp.ones_like(q[:, :1]), q / s], axis=1)  # r = r0 - (v kron I) g
    G = jnp.einsum("ni,nk,njab->iakb", v, v, M).reshape(12, 12)
    h = jnp.einsum("ni,na->ia", v, jnp.einsum("njab,njb->na", M, r0)).reshape(12)
    jitter = 10 * jnp.finfo(G.dtype).eps * jnp.trace(G) / 12 + jnp.finfo(G.dtype).tiny
    L = jnp.linalg.cholesky(G + jitter * jnp.eye(12, dtype=G.dtype))
    return RoundCost(L, jax.scipy.linalg.solve_triangular(L, h, lower=True), s)


def _residuals(xi: Array, cost: RoundCost) -> Array:
    # The weights hold the round's starting rotation, as GICP holds them fixed within a
    # linearisation; being constant in xi rather than cut by stop_gradient, this is exactly
    # the function LM minimises, so gradients through the solve are exact too.
    E = geo.so3_exp(xi[3:]) - jnp.eye(3, dtype=xi.dtype)
    g = jnp.concatenate([xi[:3], cost.s * E.T.reshape(9)])  # vec: E's columns in order
    return cost.L.T @ g - cost.u


_ADJOINTS = {"unrolled": optx.RecursiveCheckpointAdjoint(), "implicit": optx.ImplicitAdjoint()}


@jax.jit
def gauss_newton_system(T, pairs: WhitenedPairs, max_d2):
    """H = J^T J, b = J^T e, error = e.e and the inlier count at T.

    J is the whitened residuals' Jacobian with respect to the increment xi = (rho, phi) of
    :func:`retract`, ``d(b - exp(phi) R a - t - rho)/d xi = -[I, -hat(R a)]``, with the pairs'
    weights (their round's) held fixed, as GICP does within a linearisation.
    """
    e, inlier, p = _whitened(T, pairs, max_d2)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=p.dtype), (p.shape[0], 3, 3))
    # d(-exp(phi) q)/d phi = hat(q), q = R a
    columns = jnp.concatenate([-eye, geo.hat(p - T[:3, 3])], axis=-1)  # (N, 3, 6)
    J = jnp.einsum("njab,nbk->njak", pairs.W, columns)
    J = jnp.where(inlier[..., None, None], J, 0.0)
    H = jnp.einsum("njai,njak->ik", J, J)
    b = jnp.einsum("njai,nja->i", J, e)
    return H, b, jnp.sum(e * e), jnp.sum(inlier)


def _lm(T0, pairs: WhitenedPairs, max_d2, inner_steps, adjoint):
    """A few LM steps from T0 with fixed pairs: the increment xi (6,)."""
    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8, linear_solver=lx.Normal(lx.Cholesky()))
    sol = optx.least_squares(
        _residuals,
        solver,
        jnp.zeros(6, T0.dtype),
        round_cost(T0, pairs, max_d2),
        max_steps=inner_steps,
        adjoint=_ADJOINTS[adjoint],
        throw=False,
    )
    return sol.value


def gicp_round(
    T0,
    source: Cloud,
    candidates: Cloud,
    max_d2,
    inner_steps: int,
    adjoint: str = "unrolled",
    temperature=None,
) -> tuple[Array, Array, WhitenedPairs]:
    """One outer round, traceable (jit, vmap, grad): partners among the (N, K)
    ``candidates`` (:func:`candidate_cloud`) at T0, then LM from T0.

    Returns T (4, 4), the increment xi (6,) with ``T = retract(xi, T0)`` and the pairs.
    Partners are chosen among the candidates once, at T0, and held through the LM steps:
    re-choosing by distance inside LM would change the Mahalanobis cost in jumps that its
    trust region rejects.
    """
    partners = choose_partners(T0, source, candidates, temperature)
    pairs = make_pairs(T0[:3, :3], source, partners)
    xi = _lm(T0, pairs, max_d2, inner_steps, adjoint)
    return retract(xi, T0), xi, pairs


@partial(jax.jit, static_argnames=("inner_steps", "adjoint"))
def solve_round(
    T0,
    source: Cloud,
    target: Cloud,
    candidates,
    valid,
    max_d2,
    inner_steps: int,
    adjoint: str = "unrolled",
) -> tuple[Array, Array, tuple]:
    """:func:`gicp_round` with hard association, then :func:`gauss_newton_system`'s
    (H, b, error, inliers) at the result, whose step decides convergence."""
    candidates = candidate_cloud(target, candidates, valid)
    T, xi, pairs = gicp_round(T0, source, candidates, max_d2, inner_steps, adjoint)
    return T, xi, gauss_newton_system(T, pairs, max_d2)
