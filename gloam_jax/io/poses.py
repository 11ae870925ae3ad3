"""Trajectories: the one pose validator, KITTI and TUM pose files, camera <-> LiDAR poses.

Conventions (shared with :mod:`gloam_jax.geometry`):

* A pose is a float64 ``(4, 4)`` homogeneous matrix ``T_world_frame`` (maps frame points into
  the world); a trajectory is ``(N, 4, 4)``.
* KITTI pose files store the top ``3x4`` row-major, 12 numbers a line, in the camera-0 frame:
  ``P_i = T_cam0_cami``. The calibration ``Tr`` (``Tr_cam_velo``) maps Velodyne points into
  camera 0, so LiDAR poses are ``inv(Tr) @ P_i @ Tr``.
* TUM lines are ``t x y z qx qy qz qw`` (scalar-last quaternion), ``#`` starts a comment.
"""

from __future__ import annotations

import io
from typing import IO

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from gloam_jax.errors import InputError
from gloam_jax.io.files import PathLike, parse_rows, read_text, write_atomic

__all__ = [
    "as_poses",
    "cam_to_lidar_poses",
    "kitti_pose_text",
    "lidar_to_cam_poses",
    "read_kitti_poses",
    "read_tum_poses",
    "to_homogeneous",
    "tum_pose_text",
    "write_kitti_poses",
    "write_tum_poses",
]

# 17 significant digits round-trip float64 exactly; fewer (%.9e) lose ~1e-7 m on km-scale
# KITTI translations, which would show up in trajectory-error comparisons.
_FLOAT_FMT = "%.16e"

# Inputs are usually read from text with ~9 significant digits, so the bottom row of a pose is
# only checked loosely: it exists to catch a (3,4)->(4,4) padding bug, not rounding.
_BOTTOM_ROW_ATOL = 1e-6
# KITTI pose files hold rotations to about 1e-9; anything off by more than this is no rotation.
_ROTATION_ATOL = 1e-3


def to_homogeneous(top: np.ndarray) -> np.ndarray:
    """(..., 3, 4) -> (..., 4, 4) float64 with bottom row ``[0, 0, 0, 1]``."""
    out = np.zeros(top.shape[:-2] + (4, 4), dtype=np.float64)
    out[..., :3, :] = top
    out[..., 3, 3] = 1.0
    return out


def as_poses(
    poses: ArrayLike,
    what: str = "",
    source: PathLike | None = None,
    *,
    top_rows_ok: bool = False,
) -> NDArray[np.float64]:
    """Check a trajectory and return it as a float64 ``(N, 4, 4)`` array.

    The trajectory must be numeric, non-empty and finite, every bottom row ``[0, 0, 0, 1]``
    (to 1e-6, as text files round) and every rotation block a rotation (orthonormal to 1e-3,
    determinant +1): a scaled or zeroed block is no pose, and would be scored as one.
    ``top_rows_ok`` also accepts KITTI's ``(N, 3, 4)`` top rows and completes them. ``what``
    names the trajectory in messages (``"ground-truth"``); failures raise
    :class:`InputError` with ``source`` as the file name.
    """
    named = f"{what} " if what else ""
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(source, f"{named}poses are not a numeric array ({exc})") from None
    if top_rows_ok and arr.ndim == 3 and arr.shape[1:] == (3, 4):
        arr = to_homogeneous(arr)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        shapes = "(N, 4, 4) or (N, 3, 4)" if top_rows_ok else "(N, 4, 4)"
        hint = "" if top_rows_ok else " (pad KITTI (N, 3, 4) rows with [0, 0, 0, 1])"
        raise InputError(source, f"{named}poses must have shape {shapes}, got {arr.shape}{hint}")
    if arr.shape[0] == 0:
        raise InputError(source, f"{named}trajectory is empty")
    finite = np.isfinite(arr).all(axis=(1, 2))
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InputError(
            source,
            f"{named}poses contain NaN or inf at {bad.size} pose(s), first at index {bad[0]}",
        )
    bottom_ok = np.all(np.abs(arr[:, 3, :] - (0.0, 0.0, 0.0, 1.0)) <= _BOTTOM_ROW_ATOL, axis=1)
    if not bottom_ok.all():
        first = int(np.flatnonzero(~bottom_ok)[0])
        raise InputError(
            source,
            f"{named}pose {first} is not homogeneous: last row is {arr[first, 3].tolist()}, "
            "expected [0, 0, 0, 1]",
        )
    R = arr[:, :3, :3]
    off = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    rigid = (off <= _ROTATION_ATOL) & (np.linalg.det(R) > 0)
    if not rigid.all():
        first = int(np.flatnonzero(~rigid)[0])
        raise InputError(
            source,
            f"{named}pose {first} has a rotation block that is not a rotation "
            f"(R^T R differs from I by {off[first]:.3g}, det {np.linalg.det(R[first]):.3g})",
        )
    return arr


def _format_rows(rows: np.ndarray, fmt: str) -> bytes:
    buf = io.StringIO()
    np.savetxt(buf, rows, fmt=fmt, delimiter=" ")
    return buf.getvalue().encode("ascii")


def read_kitti_poses(path_or_file: PathLike | IO[str]) -> np.ndarray:
    """KITTI pose file (12 numbers a line, top 3x4 row-major) -> ``(N, 4, 4)`` float64."""
    text, name = read_text(path_or_file)
    rows = parse_rows(text, name, 12, "KITTI pose")
    return to_homogeneous(rows.reshape(-1, 3, 4))


def kitti_pose_text(poses: np.ndarray, source: PathLike | None = None) -> bytes:
    """The lines of a KITTI pose file for ``(N, 4, 4)`` poses (``source`` names it in errors)."""
    top = as_poses(poses, source=source, top_rows_ok=True)[:, :3, :]
    return _format_rows(top.reshape(-1, 12), _FLOAT_FMT)


def write_kitti_poses(path: PathLike, poses: np.ndarray) -> None:
    """Write ``(N, 4, 4)`` poses as a KITTI pose file (readable by ``evo_traj kitti``)."""
    write_atomic(path, kitti_pose_text(poses, path))


def read_tum_poses(path_or_file: PathLike | IO[str]) -> tuple[np.ndarray, np.ndarray]:
    """TUM file (``t x y z qx qy qz qw``) -> ``(times (N,), poses (N, 4, 4))`` float64.

    Quaternions are normalised, since files often hold them rounded to a few digits.
    """
    text, name = read_text(path_or_file)
    rows = parse_rows(text, name, 8, "TUM t x y z qx qy qz qw")
    quats = rows[:, 4:]
    norms = np.linalg.norm(quats, axis=1)
    bad = np.flatnonzero(norms < 1e-9)
    if bad.size:
        raise InputError(name, f"pose {bad[0] + 1} has a zero quaternion")
    poses = np.zeros((len(rows), 4, 4), dtype=np.float64)
    poses[:, :3, :3] = Rotation.from_quat(quats / norms[:, None]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    poses[:, 3, 3] = 1.0
    return rows[:, 0].copy(), poses


def tum_pose_text(times: np.ndarray, poses: np.ndarray, source: PathLike | None = None) -> bytes:
    """The lines of a TUM trajectory file for ``times (N,)`` and ``poses (N, 4, 4)``."""
    top = as_poses(poses, source=source, top_rows_ok=True)[:, :3, :]
    times = np.asarray(times, dtype=np.float64)
    if times.shape != (len(top),):
        raise InputError(source, f"times must have shape ({len(top)},), got {times.shape}")
    if not np.all(np.isfinite(times)):
        raise InputError(source, "times contain NaN or infinite values")
    quats = Rotation.from_matrix(top[:, :, :3]).as_quat(canonical=True)
    rows = np.column_stack([times, top[:, :, 3], quats])
    return _format_rows(rows, " ".join([_FLOAT_FMT] * 8))


def write_tum_poses(path: PathLike, times: np.ndarray, poses: np.ndarray) -> None:
    """Write ``times (N,)`` and ``poses (N, 4, 4)`` as a TUM trajectory file."""
    write_atomic(path, tum_pose_text(times, poses, path))


def frame_motions(poses: ArrayLike) -> np.ndarray:
    """The motion from each pose to the next, ``inv(T_k) @ T_k+1``, of poses ``(N, 4, 4)``:
    ``(N - 1, 4, 4)`` float64, in the earlier pose's frame."""
    T = np.asarray(poses, dtype=np.float64)
    return np.linalg.inv(T[:-1]) @ T[1:]


def cam_to_lidar_poses(P_cam: np.ndarray, Tr_cam_velo: np.ndarray) -> np.ndarray:
    """Camera-0 poses ``(..., 4, 4)`` -> LiDAR poses ``inv(Tr) @ P @ Tr`` (float64)."""
    P = np.asarray(P_cam, dtype=np.float64)
    Tr = np.asarray(Tr_cam_velo, dtype=np.float64)
    return np.linalg.inv(Tr) @ P @ Tr


def lidar_to_cam_poses(T_lidar, Tr_cam_velo: np.ndarray):
    """LiDAR poses ``(..., 4, 4)`` -> camera-0 poses ``Tr @ T @ inv(Tr)``: float64 NumPy, or,
    for a JAX array (traced too), a JAX array in its dtype, through its own array namespace."""
    Tr = np.asarray(Tr_cam_velo, dtype=np.float64)
    if isinstance(T_lidar, np.ndarray) or not hasattr(T_lidar, "__array_namespace__"):
        return Tr @ np.asarray(T_lidar, dtype=np.float64) @ np.linalg.inv(Tr)
    xp = T_lidar.__array_namespace__()
    Tr, Tr_inv = (xp.asarray(A, dtype=T_lidar.dtype) for A in (Tr, np.linalg.inv(Tr)))
    return Tr @ T_lidar @ Tr_inv
