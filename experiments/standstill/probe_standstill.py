"""A drive that stops among traffic (the simulator's moving road users), and the drift the stop
adds to the odometry: cruise, brake, stand still, pull away, cruise on.

    python experiments/standstill/probe_standstill.py --stop 60 --out RESULTS.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from gloam_jax import geometry as geo
from gloam_jax import io
from gloam_jax.datasets import open_dataset
from gloam_jax.odometry import OdometryConfig
from gloam_jax.pipeline import run_dataset, select_frames
from gloam_jax.simulate import ErrorSwitches, procedural_trajectory, simulate
from gloam_jax.simulate.trajectory import default_Tr_cam_velo, interpolate_poses

DT = 0.1  # s between scans


def stop_and_go(before: float, stop: float, after: float, *, speed: float = 8.0,
                decel: float = 2.0, seed: int = 0) -> tuple[np.ndarray, int, int]:  # fmt: skip
    """LiDAR poses (F, 4, 4) at 10 Hz along a procedural street: ``before`` s cruising at
    ``speed`` m/s, braking at ``decel`` m/s^2, ``stop`` s standing, pulling away at ``decel``,
    ``after`` s cruising; with 150 m of cruising before and after for the scenery. Also the
    first and last frame (of the poses) standing still."""
    ramp = speed / decel
    margin = 150.0 / speed
    t = np.arange(-margin, before + 2 * ramp + stop + after + margin + DT / 2, DT)
    t = np.round(t / DT) * DT

    def distance(tau: np.ndarray) -> np.ndarray:
        """Arc length (m) driven at time tau (s from the window's start)."""
        braking = np.clip(tau - before, 0, ramp)
        pulling = np.clip(tau - before - ramp - stop, 0, ramp)
        cruising = np.clip(tau, None, before) + np.clip(tau - before - 2 * ramp - stop, 0, None)
        return (speed * cruising + speed * braking - 0.5 * decel * braking**2
                + 0.5 * decel * pulling**2)  # fmt: skip

    s = distance(t)
    path = procedural_trajectory(int((s[-1] - s[0]) / (0.3 * speed * DT)) + 10, seed,
                                 speed=speed)  # fmt: skip
    T = path.T_world_lidar
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1))])
    arc -= arc[path.first] + s[0] - 1.0  # the drive starts a metre into the path's window
    poses = interpolate_poses(arc, T, s)
    still = np.flatnonzero(np.abs(np.gradient(s)) < 1e-9)
    return poses, int(still[0]), int(still[-1])


def stop_drift(est: np.ndarray, gt: np.ndarray, first: int, last: int) -> tuple[float, float]:
    """The error (m, deg) of the estimated motion from frame ``first`` to ``last`` (the stop):
    what standing still added to the trajectory."""
    relative = np.linalg.inv(np.linalg.inv(gt[first]) @ gt[last]) @ (
        np.linalg.inv(est[first]) @ est[last]
    )
    angle = np.rad2deg(np.linalg.norm(np.asarray(geo.so3_log(relative[:3, :3]))))
    return float(np.linalg.norm(relative[:3, 3])), float(angle)


def keyframes(est: np.ndarray, config: OdometryConfig) -> list[int]:
    """The frames that the odometry's keyframe rule (distance or angle from the last keyframe)
    takes into the map, given the estimated poses (F, 4, 4)."""
    chosen = [0]
    for k in range(1, len(est)):
        delta = np.linalg.inv(est[chosen[-1]]) @ est[k]
        angle = np.rad2deg(np.linalg.norm(np.asarray(geo.so3_log(delta[:3, :3]))))
        if np.linalg.norm(delta[:3, 3]) > config.keyframe_distance or (
            angle > config.keyframe_angle_deg
        ):
            chosen.append(k)
    return chosen


def simulate_stop(out: Path, stop: float, *, beams: int, columns: int, seed: int = 0,
                  before: float = 4.0, after: float = 4.0, decel: float = 2.0,
                  movers: bool = True) -> tuple[Path, int, int]:  # fmt: skip
    """A stop-and-go drive simulated into ``out`` (KITTI layout, sequence 00, urban style, its
    moving road users on unless ``movers`` is False); returns the root and the first and last
    standing frame."""
    poses, first_still, last_still = stop_and_go(before, stop, after, seed=seed, decel=decel)
    margin = int(round(150.0 / 8.0 / DT))
    pose_file = out / "stop_poses.txt"
    io.write_kitti_poses(pose_file, io.lidar_to_cam_poses(poses, default_Tr_cam_velo()))
    frames = len(poses) - 2 * margin
    simulate(out / "sim", trajectory=pose_file, start=margin, frames=frames, style="urban",
             seed=seed, num_beams=beams, num_columns=columns,
             switches=ErrorSwitches(moving_objects=movers))  # fmt: skip
    return out / "sim", first_still - margin, last_still - margin


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stop", type=float, default=60.0, help="s standing still")
    parser.add_argument("--beams", type=int, default=32)
    parser.add_argument("--columns", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-movers", action="store_true", help="no moving road users")
    parser.add_argument("--out", type=Path, required=True, help="results (JSON)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root, first, last = simulate_stop(Path(tmp), args.stop, beams=args.beams,
                                          columns=args.columns, seed=args.seed,
                                          movers=not args.no_movers)  # fmt: skip
        dataset = open_dataset(root, "00")
        result = run_dataset(dataset, OdometryConfig(), Path(tmp) / "run",
                             select_frames(len(dataset)))  # fmt: skip
        est = io.read_kitti_poses(Path(tmp) / "run" / "00_poses_lidar_kitti.txt")
        gt = dataset.sequence.gt_poses_lidar
        metres, degrees = stop_drift(est, gt, first, last)
        wander = max(stop_drift(est, gt, first, k)[0] for k in range(first, last + 1))
        labels = [dataset.labels(k) for k in range(first, last + 1)]
        moving = [int(np.isin(k, [252, 253, 254]).sum()) for k in labels]
        in_stop = [k for k in keyframes(est, OdometryConfig()) if first < k <= last]
        frames = json.loads((Path(tmp) / "run" / "frames.json").read_text())
    report = {"args": {k: str(v) for k, v in vars(args).items()}, "stop_frames": [first, last],
              "stop_drift_m": metres, "stop_drift_deg": degrees, "max_wander_in_stop_m": wander,
              "ate": result["ate"], "t_err_percent": result.get("t_err_percent"),
              "keyframes_in_stop": in_stop, "moving_points_per_scan_in_stop": {
                  "mean": float(np.mean(moving)), "max": max(moving),
                  "share_of_scans_with_movers": float(np.mean(np.array(moving) > 0))},
              "degenerate_frames": result["degenerate_frames"],
              "residual_during_stop": [f["residual"] for f in frames[first:last + 1]][::50],
              "config": asdict(OdometryConfig())}  # fmt: skip
    io.write_atomic(args.out, json.dumps(report, indent=2))
    print(json.dumps({k: report[k] for k in ("stop_frames", "stop_drift_m", "stop_drift_deg",
                                            "max_wander_in_stop_m")}))  # fmt: skip


if __name__ == "__main__":
    main()
