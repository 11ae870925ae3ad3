"""Tests of gloam_jax.training.losses: chain, segment plans, and the differentiable KITTI RTE
against metrics.kitti_rte, in float64 (float32 where the fast path is checked)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shared_data import shared_path

from gloam_jax.errors import InputError
from gloam_jax.io import read_kitti_poses
from gloam_jax.metrics import kitti_rte, path_lengths
from gloam_jax.training import (
    TRAINING_FRACTIONS,
    SegmentPlan,
    chain,
    relative_rotation_error,
    relative_translation_error,
    scaled_lengths,
    segment_errors,
    segment_plan,
)

DEG_PER_100M = 180.0 / math.pi * 100.0


@pytest.fixture(autouse=True, scope="module")
def x64():
    """float64 for this module only; the rest of the suite runs the default float32 path."""
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", False)


def wiggly(n: int, spacing: float = 1.0, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) KITTI-like ground truth: forward along camera z with drifting yaw, pitch, roll."""
    rng = np.random.default_rng(seed)
    angles = np.cumsum(rng.normal(0.0, [0.002, 0.02, 0.002], (n, 3)), axis=0)
    rot = Rotation.from_rotvec(angles).as_matrix()
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rot
    poses[1:, :3, 3] = np.cumsum(spacing * rot[:-1, :, 2], axis=0)
    return poses


def relative(poses: np.ndarray) -> np.ndarray:
    """Frame-to-frame poses (N - 1, 4, 4) ``T_prev_curr``, general inverses as the devkit."""
    return np.linalg.inv(poses[:-1]) @ poses[1:]


def rigid_noise(n: int, seed: int, sigma_t: float = 0.02, sigma_r: float = 2e-3) -> np.ndarray:
    """(n, 4, 4) small random rigid motions: translations ~sigma_t m, rotations ~sigma_r rad."""
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, sigma_r, (n, 3))).as_matrix()
    out[:, :3, 3] = rng.normal(0.0, sigma_t, (n, 3))
    return out


def chain_loop(rel: np.ndarray) -> np.ndarray:
    """Reference for chain: (N, 4, 4) -> (N + 1, 4, 4) by a plain numpy loop."""
    out = [np.eye(4)]
    for T in rel:
        out.append(out[-1] @ T)
    return np.stack(out)


def perturbed(gt: np.ndarray, seed: int) -> np.ndarray:
    """Estimate from the ground-truth increments, each right-multiplied by a small random motion
    (on the host, so that the tests compile only the code under test)."""
    return gt[0] @ chain_loop(relative(gt) @ rigid_noise(gt.shape[0] - 1, seed))


def both_losses(est: jax.Array, gt: np.ndarray, plan: SegmentPlan) -> jax.Array:
    """(2,): translation (fraction) and rotation (rad/m) error."""
    return jnp.stack(
        [relative_translation_error(est, gt, plan), relative_rotation_error(est, gt, plan)]
    )


@jax.jit
def devkit_twin(est: jax.Array, gt: np.ndarray, plan: SegmentPlan) -> tuple[jax.Array, ...]:
    """Per-segment (t_err, r_err) and both means, compiled once per shape (eager JAX would
    dispatch, and compile, every op one by one)."""
    return (*segment_errors(est, gt, plan), both_losses(est, gt, plan))


def kitti_or_skip(name: str) -> np.ndarray:
    return read_kitti_poses(shared_path(f"kitti_gt_poses/{name}.txt"))


# --------------------------------------------------------------------------------------------
# chain


@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-12), (np.float32, 1e-5)])
def test_chain_matches_numpy_loop(dtype, rtol) -> None:
    rel = rigid_noise(40, seed=1, sigma_t=0.5, sigma_r=0.1)
    out = jax.jit(chain)(rel.astype(dtype))
    assert out.shape == (41, 4, 4) and out.dtype == dtype
    np.testing.assert_allclose(out, chain_loop(rel), rtol=rtol, atol=rtol)


def test_chain_batch_axes_and_empty() -> None:
    rel = rigid_noise(24, seed=2, sigma_r=0.1).reshape(2, 3, 4, 4, 4)
    out = jax.jit(chain)(rel)
    assert out.shape == (2, 3, 5, 4, 4)
    np.testing.assert_allclose(out[1, 2], jax.jit(chain)(rel[1, 2]), rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(chain(np.zeros((0, 4, 4))), np.eye(4)[None])


def test_chain_rejects_bad_shape() -> None:
    with pytest.raises(InputError, match=r"\(\.\.\., N, 4, 4\), got \(5, 3, 4\)"):
        chain(np.zeros((5, 3, 4)))


# --------------------------------------------------------------------------------------------
# segment plans


def test_plan_matches_kitti_rte_segments() -> None:
    gt = wiggly(900, spacing=1.1)
    plan = segment_plan(gt, step=7)
    res = kitti_rte(gt, gt, step=7, precision="float64")
    assert plan.num_poses == 900 and plan.num_segments == res.num_segments > 0
    np.testing.assert_array_equal(plan.first_frames, res.first_frames)
    np.testing.assert_array_equal(plan.last_frames, res.last_frames)
    np.testing.assert_array_equal(plan.lengths, res.segment_lengths)


def test_scaled_lengths_give_a_short_window_segments() -> None:
    gt = wiggly(151)  # 150 m, far below KITTI's shortest 100 m segments from most frames
    lengths = scaled_lengths(gt)
    total = path_lengths(gt)[-1]
    np.testing.assert_allclose(lengths, np.asarray(TRAINING_FRACTIONS) * total, rtol=1e-15)
    plan = segment_plan(gt, lengths)
    # Every length has at least the segment from frame 0, and each ends strictly beyond L.
    assert set(plan.lengths.tolist()) == set(lengths)
    d = path_lengths(gt)
    assert np.all(d[plan.last_frames] - d[plan.first_frames] > plan.lengths)
    assert np.all(d[plan.last_frames - 1] - d[plan.first_frames] <= plan.lengths)


def test_plan_errors_name_the_problem() -> None:
    with pytest.raises(
        InputError, match=r"50 poses is 49\.000 m long.*shortest segment length 100 m"
    ):
        segment_plan(wiggly(50))
    # A segment must be strictly longer than L: exactly 100 m of path is still too short.
    line = np.tile(np.eye(4), (101, 1, 1))
    line[:, 2, 3] = np.arange(101.0)
    with pytest.raises(InputError, match="not longer than"):
        segment_plan(line, source="seq.txt")
    with pytest.raises(InputError, match=r"^seq\.txt: ground-truth poses must have shape"):
        segment_plan(np.zeros((10, 3, 4)), source="seq.txt")
    with pytest.raises(ValueError, match="step must be a positive integer"):
        segment_plan(line, step=0)
    with pytest.raises(ValueError, match="distinct"):
        segment_plan(line, (10.0, 10.0))
    with pytest.raises(ValueError, match="must lie in"):
        segment_plan(line, (10.0, -5.0))
    with pytest.raises(ValueError, match=r"must lie in \(0, 1\)"):
        scaled_lengths(line, (0.5, 1.0))
    with pytest.raises(InputError, match="101 poses has zero length"):
        scaled_lengths(np.tile(np.eye(4), (101, 1, 1)))


def test_loss_rejects_mismatched_pose_counts() -> None:
    gt = wiggly(300)
    plan = segment_plan(gt)
    with pytest.raises(InputError, match="estimated trajectory has 299 poses .* for 300"):
        relative_translation_error(gt[:-1], gt, plan)
    with pytest.raises(InputError, match="ground-truth trajectory has 301 poses .* for 300"):
        relative_rotation_error(gt, wiggly(301), plan)
    with pytest.raises(InputError, match=r"estimated poses must have shape \(N, 4, 4\)"):
        relative_translation_error(gt[None], gt, plan)


# --------------------------------------------------------------------------------------------
# agreement with the devkit (metrics.kitti_rte, float64)


def _check_against_devkit(gt: np.ndarray, est: np.ndarray, r_rtol: float = 1e-9, **plan_kw) -> None:
    res = kitti_rte(gt, est, precision="float64", **plan_kw)
    plan = segment_plan(gt, **plan_kw)
    t, r, (t_mean, r_mean) = devkit_twin(est, gt, plan)
    np.testing.assert_allclose(t, res.t_err, rtol=1e-9)
    # The devkit's arccos(c) moves by ~1e-16 / angle for a rounding of c, ~1e-12 rad at the
    # smallest error angles here: the absolute slack on the angles.
    np.testing.assert_allclose(r * plan.lengths, res.r_err * plan.lengths, rtol=r_rtol, atol=1e-12)
    # Units: a fraction and rad/m; kitti_rte reports percent and deg/100m.
    np.testing.assert_allclose(t_mean, res.t_err_percent / 100.0, rtol=1e-9)
    np.testing.assert_allclose(r_mean * DEG_PER_100M, res.r_err_deg_per_100m, rtol=1e-9)
    assert t_mean > 1e-4 and r_mean > 1e-7  # the comparison is not between two zeros


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_kitti_rte_on_synthetic_trajectories(seed) -> None:
    gt = wiggly(1000, spacing=1.2, seed=seed)
    est = perturbed(gt, seed=10 + seed)
    _check_against_devkit(gt, est)
    _check_against_devkit(gt, est, step=3, lengths=(50, 125, 333))


@pytest.mark.parametrize("sequence", ["04", "03"])
def test_matches_kitti_rte_on_kitti_ground_truth(sequence) -> None:
    # Poses read from text are orthonormal to ~1e-7 only: the twin must invert as the devkit.
    # For such rotations the skew part (used here) and the trace (the devkit's arccos) give
    # angles ~1e-9 apart (1e-11 once orthonormalised); the means still agree to 1e-9.
    gt = kitti_or_skip(sequence)
    est = perturbed(gt, seed=3)
    _check_against_devkit(gt, est, r_rtol=3e-9)


# --------------------------------------------------------------------------------------------
# gradients


def test_gradient_matches_central_differences() -> None:
    gt = wiggly(31, seed=4)
    plan = segment_plan(gt, (8.0, 15.5, 25.0), step=3)
    rel0 = jnp.asarray(relative(gt) @ rigid_noise(30, seed=5))

    def f(delta):
        # delta (30, 3, 4) moves every entry of the relative poses' top rows. r_err (rad/m) is
        # ~100x smaller than t_err here: weigh it up so that both terms count.
        est = gt[0] @ chain(rel0.at[:, :3, :].add(delta))
        return both_losses(est, gt, plan) @ jnp.array([1.0, 100.0])

    zero = np.zeros((30, 3, 4))
    grad = jax.jit(jax.grad(f))(zero)
    h = 1e-6
    basis = np.eye(zero.size).reshape(-1, *zero.shape) * h
    fd = jax.jit(jax.vmap(lambda d: (f(d) - f(-d)) / (2 * h)))(basis)
    fd = np.asarray(fd).reshape(zero.shape)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())


def test_zero_error_and_finite_gradient_at_ground_truth() -> None:
    # Whole-metre zigzag without rotation: every product and inverse is exact, so the chained
    # estimate is exactly the ground truth and the error poses are exactly I: the norms sit at
    # their non-differentiable zero, where only the guards keep gradients finite.
    n = 301
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = 20 - np.abs((np.arange(n) % 40) - 20)  # starts at the origin, as chain
    gt[:, 2, 3] = np.arange(n)
    plan = segment_plan(gt, (50, 100))

    def total(rel):
        est = chain(rel)
        return both_losses(est, gt, plan).sum(), est

    (value, est), grad = jax.jit(jax.value_and_grad(total, has_aux=True))(relative(gt))
    np.testing.assert_array_equal(est, gt)
    assert value == 0.0
    assert np.isfinite(grad).all()


def test_float32_near_zero_error() -> None:
    # The training precision: float32 relative poses chained over 200 frames.
    gt = wiggly(200, seed=6)
    plan = segment_plan(gt, (60, 120))

    @jax.jit
    def losses(rel, gt, plan):
        return both_losses(gt[0] @ chain(rel), gt, plan)

    losses = losses(relative(gt).astype(np.float32), gt.astype(np.float32), plan)
    assert losses.dtype == np.float32
    assert np.all((losses >= 0.0) & (losses < 1e-5))


# --------------------------------------------------------------------------------------------
# jit and vmap


def test_jit_vmap_over_a_batch_of_trajectories() -> None:
    gt = wiggly(1000, spacing=1.2, seed=7)  # the shape of the synthetic trajectories above
    lengths = (100, 350, 700)
    plan = segment_plan(gt, lengths, step=5)
    ests = np.stack([perturbed(gt, seed=s) for s in range(3)])
    # The plan passes through jit as a pytree argument (num_poses static) and is shared by vmap.
    batched = jax.jit(jax.vmap(both_losses, (0, None, None)))(ests, gt, plan)
    assert batched.shape == (3, 2)
    for est, (t_err, r_err) in zip(ests, batched, strict=True):
        res = kitti_rte(gt, est, step=5, lengths=lengths, precision="float64")
        np.testing.assert_allclose([t_err, r_err], [res.t_err.mean(), res.r_err.mean()], rtol=1e-9)
