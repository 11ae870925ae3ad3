"""Vehicle trajectories for the simulator: windows of KITTI ground truth, or procedural paths.

Poses are ``T_world_lidar`` (LiDAR frame -> a fixed world frame whose z axis is up), sampled at
frame times in seconds. KITTI pose files give camera-0 poses; they become LiDAR poses through
``inv(Tr) @ P @ Tr`` (see :mod:`gloam_jax.io`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gloam_jax import geometry as geo
from gloam_jax import io
from gloam_jax.errors import InputError

# Scenery must exist this far (m) before the first and after the last frame, beyond the
# sensor's range, so no scan looks past the end of the world.
PATH_MARGIN_M = 150.0


@dataclass(frozen=True)
class Trajectory:
    """LiDAR poses over a window of frames, plus the surrounding path for scenery.

    times: (M,) s; T_world_lidar: (M, 4, 4); frames [first, first + num_frames) of these M
    samples are the ones to simulate; the rest extend the road beyond the window.
    """

    times: np.ndarray
    T_world_lidar: np.ndarray
    first: int
    num_frames: int
    Tr_cam_velo: np.ndarray
    source: str

    @property
    def frame_times(self) -> np.ndarray:
        return self.times[self.first : self.first + self.num_frames]

    @property
    def frame_poses(self) -> np.ndarray:
        return self.T_world_lidar[self.first : self.first + self.num_frames]

    def poses_at(self, t: np.ndarray) -> np.ndarray:
        """Poses at times t, SE(3)-interpolated (extrapolated past the ends): (K,) -> (K, 4, 4)."""
        return interpolate_poses(self.times, self.T_world_lidar, t)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses (M, 4, 4) sampled at ``times`` (M,), SE(3)-interpolated at ``t`` (K,) between
    neighbouring samples (extrapolated past the ends): (K, 4, 4)."""
    t = np.asarray(t, dtype=np.float64)
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    alpha = (t - times[k]) / (times[k + 1] - times[k])
    T0, T1 = poses[k], poses[k + 1]
    # Interpolate the small relative motion (accurate in float32) and compose in float64.
    xi = np.asarray(geo.se3_log(np.linalg.inv(T0) @ T1), dtype=np.float64)
    step = np.asarray(geo.se3_exp(alpha[:, None] * xi), dtype=np.float64)
    return T0 @ step


def default_Tr_cam_velo() -> np.ndarray:
    """A realistic Velodyne -> camera-0 extrinsic: axis swap, sub-degree misalignment, lever arm."""
    axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    tilt = np.asarray(geo.so3_exp(np.deg2rad([0.41, -0.27, 0.12])), dtype=np.float64)
    Tr = np.eye(4)
    Tr[:3, :3] = tilt @ axes
    Tr[:3, 3] = [-0.008, -0.071, -0.305]
    return Tr


def _kitti_times_path(pose_file: Path) -> Path | None:
    for candidate in (
        pose_file.with_name(f"{pose_file.stem}_times.txt"),
        pose_file.parent.parent / "sequences" / pose_file.stem / "times.txt",
    ):
        if candidate.exists():
            return candidate
    return None


def _kitti_Tr(pose_file: Path, calib: Path | None) -> np.ndarray:
    """Tr for a KITTI pose file: an explicit calib file, else the shared per-day file, else ours."""
    if calib is not None:
        entries = io.read_calib(calib)
        keys = [k for k in entries if k.startswith("Tr")]
        if not keys:
            raise InputError(calib, "no 'Tr' entry (Velodyne -> camera-0 extrinsic)")
        return entries[keys[0]]
    shared = pose_file.with_name("calib_Tr_velo_to_cam0.txt")
    if shared.exists() and re.fullmatch(r"\d+", pose_file.stem):
        seq = int(pose_file.stem)
        entries = io.read_calib(shared)
        for key, value in entries.items():
            m = re.fullmatch(r"Tr_(\d+)_(\d+)", key)
            if m and int(m.group(1)) <= seq <= int(m.group(2)):
                return value
    return default_Tr_cam_velo()


def load_kitti_trajectory(
    pose_file: str | Path, start: int, frames: int, calib: str | Path | None = None
) -> Trajectory:
    """A window ``[start, start + frames)`` of a KITTI camera-0 pose file, as LiDAR poses.

    Times come from ``NN_times.txt`` beside the file (or the sequence's ``times.txt``), else a
    nominal 10 Hz. Extra poses before and after the window are kept so the scene extends past it.
    """
    pose_file = Path(pose_file)
    P_cam = io.read_kitti_poses(pose_file)
    if start < 0 or frames < 2 or start + frames > len(P_cam):
        raise InputError(
            pose_file,
            f"window start={start} frames={frames} does not fit in its {len(P_cam)} poses",
        )
    times_path = _kitti_times_path(pose_file)
    if times_path is not None:
        times = io.read_times(times_path)
        if len(times) != len(P_cam):
            raise InputError(times_path, f"{len(times)} times vs {len(P_cam)} poses in {pose_file}")
    else:
        times = 0.1 * np.arange(len(P_cam))
    Tr = _kitti_Tr(pose_file, None if calib is None else Path(calib))
    T_world_lidar = io.cam_to_lidar_poses(P_cam, Tr)
    dist = np.concatenate(
        [[0.0], np.cumsum(np.linalg.norm(np.diff(T_world_lidar[:, :3, 3], axis=0), axis=1))]
    )
    lo = int(np.searchsorted(dist, dist[start] - PATH_MARGIN_M, side="left"))
    hi = int(np.searchsorted(dist, dist[start + frames - 1] + PATH_MARGIN_M, side="right"))
    lo, hi = max(lo - 1, 0), min(hi + 1, len(P_cam))
    times, T_world_lidar = _extend_straight(times[lo:hi], T_world_lidar[lo:hi])
    extra = len(times) - (hi - lo)
    return Trajectory(
        times=times,
        T_world_lidar=T_world_lidar,
        first=start - lo + extra // 2,
        num_frames=frames,
        Tr_cam_velo=Tr,
        source=f"{pose_file} [{start}:{start + frames}]",
    )


def _extend_straight(times: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pad both ends with straight constant-speed motion so the path spans PATH_MARGIN_M more.

    Pads the same number of samples at each end (callers recover the window offset from that).
    """
    dt = float(np.median(np.diff(times)))
    n = int(np.ceil(PATH_MARGIN_M / 5.0 / dt))  # at >= 5 m/s; slower or stopped vehicles
    heads, tails = [], []
    for end, sign in ((0, -1), (-1, 1)):
        R = T[end, :3, :3]
        forward = R[:, 0] * np.array([1.0, 1.0, 0.0])
        forward /= max(np.linalg.norm(forward), 1e-9)
        steps = sign * np.arange(1, n + 1)[:, None] * 5.0 * dt * forward
        pads = np.repeat(T[end][None], n, axis=0)
        pads[:, :3, 3] += steps
        pad_times = times[end] + sign * dt * np.arange(1, n + 1)
        if sign < 0:
            heads = (pad_times[::-1], pads[::-1])
        else:
            tails = (pad_times, pads)
    return (
        np.concatenate([heads[0], times, tails[0]]),
        np.concatenate([heads[1], T, tails[1]]),
    )


def procedural_trajectory(frames: int, seed: int, *, speed: float = 9.0) -> Trajectory:
    """A smooth 10 Hz drive: gentle random turns and slopes, speed varying about ``speed`` m/s."""
    rng = np.random.default_rng(seed)
    dt = 0.1
    pad = int(np.ceil(PATH_MARGIN_M / (0.5 * speed) / dt))
    n = frames + 2 * pad
    t = dt * np.arange(n)

    def smooth_noise(scale: float, corr_s: float) -> np.ndarray:
        k = max(int(corr_s / dt), 1)
        raw = rng.normal(size=n + 2 * k)
        kernel = np.hanning(2 * k + 1)
        out = np.convolve(raw, kernel / kernel.sum(), mode="same")[k:-k]
        return scale * out / max(np.std(out), 1e-9)

    v = np.clip(speed + smooth_noise(0.25 * speed, 6.0), 0.3 * speed, 1.6 * speed)
    yaw_rate = smooth_noise(0.08, 5.0)
    # A few deliberate turns, as at street corners.
    for centre in rng.uniform(0.2, 0.8, size=2) * t[-1]:
        yaw_rate += rng.choice([-1, 1]) * 0.35 * np.exp(-0.5 * ((t - centre) / 1.2) ** 2)
    yaw = np.cumsum(yaw_rate) * dt
    pitch = smooth_noise(0.015, 8.0)
    heading = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], 1)
    pos = np.cumsum(heading * (v * dt)[:, None], axis=0)
    pos -= pos[pad]
    rotations = np.asarray(
        geo.so3_exp(np.stack([np.zeros(n), np.zeros(n), yaw], 1)), dtype=np.float64
    ) @ np.asarray(geo.so3_exp(np.stack([np.zeros(n), -pitch, np.zeros(n)], 1)), dtype=np.float64)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = rotations
    T[:, :3, 3] = pos
    return Trajectory(
        times=t - t[pad],
        T_world_lidar=T,
        first=pad,
        num_frames=frames,
        Tr_cam_velo=default_Tr_cam_velo(),
        source=f"procedural(seed={seed})",
    )


def with_speed(traj: Trajectory, scale: float, frames: int) -> Trajectory:
    """The same path driven ``scale`` times as fast, resampled at 10 Hz: ``frames`` frames from
    the window's first pose (the trajectory must reach ``(frames - 1) * 0.1 * scale`` s past it,
    in the recording's time)."""
    t = (traj.times - traj.times[traj.first]) / scale  # the window starts at 0
    dt = 0.1
    k0, k1 = int(np.ceil(t[0] / dt)), int(np.floor(t[-1] / dt))
    grid = dt * np.arange(k0, k1 + 1)
    if -k0 + frames > len(grid):
        raise InputError(traj.source, f"too short for {frames} frames at {scale:g}x speed")
    return Trajectory(
        times=grid + traj.times[traj.first],
        T_world_lidar=interpolate_poses(t, traj.T_world_lidar, grid),
        first=-k0,
        num_frames=frames,
        Tr_cam_velo=traj.Tr_cam_velo,
        source=f"{traj.source} at {scale:g}x speed",
    )


def drive_stats(traj: Trajectory) -> dict:
    """How the window's frames drive: path length (m), mean speed (m/s), total heading change
    (degrees, turns either way counted positive)."""
    T = traj.frame_poses
    length = float(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum())
    yaw = np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    duration = float(traj.frame_times[-1] - traj.frame_times[0])
    return {
        "length_m": round(length, 2),
        "mean_speed_mps": round(length / max(duration, 1e-9), 2),
        "turn_deg": round(float(np.degrees(np.abs(np.diff(yaw)).sum())), 1),
    }
