"""Reading and writing poses, calibration, scans and labels (NumPy, no JAX).

Each module states its own conventions: :mod:`~gloam_jax.io.files` (errors, atomic writes),
:mod:`~gloam_jax.io.poses` (pose frames, KITTI and TUM pose files), :mod:`~gloam_jax.io.scans`
(point clouds) and :mod:`~gloam_jax.io.kitti` (calibration, timestamps, labels, the odometry
layout). Everything a caller needs is importable from here.
"""

from gloam_jax.io.files import write_atomic, write_figure, write_npz
from gloam_jax.io.kitti import (
    KittiSequence,
    read_calib,
    read_labels,
    read_times,
    write_calib,
    write_labels,
)
from gloam_jax.io.poses import (
    as_poses,
    cam_to_lidar_poses,
    frame_motions,
    kitti_pose_text,
    lidar_to_cam_poses,
    read_kitti_poses,
    read_tum_poses,
    tum_pose_text,
    write_kitti_poses,
    write_tum_poses,
)
from gloam_jax.io.scans import read_scan, write_scan_bin

__all__ = [
    "KittiSequence",
    "as_poses",
    "cam_to_lidar_poses",
    "frame_motions",
    "kitti_pose_text",
    "lidar_to_cam_poses",
    "read_calib",
    "read_kitti_poses",
    "read_labels",
    "read_scan",
    "read_times",
    "read_tum_poses",
    "tum_pose_text",
    "write_atomic",
    "write_calib",
    "write_figure",
    "write_kitti_poses",
    "write_labels",
    "write_npz",
    "write_scan_bin",
    "write_tum_poses",
]
