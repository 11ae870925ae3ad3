"""Tests of gloam_jax.metrics: KITTI RTE, ATE, the combined report and the plot."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shared_data import shared_path

from gloam_jax.errors import InputError
from gloam_jax.io import frame_motions
from gloam_jax.metrics import (
    DEFAULT_LENGTHS,
    ate,
    evaluate,
    evaluate_without_rte,
    frame_rotation_drift,
    kitti_rte,
    path_lengths,
    plot_evaluation,
)

DEG_PER_100M = 180.0 / math.pi * 100.0


def straight_line(n: int, spacing: float = 1.0) -> np.ndarray:
    """(n, 4, 4) identity-rotation poses moving along +z (camera forward) by ``spacing``."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = spacing * np.arange(n)
    return poses


def rot_y(angle: np.ndarray) -> np.ndarray:
    """Rotations about y (yaw for KITTI camera frames): (n,) -> (n, 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((*np.shape(angle), 3, 3))
    out[..., 0, 0], out[..., 0, 2], out[..., 1, 1] = c, s, 1.0
    out[..., 2, 0], out[..., 2, 2] = -s, c
    return out


def load_kitti(path: Path) -> np.ndarray:
    rows = np.loadtxt(path).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :] = rows
    return poses


def expected_counts_unit_line(n: int, step: int) -> dict[int, int]:
    # With 1 m spacing a segment of L metres from f ends at f + L + 1 (strictly longer than L).
    return {
        length: sum(1 for f in range(0, n, step) if f + length + 1 <= n - 1)
        for length in DEFAULT_LENGTHS
    }


# --------------------------------------------------------------------------------------------
# path_lengths


def test_path_lengths_straight_line() -> None:
    d = path_lengths(straight_line(5, spacing=2.5))
    np.testing.assert_array_equal(d, [0.0, 2.5, 5.0, 7.5, 10.0])


# --------------------------------------------------------------------------------------------
# kitti_rte


def test_identity_estimate_is_exactly_zero() -> None:
    gt = straight_line(1001)
    res = kitti_rte(gt, gt.copy())
    assert res.t_err_percent == 0.0
    assert res.r_err_deg_per_100m == 0.0
    assert np.all(res.t_err == 0.0) and np.all(res.r_err == 0.0)


def test_identity_estimate_on_kitti_is_rounding_only() -> None:
    gt = load_kitti(shared_path("kitti_gt_poses/04.txt"))
    res = kitti_rte(gt, gt.copy())
    assert res.num_segments > 0
    assert res.t_err_percent < 1e-12
    # arccos near 1 amplifies rounding to ~1e-8 rad; still negligible per 100 m.
    assert res.r_err_deg_per_100m < 1e-6


def test_segment_counts_unit_line_worked_by_hand() -> None:
    # 1001 poses 1 m apart, first frames 0, 10, ..., 1000. A 100 m segment from f ends at
    # f + 101, which must be <= 1000, so f <= 899: f = 0..890 -> 90 segments; each extra
    # 100 m removes 10 first frames: 90, 80, ..., 20 -> 440 in total.
    res = kitti_rte(straight_line(1001), straight_line(1001))
    expected = {100: 90, 200: 80, 300: 70, 400: 60, 500: 50, 600: 40, 700: 30, 800: 20}
    assert expected == expected_counts_unit_line(1001, 10)
    assert {k: v["num_segments"] for k, v in res.per_length.items()} == expected
    assert res.num_segments == 440
    np.testing.assert_array_equal(res.last_frames - res.first_frames, res.segment_lengths + 1)
    # Devkit order: first frame outer loop, length inner loop.
    assert res.first_frames[:8].tolist() == [0] * 8
    assert res.segment_lengths[:8].tolist() == list(DEFAULT_LENGTHS)


def test_step_changes_first_frames() -> None:
    res = kitti_rte(straight_line(301), straight_line(301), step=1, lengths=(100,))
    # f + 101 <= 300  ->  f = 0..199
    assert res.num_segments == 200
    np.testing.assert_array_equal(res.first_frames, np.arange(200))


def test_scale_drift_on_straight_line() -> None:
    gt = straight_line(1001)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    res = kitti_rte(gt, est, precision="float64")
    # The devkit divides by the nominal length L while the segment really spans L + 1 m of
    # ground truth (first frame strictly beyond L), so each segment reads 1% * (L + 1) / L.
    np.testing.assert_allclose(
        res.t_err, 0.01 * (res.segment_lengths + 1) / res.segment_lengths, rtol=1e-12
    )
    counts = expected_counts_unit_line(1001, 10)
    expected = sum(c * (length + 1) / length for length, c in counts.items()) / sum(counts.values())
    np.testing.assert_allclose(res.t_err_percent, expected, rtol=1e-6)
    for length, v in res.per_length.items():
        np.testing.assert_allclose(v["t_err_percent"], (length + 1) / length, rtol=1e-12)
    assert res.r_err_deg_per_100m == 0.0


def test_scale_drift_relative_to_actual_distance_is_one_percent() -> None:
    gt = straight_line(1001)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    res = kitti_rte(gt, est)
    d = path_lengths(gt)
    actual = d[res.last_frames] - d[res.first_frames]
    np.testing.assert_allclose(res.t_err * res.segment_lengths / actual, 0.01, rtol=1e-6)


def test_constant_yaw_drift_rotation_error() -> None:
    # Same positions, heading drifting by delta per frame. Over a segment f -> l = f + k the
    # error rotation is a yaw by k * delta, so r_err = k * delta / L; the estimate sees the
    # ground-truth displacement d (along z, normal to the yaw axis) in a frame turned by
    # f * delta, so |t_error| = |(I - R_f^T) d| = 2 sin(f * delta / 2) |d|.
    n, delta = 1001, 1e-4
    gt = straight_line(n)
    est = gt.copy()
    est[:, :3, :3] = rot_y(delta * np.arange(n))
    res = kitti_rte(gt, est, precision="float64")
    k = res.last_frames - res.first_frames  # = L + 1
    np.testing.assert_allclose(res.r_err, k * delta / res.segment_lengths, rtol=1e-6)
    counts = expected_counts_unit_line(n, 10)
    expected_rad_per_m = sum(c * (length + 1) * delta / length for length, c in counts.items())
    expected_rad_per_m /= sum(counts.values())
    np.testing.assert_allclose(res.r_err_deg_per_100m, expected_rad_per_m * DEG_PER_100M, rtol=1e-6)
    d = path_lengths(gt)
    expected_t = (
        2.0
        * np.sin(0.5 * delta * res.first_frames)
        * (d[res.last_frames] - d[res.first_frames])
        / res.segment_lengths
    )
    np.testing.assert_allclose(res.t_err, expected_t, rtol=1e-9, atol=1e-15)


def test_to_dict_is_json_ready() -> None:
    gt = straight_line(1001)
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    d = kitti_rte(gt, est).to_dict()
    assert set(d) == {"t_err_percent", "r_err_deg_per_100m", "num_segments", "per_length"}
    assert set(d["per_length"]) == {str(x) for x in DEFAULT_LENGTHS}
    assert set(d["per_length"]["100"]) == {"t_err_percent", "r_err_deg_per_100m", "num_segments"}
    assert json.loads(json.dumps(d)) == d


def test_lengths_without_segments_are_left_out() -> None:
    res = kitti_rte(straight_line(351), straight_line(351))
    assert sorted(res.per_length) == [100, 200, 300]


# --------------------------------------------------------------------------------------------
# agreement with evo's RPE


def _curvy(n: int, spacing: float, seed: int) -> np.ndarray:
    """Planar (x-z) path with constant spacing and a slowly varying heading."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0.0, 0.02, n))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rot_y(heading)
    step = spacing * np.stack([np.sin(heading), np.zeros(n), np.cos(heading)], axis=1)
    poses[1:, :3, 3] = np.cumsum(step[:-1], axis=0)
    return poses


def _noisy(gt: np.ndarray, seed: int) -> np.ndarray:
    """Estimate from the ground-truth increments with small per-step SE(3) noise."""
    rng = np.random.default_rng(seed)
    rel = np.linalg.inv(gt[:-1]) @ gt[1:]
    noise = np.tile(np.eye(4), (rel.shape[0], 1, 1))
    noise[:, :3, :3] = rot_y(rng.normal(0.0, 1e-3, rel.shape[0]))
    noise[:, :3, 3] = rng.normal(0.0, 0.01, (rel.shape[0], 3))
    out = [gt[0]]
    for r in rel @ noise:
        out.append(out[-1] @ r)
    return np.stack(out)


@pytest.mark.parametrize("all_pairs", [True, False])
def test_matches_evo_rpe_with_frame_delta(all_pairs: bool) -> None:
    """evo's RPE equals ours where the segment selections coincide.

    With a constant spacing of 0.7 m a 100 m segment always spans 143 frames (0.7 * 143 =
    100.1 m is the first distance beyond 100 m, far from any rounding tie). evo with
    delta = 143 frames then pairs (i, i + 143): all i for ``all_pairs`` (our step = 1), or
    i = 0, 143, 286, ... otherwise (our step = 143). evo's error pose is inv(Q_rel) P_rel, the
    inverse of the devkit's, which has the same translation norm and rotation angle; the devkit
    then divides by the nominal 100 m.
    """
    from evo.core import metrics
    from evo.core.trajectory import PosePath3D

    length, frames = 100, 143
    gt = _curvy(1200, 0.7, seed=1)
    est = _noisy(gt, seed=2)
    ours = kitti_rte(
        gt, est, step=1 if all_pairs else frames, lengths=(length,), precision="float64"
    )
    np.testing.assert_array_equal(ours.last_frames - ours.first_frames, frames)

    data = (PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est)))
    rpe_t = metrics.RPE(
        metrics.PoseRelation.translation_part,
        delta=frames,
        delta_unit=metrics.Unit.frames,
        all_pairs=all_pairs,
    )
    rpe_t.process_data(data)
    rpe_r = metrics.RPE(
        metrics.PoseRelation.rotation_angle_rad,
        delta=frames,
        delta_unit=metrics.Unit.frames,
        all_pairs=all_pairs,
    )
    rpe_r.process_data(data)

    assert rpe_t.error.shape == ours.t_err.shape
    np.testing.assert_allclose(ours.t_err, rpe_t.error / length, rtol=1e-9, atol=1e-14)
    # evo takes the angle from a rotation log; the devkit from arccos of the trace, which is
    # ill-conditioned near 0, hence an absolute tolerance.
    np.testing.assert_allclose(ours.r_err, rpe_r.error / length, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(
        ours.t_err_percent,
        rpe_t.get_statistic(metrics.StatisticsType.mean) / length * 100,
        rtol=1e-9,
    )


# --------------------------------------------------------------------------------------------
# precision: the official devkit's float arithmetic vs float64

# The official evaluate_odometry.cpp (C float errors, double matrices), trimmed to one pair and
# run on the pair below written with %.9e; float64: the same code with float -> double.
DEVKIT_FLOAT = (0.01072780415, 6.321263936e-05)  # (t_err m/m, r_err rad/m), 449 segments
DEVKIT_DOUBLE = (0.01072857893, 6.324263376e-05)


def test_precision_modes_match_devkit_builds(tmp_path: Path) -> None:
    gt = _curvy(1200, 0.7, seed=1)
    for name, poses in (("gt", gt), ("est", _noisy(gt, seed=2))):
        np.savetxt(tmp_path / f"{name}.txt", poses[:, :3, :].reshape(-1, 12), fmt="%.9e")
    gt, est = load_kitti(tmp_path / "gt.txt"), load_kitti(tmp_path / "est.txt")
    res = {p: kitti_rte(gt, est, precision=p) for p in ("devkit", "float64")}
    for prec, official in (("devkit", DEVKIT_FLOAT), ("float64", DEVKIT_DOUBLE)):
        assert res[prec].num_segments == 449
        ours = (res[prec].t_err_percent / 100.0, res[prec].r_err_deg_per_100m / DEG_PER_100M)
        np.testing.assert_allclose(ours, official, rtol=1e-7)
    # The replay is active: float arccos of the trace moves r_err measurably, but not far.
    r_dev, r_64 = (res[p].r_err_deg_per_100m for p in ("devkit", "float64"))
    assert 1e-5 < abs(r_dev / r_64 - 1.0) < 1e-3
    assert np.all(res["devkit"].r_err.astype(np.float32) == res["devkit"].r_err)
    assert kitti_rte(gt, est).r_err_deg_per_100m == r_dev  # devkit is the default
    out = evaluate(gt, est, precision="float64")
    assert out["r_err_deg_per_100m"] == r_64


# --------------------------------------------------------------------------------------------
# ATE


def test_ate_zero_for_rigidly_moved_estimate() -> None:
    gt = _curvy(500, 1.0, seed=3)
    gt[:, 1, 3] = np.sin(np.arange(500) / 40.0)  # some height so the points are not planar
    T = np.eye(4)
    T[:3, :3] = rot_y(np.array(0.7))[...] @ np.array(
        [[1.0, 0.0, 0.0], [0.0, math.cos(0.2), -math.sin(0.2)], [0.0, math.sin(0.2), math.cos(0.2)]]
    )
    T[:3, 3] = [12.0, -3.0, 40.0]
    est = T @ gt
    aligned = ate(gt, est)
    assert aligned.rmse < 1e-9 and aligned.max < 1e-9
    np.testing.assert_allclose(aligned.rotation @ T[:3, :3], np.eye(3), atol=1e-12)
    assert ate(gt, est, align=False).rmse > 10.0


def test_ate_known_offset_without_alignment() -> None:
    gt = _curvy(300, 1.0, seed=4)
    est = gt.copy()
    est[:, :3, 3] += [3.0, 0.0, 4.0]
    res = ate(gt, est, align=False)
    for value in (res.rmse, res.mean, res.median, res.max):
        assert value == pytest.approx(5.0, rel=1e-12)
    assert res.std == pytest.approx(0.0, abs=1e-12)
    assert ate(gt, est, align=True).rmse < 1e-9
    d = res.to_dict()
    assert set(d) >= {"rmse", "mean", "median", "std", "max"}
    assert json.loads(json.dumps(d)) == d


def test_ate_alignment_is_a_rotation_not_a_reflection() -> None:
    gt = _curvy(200, 1.0, seed=5)
    gt[:, 1, 3] = np.linspace(0.0, 30.0, 200) ** 1.5 / 10.0  # leave the plane: a 3D point set
    est = gt.copy()
    est[:, 0, 3] *= -1.0  # mirrored estimate: the best proper rotation cannot undo it
    res = ate(gt, est)
    assert np.linalg.det(res.rotation) == pytest.approx(1.0)
    assert res.rmse > 0.1


# --------------------------------------------------------------------------------------------
# evaluate and plot


def test_evaluate_combines_everything() -> None:
    gt = straight_line(1001)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    out = evaluate(gt, est)
    assert {"t_err_percent", "r_err_deg_per_100m", "num_segments", "per_length", "ate"} <= set(out)
    assert out["num_poses"] == 1001
    assert out["path_length_m"] == pytest.approx(1000.0)
    assert out["t_err_percent"] == kitti_rte(gt, est).t_err_percent
    assert json.loads(json.dumps(out)) == out


def test_frame_rotation_drift_splits_a_bias_from_noise() -> None:
    """A constant extra pitch (about x) of 0.01 deg per frame is a 10 mdeg mean with no
    spread; zero-mean noise about y is spread with a mean near 0."""
    gt = _curvy(401, 0.7, seed=3)
    rel = frame_motions(gt)
    extra = np.tile(np.eye(4), (len(rel), 1, 1))
    extra[:, :3, :3] = Rotation.from_rotvec([np.deg2rad(0.01), 0.0, 0.0]).as_matrix()
    out = [gt[0]]
    for r in rel @ extra:
        out.append(out[-1] @ r)
    drift = frame_rotation_drift(gt, np.stack(out))
    np.testing.assert_allclose(drift["mean_mdeg"], [10.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(drift["std_mdeg"], [0.0, 0.0, 0.0], atol=1e-6)
    assert drift["num_frames"] == 400
    noisy = frame_rotation_drift(gt, _noisy(gt, seed=4))  # 1e-3 rad (57 mdeg) about y
    assert noisy["std_mdeg"][1] == pytest.approx(57.3, rel=0.1)
    assert abs(noisy["mean_mdeg"][1]) < 3 * 57.3 / np.sqrt(400)
    assert evaluate(gt, np.stack(out))["frame_rotation"] == drift
    with pytest.raises(InputError, match="at least 2 poses"):
        frame_rotation_drift(gt[:1], gt[:1], source="est.txt")
    one = evaluate_without_rte(gt[:1], gt[:1], "too short")
    assert one["frame_rotation"] is None and one["ate"]["rmse"] == 0.0


def test_plot_evaluation_writes_png(tmp_path: Path) -> None:
    gt = _curvy(1200, 0.7, seed=6)
    est = _noisy(gt, seed=7)
    target = tmp_path / "nested" / "dir" / "eval.png"
    written = plot_evaluation(gt, est, kitti_rte(gt, est), target, title="test")
    assert written == target
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in target.parent.iterdir()] == ["eval.png"]  # no temp file left
    plot_evaluation(gt, est, None, target)  # overwrite, computing the RTE itself


# --------------------------------------------------------------------------------------------
# input errors


def test_length_mismatch() -> None:
    with pytest.raises(InputError, match="1001 gt poses vs 1000 estimated poses"):
        kitti_rte(straight_line(1001), straight_line(1000))
    with pytest.raises(InputError, match="^est.txt: 10 gt poses vs 9 estimated poses"):
        ate(straight_line(10), straight_line(9), source="est.txt")


def test_nan_and_inf() -> None:
    est = straight_line(1001)
    est[17, 0, 3] = np.nan
    with pytest.raises(InputError, match="NaN or inf.*index 17"):
        kitti_rte(straight_line(1001), est)
    est[17, 0, 3] = np.inf
    with pytest.raises(InputError, match="NaN or inf"):
        evaluate(straight_line(1001), est)


def test_bad_shapes() -> None:
    with pytest.raises(InputError, match=r"shape \(N, 4, 4\)"):
        kitti_rte(straight_line(1001)[:, :3, :], straight_line(1001)[:, :3, :])
    with pytest.raises(InputError, match="empty"):
        ate(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
    bad = straight_line(1001)
    bad[3, 3, :] = 0.0
    with pytest.raises(InputError, match="pose 3 is not homogeneous"):
        kitti_rte(bad, straight_line(1001))


def test_too_short() -> None:
    with pytest.raises(InputError, match=r"path of 51 poses is 50\.000 m long.* 100 m") as info:
        kitti_rte(straight_line(51), straight_line(51), source="seq.txt")
    assert info.value.source == "seq.txt"
    # Exactly 100 m is still too short: a segment must be strictly longer than its length.
    with pytest.raises(InputError, match="not longer than the shortest segment length 100 m"):
        kitti_rte(straight_line(101), straight_line(101))
    assert kitti_rte(straight_line(102), straight_line(102)).num_segments == 1


def test_bad_parameters() -> None:
    with pytest.raises(ValueError, match="step"):
        kitti_rte(straight_line(200), straight_line(200), step=0)
    with pytest.raises(ValueError, match="whole metres"):
        kitti_rte(straight_line(200), straight_line(200), lengths=(50.5,))
    with pytest.raises(ValueError, match="precision"):
        line = straight_line(200)
        kitti_rte(line, line, precision="float32")  # type: ignore[arg-type]
