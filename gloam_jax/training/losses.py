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
on the host (numpy) and the loss has static shapes. The plan, :func:`segment_plan`,
:func:`scaled_lengths` and :data:`TRAINING_FRACTIONS` live in :mod:`gloam_jax.metrics` (the
same segment choice as ``kitti_rte``) and are re-exported here.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from gloam_jax.errors import InputError
from gloam_jax.geometry import vee
from gloam_jax.metrics import TRAINING_FRACTIONS, SegmentPlan, scaled_lengths, segment_plan

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

# A plan's index and length arrays are leaves and its pose count static, so a plan can be
# closed over or passed to jitted functions.
jax.tree_util.register_dataclass(
    SegmentPlan, data_fields=["first_frames", "last_frames", "lengths"], meta_fields=["num_poses"]
)

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


def safe_norm(v: Array) -> Array:
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
    sin = 0.5 * safe_norm(vee(R - jnp.swapaxes(R, -1, -2)))
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
    return safe_norm(err[:, :3, 3]) / lengths, _rotation_angle(err[:, :3, :3]) / lengths


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
