"""Differentiable KITTI relative trajectory error, the training loss of the paper's Eq. (8).

Poses follow :mod:`gloam_jax.geometry`: ``(N, 4, 4)`` matrices ``T_world_frame``. Odometry
gives frame-to-frame estimates ``T_prev_curr``; :func:`chain` turns them into a trajectory.

The loss is the KITTI devkit's relative trajectory error (:func:`gloam_jax.metrics.kitti_rte`
with ``precision="float64"``) as a JAX function of the estimate. Eq. (8) sums
``||dt_gt - dt_est||`` over sub-trajectories of the KITTI lengths; that norm is the translation
norm of the devkit's error pose ``inv(inv(E_f) E_l) @ inv(G_f) G_l`` (a rotation keeps lengths).
The paper calls its loss the devkit's translational RTE, so, as in the devkit, each term is
divided by its nominal length and the terms are averaged over all segments: the training loss
is the benchmark number, as a fraction (m/m) rather than percent.

Which segments exist depends on the ground truth only, so a :class:`SegmentPlan` is built once
on the host (numpy) and the loss has static shapes.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike
from numpy.typing import ArrayLike as NpArrayLike
from numpy.typing import NDArray

from gloam_jax.errors import InputError
from gloam_jax.geometry import vee
from gloam_jax.io import as_poses
from gloam_jax.metrics import DEFAULT_LENGTHS, path_lengths

__all__ = [
    "TRAINING_FRACTIONS",
    "SegmentPlan",
    "chain",
    "relative_rotation_error",
    "relative_translation_error",
    "scaled_lengths",
    "segment_errors",
    "segment_plan",
]

TRAINING_FRACTIONS: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
"""Default segment lengths of :func:`scaled_lengths`, as fractions of the path length: the
KITTI lengths 100..800 m as if the training window were 1 km long."""

Source = str | os.PathLike[str] | None

# Full float32 products: the default lets GPUs use TF32 (10-bit mantissa), which would put
# decimetre errors on kilometre-scale chained translations, the size of the signal itself.
_matmul = partial(jnp.matmul, precision=jax.lax.Precision.HIGHEST)


def chain(T_rel: ArrayLike) -> Array:
    """Absolute poses from relative ones: (..., N, 4, 4) ``T_prev_curr`` -> (..., N + 1, 4, 4).

    Pose 0 is the identity and pose ``k`` is ``T_rel[0] @ ... @ T_rel[k - 1]``. The products
    run as a parallel prefix scan (log N depth, not a chain of N dependent steps), in the
    input's dtype.
    """
    T_rel = jnp.asarray(T_rel)
    if T_rel.ndim < 3 or T_rel.shape[-2:] != (4, 4):
        raise InputError(None, f"relative poses must have shape (..., N, 4, 4), got {T_rel.shape}")
    if not jnp.issubdtype(T_rel.dtype, jnp.floating):
        raise InputError(None, f"relative poses must be floating point, got {T_rel.dtype}")
    eye = jnp.broadcast_to(jnp.eye(4, dtype=T_rel.dtype), (*T_rel.shape[:-3], 1, 4, 4))
    # Scanning [I, T_1, ..., T_N] puts pose 0 in place and handles N = 0 without a branch.
    elems = jnp.concatenate([eye, T_rel], axis=-3)
    return jax.lax.associative_scan(_matmul, elems, axis=elems.ndim - 3)


@partial(
    jax.tree_util.register_dataclass,
    data_fields=["first_frames", "last_frames", "lengths"],
    meta_fields=["num_poses"],
)
@dataclass(frozen=True, eq=False)
class SegmentPlan:
    """The devkit's segments of one ground-truth trajectory, in its order (first frame outer,
    length inner); built by :func:`segment_plan`.

    ``first_frames``, ``last_frames``: (S,) int64 pose indices; ``lengths``: (S,) float64
    nominal segment lengths, metres; ``num_poses``: the trajectory's pose count N. A pytree with
    ``num_poses`` static, so it can be closed over or passed to jitted functions.
    """

    first_frames: NDArray[np.int64]
    last_frames: NDArray[np.int64]
    lengths: NDArray[np.float64]
    num_poses: int

    @property
    def num_segments(self) -> int:
        """S, the number of segments."""
        return int(np.shape(self.first_frames)[0])


def _check_values(values: Sequence[float], what: str, upper: float) -> NDArray[np.float64]:
    """1-D, non-empty, distinct, finite values in (0, upper), as float64; else ValueError."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{what} must be a non-empty sequence of numbers, got {values!r}")
    if not np.all(np.isfinite(arr) & (arr > 0.0) & (arr < upper)):
        raise ValueError(f"{what} must lie in (0, {upper:g}), got {list(values)}")
    if np.unique(arr).size != arr.size:
        raise ValueError(f"{what} must be distinct, got {list(values)}")
    return arr


def segment_plan(
    gt_poses: NpArrayLike,
    lengths: Sequence[float] = DEFAULT_LENGTHS,
    *,
    step: int = 10,
    source: Source = None,
) -> SegmentPlan:
    """Segments of ``gt_poses`` (N, 4, 4) exactly as :func:`~gloam_jax.metrics.kitti_rte`
    (``precision="float64"``) picks them, for ``lengths`` in metres.

    A segment starts at every ``step``-th frame ``f``; for each length ``L`` it ends at the first
    frame whose ground-truth path distance exceeds ``dist[f] + L`` and is dropped when there is
    none. Lengths may be fractional (see :func:`scaled_lengths`); ``kitti_rte`` itself takes whole
    metres only. Raises :class:`InputError` for bad poses or when no segment fits.
    """
    if int(step) != step or step < 1:
        raise ValueError(f"step must be a positive integer, got {step!r}")
    lens = _check_values(lengths, "segment lengths (m)", math.inf)
    gt = as_poses(gt_poses, "ground-truth", source)
    n = gt.shape[0]
    dist = path_lengths(gt, source=source)
    starts = np.arange(0, n, int(step), dtype=np.int64)
    first = np.repeat(starts, lens.size)
    seg_len = np.tile(lens, starts.size)
    # dist is non-decreasing, so the devkit's linear scan for the first dist[j] > dist[f] + L
    # is a right-sided binary search (as in metrics.kitti_rte).
    last = np.searchsorted(dist, dist[first] + seg_len, side="right")
    keep = last < n
    if not keep.any():
        raise InputError(
            source,
            f"no segment fits: the ground-truth path of {n} poses is {dist[-1]:.3f} m long, "
            f"not longer than the shortest segment length {lens.min():g} m",
        )
    return SegmentPlan(
        first_frames=first[keep],
        last_frames=last[keep].astype(np.int64),
        lengths=seg_len[keep],
        num_poses=n,
    )


def scaled_lengths(
    gt_poses: NpArrayLike,
    fractions: Sequence[float] = TRAINING_FRACTIONS,
    *,
    source: Source = None,
) -> tuple[float, ...]:
    """Segment lengths in metres for a short training window: ``fractions`` (each in (0, 1)) of
    the ground-truth path length of ``gt_poses`` (N, 4, 4).

    Every fraction below 1 leaves at least the segment from frame 0, so a 150 m window gets
    segments of 15..120 m with the defaults. Raises :class:`InputError` for a path of length 0.
    """
    frac = _check_values(fractions, "length fractions", 1.0)
    gt = as_poses(gt_poses, "ground-truth", source)
    total = float(path_lengths(gt, source=source)[-1])
    if total <= 0.0:
        raise InputError(
            source,
            f"the ground-truth path of {gt.shape[0]} poses has zero length, so no "
            "segment length can be scaled from it",
        )
    return tuple(float(f * total) for f in frac)


def _trajectory(poses: ArrayLike, plan: SegmentPlan, what: str) -> Array:
    """``poses`` as an array of shape (plan.num_poses, 4, 4); InputError otherwise."""
    poses = jnp.asarray(poses)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InputError(None, f"{what} poses must have shape (N, 4, 4), got {poses.shape}")
    if poses.shape[0] != plan.num_poses:
        raise InputError(
            None,
            f"{what} trajectory has {poses.shape[0]} poses but the segment plan was built "
            f"for {plan.num_poses} ground-truth poses",
        )
    return poses


def _safe_norm(v: Array) -> Array:
    """Norm over the last axis with a finite (zero) gradient at v = 0."""
    sq = jnp.sum(v * v, axis=-1)
    positive = sq > 0.0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _rotation_angle(R: Array) -> Array:
    """Angle in [0, pi] of rotations (..., 3, 3), radians.

    atan2(sin, cos) with sin from the skew part and cos from the trace: the same angle as the
    devkit's arccos of the trace, but arccos has an infinite slope at angle 0 (a perfect
    estimate), where this one's gradient stays finite.
    """
    sin = 0.5 * _safe_norm(vee(R - jnp.swapaxes(R, -1, -2)))
    cos = 0.5 * (jnp.trace(R, axis1=-2, axis2=-1) - 1.0)
    return jnp.arctan2(sin, cos)


def _affine_inverse(T: Array) -> Array:
    """General inverse of homogeneous matrices (..., 4, 4) with bottom row [0, 0, 0, 1].

    Not the rigid transpose: the devkit inverts in general, and ground truth read from text is
    orthonormal to ~1e-7 only, which the transpose would turn into a mismatch with kitti_rte.
    The 3x3 block by its adjugate (rows' cross products) instead of an LU solve: a few
    elementwise ops that compile fast and differentiate simply, exact to rounding near a
    rotation (determinant ~1).
    """
    r0, r1, r2 = T[..., 0, :3], T[..., 1, :3], T[..., 2, :3]
    c0, c1, c2 = jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)
    det = jnp.sum(r0 * c0, axis=-1)
    A_inv = jnp.stack([c0, c1, c2], axis=-1) / det[..., None, None]
    t_inv = -_matmul(A_inv, T[..., :3, 3:4])[..., 0]
    bottom = jnp.broadcast_to(jnp.eye(4, dtype=T.dtype)[3], (*T.shape[:-2], 1, 4))
    top = jnp.concatenate([A_inv, t_inv[..., None]], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def segment_errors(T_est: ArrayLike, T_gt: ArrayLike, plan: SegmentPlan) -> tuple[Array, Array]:
    """Per-segment errors of ``T_est`` against ``T_gt`` (both (N, 4, 4), bottom rows
    [0, 0, 0, 1]), in ``plan``'s order.

    Returns ``(t_err, r_err)``, each (S,): the translation norm of the error pose
    ``inv(inv(E_f) E_l) @ inv(G_f) G_l`` divided by the nominal length (a fraction, m/m), and its
    rotation angle divided by the length (rad/m), as ``kitti_rte``'s ``t_err`` and ``r_err``;
    in the inputs' promoted dtype, at least float32.
    """
    T_est = _trajectory(T_est, plan, "estimated")
    T_gt = _trajectory(T_gt, plan, "ground-truth")
    dtype = jnp.result_type(T_est, T_gt, jnp.float32)
    T_est, T_gt = T_est.astype(dtype), T_gt.astype(dtype)
    first, last = jnp.asarray(plan.first_frames), jnp.asarray(plan.last_frames)
    # inv(inv(E_f) E_l) = inv(E_l) E_f: every pose is inverted once (N inverses, not 3 per
    # segment), both trajectories in one batch.
    inv_est, inv_gt = _affine_inverse(jnp.stack([T_est, T_gt]))
    err = _matmul(_matmul(inv_est[last], T_est[first]), _matmul(inv_gt[first], T_gt[last]))
    lengths = jnp.asarray(plan.lengths, dtype)
    return _safe_norm(err[:, :3, 3]) / lengths, _rotation_angle(err[:, :3, :3]) / lengths


def relative_translation_error(T_est: ArrayLike, T_gt: ArrayLike, plan: SegmentPlan) -> Array:
    """The devkit's translation error of ``T_est`` (N, 4, 4): a scalar fraction (m/m).

    Mean over all segments of all lengths of the error pose's translation norm / length; times
    100 it is ``kitti_rte(..., precision="float64").t_err_percent``. Differentiable, NaN-free in
    value and gradient at ``T_est == T_gt``.
    """
    return jnp.mean(segment_errors(T_est, T_gt, plan)[0])


def relative_rotation_error(T_est: ArrayLike, T_gt: ArrayLike, plan: SegmentPlan) -> Array:
    """The devkit's rotation error of ``T_est`` (N, 4, 4): a scalar in rad/m.

    Mean over all segments of the error pose's rotation angle / length; times 180/pi * 100 it is
    ``kitti_rte(..., precision="float64").r_err_deg_per_100m``. NaN-free at ``T_est == T_gt``.
    """
    return jnp.mean(segment_errors(T_est, T_gt, plan)[1])
