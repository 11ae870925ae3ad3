"""Trajectory metrics in numpy: KITTI relative error, absolute error, plots.

Poses are ``(N, 4, 4)`` homogeneous matrices ``T_world_frame`` (see :mod:`gloam_jax.geometry`),
ground truth and estimate indexed by the same frames.

:func:`kitti_rte` reproduces the KITTI odometry devkit (``evaluate_odometry.cpp``): segments of
100..800 m measured along the ground truth, starting every 10th frame, and the sequence score is
the mean over all segments of all lengths. By default it replays the devkit's C ``float``
arithmetic, so it reports the official numbers; ``precision="float64"`` gives the exact values.
Its segments come from :func:`segment_plan`, which the training loss
(:mod:`gloam_jax.training.losses`) uses as well, so loss and benchmark score the same segments.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from gloam_jax.errors import InputError
from gloam_jax.io import as_poses, frame_motions, write_figure

__all__ = [
    "DEFAULT_LENGTHS",
    "TRAINING_FRACTIONS",
    "AteResult",
    "RteResult",
    "SegmentPlan",
    "ate",
    "evaluate",
    "evaluate_without_rte",
    "frame_rotation_drift",
    "kitti_rte",
    "path_lengths",
    "plot_evaluation",
    "scaled_lengths",
    "segment_plan",
]

DEFAULT_LENGTHS: tuple[int, ...] = (100, 200, 300, 400, 500, 600, 700, 800)
"""Segment lengths of the KITTI odometry benchmark, metres."""

TRAINING_FRACTIONS: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
"""Default segment lengths of :func:`scaled_lengths`, as fractions of the path length: the
KITTI lengths 100..800 m as if the training window were 1 km long."""

_RAD_PER_M_TO_DEG_PER_100M = 180.0 / math.pi * 100.0

Source = str | os.PathLike[str] | None
Precision = Literal["devkit", "float64"]


def _as_pair(
    gt_poses: ArrayLike, est_poses: ArrayLike, source: Source
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    gt = as_poses(gt_poses, "ground-truth", source)
    est = as_poses(est_poses, "estimated", source)
    if gt.shape[0] != est.shape[0]:
        raise InputError(source, f"{gt.shape[0]} gt poses vs {est.shape[0]} estimated poses")
    return gt, est


def _float_type(precision: Precision) -> type[np.floating[Any]]:
    """The devkit's ``float`` (float32) or float64; anything else is a ValueError."""
    if precision == "devkit":
        return np.float32
    if precision == "float64":
        return np.float64
    raise ValueError(f"precision must be 'devkit' or 'float64', got {precision!r}")


def _norm3(v: NDArray[np.floating[Any]]) -> NDArray[np.floating[Any]]:
    """Row norms of (M, 3) as the devkit writes them, ``sqrt(x*x + y*y + z*z)``, in v's dtype."""
    return np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])


def _mean(values: NDArray[np.floating[Any]]) -> float:
    """Mean with the devkit's running sum in values' dtype (cumsum adds in order, not pairwise)."""
    return float(np.cumsum(values, dtype=values.dtype)[-1] / values.dtype.type(values.size))


def _distances(
    poses: NDArray[np.float64], dtype: type[np.floating[Any]] = np.float64
) -> NDArray[np.floating[Any]]:
    """Cumulative ground-truth distance (N,) in ``dtype``, summed step by step as the devkit."""
    steps = _norm3(np.diff(poses[:, :3, 3], axis=0).astype(dtype))
    return np.concatenate((np.zeros(1, dtype), np.cumsum(steps, dtype=dtype)))


def path_lengths(poses: ArrayLike, *, source: Source = None) -> NDArray[np.float64]:
    """Cumulative distance travelled along the positions: (N, 4, 4) -> (N,), starting at 0."""
    return _distances(as_poses(poses, "input", source))


@dataclass(frozen=True, eq=False)
class SegmentPlan:
    """The devkit's segments of one ground-truth trajectory, in its order (first frame outer,
    length inner); built by :func:`segment_plan`.

    ``first_frames``, ``last_frames``: (S,) int64 pose indices; ``lengths``: (S,) nominal
    segment lengths, metres, in the float type the plan was built with (float64 unless it is
    the devkit's float32); ``num_poses``: the trajectory's pose count N.
    :mod:`gloam_jax.training.losses` registers it as a JAX pytree with ``num_poses`` static, so
    it can be closed over or passed to jitted functions.
    """

    first_frames: NDArray[np.int64]
    last_frames: NDArray[np.int64]
    lengths: NDArray[np.floating[Any]]
    num_poses: int

    @property
    def num_segments(self) -> int:
        """S, the number of segments."""
        return int(np.shape(self.first_frames)[0])


def _check_step(step: int) -> int:
    if int(step) != step or step < 1:
        raise ValueError(f"step must be a positive integer, got {step!r}")
    return int(step)


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
    gt_poses: ArrayLike,
    lengths: Sequence[float] = DEFAULT_LENGTHS,
    *,
    step: int = 10,
    dtype: type[np.floating[Any]] = np.float64,
    source: Source = None,
) -> SegmentPlan:
    """The segments of ``gt_poses`` (N, 4, 4) that :func:`kitti_rte` scores, for ``lengths``
    in metres.

    A segment starts at every ``step``-th frame ``f``; for each length ``L`` it ends at the first
    frame whose ground-truth path distance exceeds ``dist[f] + L`` and is dropped when there is
    none. Distances and lengths are summed and compared in ``dtype``: float64, or float32 to
    replay the devkit's C ``float``. Lengths may be fractional (see :func:`scaled_lengths`);
    ``kitti_rte`` itself takes whole metres only. Raises :class:`InputError` for bad poses or
    when no segment fits.
    """
    step = _check_step(step)
    lens = _check_values(lengths, "segment lengths (m)", math.inf).astype(dtype)
    gt = as_poses(gt_poses, "ground-truth", source)
    n = gt.shape[0]
    dist = _distances(gt, dtype)
    starts = np.arange(0, n, step, dtype=np.int64)
    # Devkit order: first frame in the outer loop, length in the inner one.
    first = np.repeat(starts, lens.size)
    seg_len = np.tile(lens, starts.size)
    # dist is non-decreasing, so the devkit's linear scan for the first dist[j] > dist[f] + L
    # is exactly a right-sided binary search.
    last = np.searchsorted(dist, dist[first] + seg_len, side="right")
    keep = last < n
    if not keep.any():
        # A segment must be strictly longer than its length, so equality is too short as well.
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
    gt_poses: ArrayLike,
    fractions: Sequence[float] = TRAINING_FRACTIONS,
    *,
    source: Source = None,
) -> tuple[float, ...]:
    """Segment lengths in metres for a short window: ``fractions`` (each in (0, 1)) of the
    ground-truth path length of ``gt_poses`` (N, 4, 4).

    Every fraction below 1 leaves at least the segment from frame 0, so a 150 m window gets
    segments of 15..120 m with the defaults. Raises :class:`InputError` for a path of length 0.
    """
    frac = _check_values(fractions, "length fractions", 1.0)
    gt = as_poses(gt_poses, "ground-truth", source)
    total = float(_distances(gt)[-1])
    if total <= 0.0:
        raise InputError(
            source,
            f"the ground-truth path of {gt.shape[0]} poses has zero length, so no "
            "segment length can be scaled from it",
        )
    return tuple(float(f * total) for f in frac)


@dataclass(frozen=True)
class RteResult:
    """KITTI relative trajectory error.

    The scalar fields average over every segment of every length (the devkit's sequence score).
    ``per_length`` has one entry per length with at least one segment. The per-segment arrays,
    all ``(S,)`` in the devkit's order (first frame outer, length inner), hold ``t_err`` as a
    fraction (m/m) and ``r_err`` in rad/m, both divided by the nominal segment length (float32
    values held as float64 with the default ``precision="devkit"``).
    """

    t_err_percent: float
    r_err_deg_per_100m: float
    num_segments: int
    per_length: dict[int, dict[str, float | int]]
    first_frames: NDArray[np.int64] = field(repr=False)
    last_frames: NDArray[np.int64] = field(repr=False)
    segment_lengths: NDArray[np.float64] = field(repr=False)
    t_err: NDArray[np.float64] = field(repr=False)
    r_err: NDArray[np.float64] = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: plain floats and ints, ``per_length`` keyed by strings."""
        return {
            "t_err_percent": float(self.t_err_percent),
            "r_err_deg_per_100m": float(self.r_err_deg_per_100m),
            "num_segments": int(self.num_segments),
            "per_length": {
                str(length): {
                    "t_err_percent": float(v["t_err_percent"]),
                    "r_err_deg_per_100m": float(v["r_err_deg_per_100m"]),
                    "num_segments": int(v["num_segments"]),
                }
                for length, v in self.per_length.items()
            },
        }


def _check_lengths(lengths: tuple[float, ...] | list[float]) -> list[int]:
    out: list[int] = []
    for length in lengths:
        # Integer metres keep the per-length dict keys (and their JSON strings) unambiguous.
        if not (math.isfinite(length) and float(length).is_integer() and length > 0):
            raise ValueError(f"segment lengths must be positive whole metres, got {length!r}")
        out.append(int(length))
    if not out:
        raise ValueError("at least one segment length is needed")
    if len(set(out)) != len(out):
        raise ValueError(f"segment lengths must be distinct, got {list(lengths)}")
    return out


def kitti_rte(
    gt_poses: ArrayLike,
    est_poses: ArrayLike,
    *,
    step: int = 10,
    lengths: tuple[float, ...] | list[float] = DEFAULT_LENGTHS,
    precision: Precision = "devkit",
    source: Source = None,
) -> RteResult:
    """KITTI odometry relative trajectory error of ``est_poses`` (N, 4, 4) against ``gt_poses``.

    Same definition as the official devkit: segments start every ``step`` frames; a segment of
    length ``L`` from frame ``f`` ends at the first frame whose ground-truth distance exceeds
    ``dist[f] + L``; its error pose is ``inv(inv(E_f) E_l) @ (inv(G_f) G_l)``; errors are divided
    by ``L`` (not the actual distance) and averaged over all segments of all lengths.

    ``precision="devkit"`` replays the devkit's C ``float`` steps: the official benchmark numbers.
    ``"float64"``: exact values; r_err differs ~1e-3 relative, more near 0 (float arccos ~5e-4 rad).

    Raises :class:`InputError` (with ``source`` as the file name) for mismatched lengths, bad
    shapes, NaN/inf, or a trajectory too short for any segment.
    """
    step = _check_step(step)
    lens = _check_lengths(lengths)
    real = _float_type(precision)
    gt, est = _as_pair(gt_poses, est_poses, source)
    plan = segment_plan(gt, lens, step=step, dtype=real, source=source)
    first, last, seg_len = plan.first_frames, plan.last_frames, plan.lengths

    # General inverses (not the rigid-transform shortcut), as the devkit does, so slightly
    # non-orthonormal rotations read from text are treated identically.
    delta_gt = np.linalg.inv(gt[first]) @ gt[last]
    delta_est = np.linalg.inv(est[first]) @ est[last]
    err = np.linalg.inv(delta_est) @ delta_gt
    # The devkit's rotationError: d = 0.5 * (a + b + c - 1.0) with a, b, c and the sum in `real`
    # but the double literal 1.0 making the rest double, then d rounded back to `real`.
    diag = np.diagonal(err[:, :3, :3], axis1=1, axis2=2).astype(real)
    trace = diag[:, 0] + diag[:, 1] + diag[:, 2]
    cos_angle = (0.5 * (trace.astype(np.float64) - 1.0)).astype(real)
    r_err = np.arccos(np.clip(cos_angle, real(-1.0), real(1.0))) / seg_len
    t_err = _norm3(err[:, :3, 3].astype(real)) / seg_len

    per_length: dict[int, dict[str, float | int]] = {}
    for length in lens:
        sel = seg_len == length
        count = int(sel.sum())
        if count:
            per_length[length] = {
                "t_err_percent": _mean(t_err[sel]) * 100.0,
                "r_err_deg_per_100m": _mean(r_err[sel]) * _RAD_PER_M_TO_DEG_PER_100M,
                "num_segments": count,
            }
    return RteResult(
        t_err_percent=_mean(t_err) * 100.0,
        r_err_deg_per_100m=_mean(r_err) * _RAD_PER_M_TO_DEG_PER_100M,
        num_segments=int(t_err.size),
        per_length=per_length,
        first_frames=first,
        last_frames=last,
        segment_lengths=seg_len.astype(np.float64),
        t_err=t_err.astype(np.float64),
        r_err=r_err.astype(np.float64),
    )


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error of positions, metres.

    ``errors`` is (N,); ``rotation`` (3, 3) and ``translation`` (3,) map the estimate onto the
    ground truth (identity and zero when ``aligned`` is False). ``std`` is the population std.
    """

    rmse: float
    mean: float
    median: float
    std: float
    max: float
    num_poses: int
    aligned: bool
    errors: NDArray[np.float64] = field(repr=False)
    rotation: NDArray[np.float64] = field(repr=False)
    translation: NDArray[np.float64] = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (statistics, ``num_poses``, ``aligned``)."""
        return {
            "rmse": float(self.rmse),
            "mean": float(self.mean),
            "median": float(self.median),
            "std": float(self.std),
            "max": float(self.max),
            "num_poses": int(self.num_poses),
            "aligned": bool(self.aligned),
        }


def _umeyama_se3(
    src: NDArray[np.float64], dst: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rigid (R, t) minimising sum ||dst - (R src + t)||^2 for points (N, 3); no scale."""
    mu_src = src.mean(axis=0)
    mu_dst = dst.mean(axis=0)
    cov = (dst - mu_dst).T @ (src - mu_src) / src.shape[0]
    u, _, vt = np.linalg.svd(cov)
    # Flip the weakest axis when needed so that R is a rotation, never a reflection.
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        d[2] = -1.0
    rot = (u * d) @ vt
    return rot, mu_dst - rot @ mu_src


def ate(
    gt_poses: ArrayLike,
    est_poses: ArrayLike,
    align: bool = True,
    *,
    source: Source = None,
) -> AteResult:
    """Absolute position error of ``est_poses`` (N, 4, 4) against ``gt_poses`` (N, 4, 4).

    With ``align`` the estimate is first moved by the least-squares rigid transform (Umeyama,
    rotation + translation, no scale) onto the ground truth.
    """
    gt, est = _as_pair(gt_poses, est_poses, source)
    p_gt = gt[:, :3, 3]
    p_est = est[:, :3, 3]
    if align:
        rot, trans = _umeyama_se3(p_est, p_gt)
    else:
        rot, trans = np.eye(3), np.zeros(3)
    errors = np.linalg.norm(p_gt - (p_est @ rot.T + trans), axis=1)
    return AteResult(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(errors.mean()),
        median=float(np.median(errors)),
        std=float(errors.std()),
        max=float(errors.max()),
        num_poses=int(errors.size),
        aligned=bool(align),
        errors=errors,
        rotation=rot,
        translation=trans,
    )


def frame_rotation_drift(
    gt_poses: ArrayLike, est_poses: ArrayLike, *, source: Source = None
) -> dict[str, Any]:
    """Each frame's rotation error, split into drift and noise: the mean over frames of the
    error of the estimated frame-to-frame motion (its rotation vector about the poses' own
    x, y, z axes; for KITTI's camera-0 poses pitch, yaw, roll) and its standard deviation,
    millidegrees a frame. A mean adds up over a drive (a per-frame bias b tilts the path by
    n b after n frames); noise around it largely does not. (N, 4, 4) each, N >= 2."""
    gt, est = _as_pair(gt_poses, est_poses, source)
    if gt.shape[0] < 2:
        raise InputError(source, "frame-to-frame errors need at least 2 poses")
    err = np.linalg.inv(frame_motions(gt)) @ frame_motions(est)
    mdeg = Rotation.from_matrix(err[:, :3, :3]).as_rotvec(degrees=True) * 1e3
    std = mdeg.std(axis=0, ddof=1) if len(mdeg) > 1 else np.zeros(3)
    return {
        "mean_mdeg": [float(v) for v in mdeg.mean(axis=0)],
        "std_mdeg": [float(v) for v in std],
        "num_frames": int(len(mdeg)),
    }


def evaluate(
    gt_poses: ArrayLike,
    est_poses: ArrayLike,
    *,
    step: int = 10,
    lengths: tuple[float, ...] | list[float] = DEFAULT_LENGTHS,
    precision: Precision = "devkit",
    source: Source = None,
) -> dict[str, Any]:
    """KITTI RTE and aligned ATE of (N, 4, 4) trajectories in one JSON-ready dict.

    Keys: those of :meth:`RteResult.to_dict`, ``ate`` (:meth:`AteResult.to_dict`),
    ``frame_rotation`` (:func:`frame_rotation_drift`), ``num_poses`` and ``path_length_m``
    (ground-truth path length); ``precision`` as for :func:`kitti_rte`.
    """
    gt, est = _as_pair(gt_poses, est_poses, source)
    rte = kitti_rte(gt, est, step=step, lengths=lengths, precision=precision, source=source)
    return {
        **rte.to_dict(),
        "ate": ate(gt, est, align=True, source=source).to_dict(),
        "frame_rotation": frame_rotation_drift(gt, est, source=source),
        "num_poses": int(gt.shape[0]),
        "path_length_m": float(_distances(gt)[-1]),
    }


def evaluate_without_rte(
    gt_poses: ArrayLike, est_poses: ArrayLike, problem: str, *, source: Source = None
) -> dict[str, Any]:
    """What :func:`evaluate` gives of a path too short for the devkit's segments (``problem``
    says why, as ``rte_unavailable``): ``ate`` and ``frame_rotation`` (None for one pose)."""
    gt, est = _as_pair(gt_poses, est_poses, source)
    return {
        "rte_unavailable": problem,
        "ate": ate(gt, est, source=source).to_dict(),
        "frame_rotation": frame_rotation_drift(gt, est) if len(gt) > 1 else None,
    }


def format_spread(agg: dict[str, Any]) -> str:
    """``mean ± std`` (3 decimals) of an error aggregated over runs, ``{"mean", "std"}`` as the
    protocol's tables and test scores keep it; one run has no spread (``± n/a``)."""
    std = "n/a" if agg.get("std") is None else f"{agg['std']:.3f}"
    return f"{agg['mean']:.3f} ± {std}"


def _plane_axes(*positions: NDArray[np.float64]) -> tuple[int, int]:
    """The two axes with the largest extent, in axis order (x-z for KITTI camera poses)."""
    pts = np.concatenate(positions, axis=0)
    extent = pts.max(axis=0) - pts.min(axis=0)
    # Stable sort so that ties (e.g. a straight line) fall back to the lower axis index.
    first, second = sorted(np.argsort(-extent, kind="stable")[:2].tolist())
    return int(first), int(second)


def _trajectory_panel(ax, p_gt, p_est, axes: tuple[int, int]) -> None:
    """Estimated (and ground-truth, unless None) positions (N, 3) on the plane of ``axes``."""
    a, b = axes
    if p_gt is not None:
        ax.plot(p_gt[:, a], p_gt[:, b], color="tab:red", lw=1.2, label="ground truth")
    ax.plot(p_est[:, a], p_est[:, b], color="tab:blue", lw=1.2, label="estimate")
    ax.plot(p_est[0, a], p_est[0, b], "ks", ms=6, mfc="none", label="start")
    ax.set_xlabel(f"{'xyz'[a]} [m]")
    ax.set_ylabel(f"{'xyz'[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")


def plot_trajectory(
    est_poses: ArrayLike, gt_poses: ArrayLike | None, path: str | os.PathLike[str], title: str
) -> Path:
    """Write a PNG of the trajectory panel alone (where no RTE is available): the estimate, and
    the ground truth unless None, on the plane of their two largest extents."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    p_est = as_poses(est_poses, "estimated")[:, :3, 3]
    p_gt = None if gt_poses is None else as_poses(gt_poses, "ground-truth")[:, :3, 3]
    fig = Figure(figsize=(7.0, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    _trajectory_panel(ax, p_gt, p_est, _plane_axes(*(p for p in (p_est, p_gt) if p is not None)))
    ax.set_title(title, fontsize=9)
    return write_figure(path, fig, dpi=110)


def plot_evaluation(
    gt_poses: ArrayLike,
    est_poses: ArrayLike,
    rte_result: RteResult | None,
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
    source: Source = None,
) -> Path:
    """Write a PNG: top-down trajectories, and t_err % / r_err deg/100m per segment length.

    ``rte_result`` is computed with the defaults when None. The file is written atomically
    (temporary file in the same folder, then renamed); parent folders are created. Returns the
    path written.
    """
    # The object-oriented API with an explicit Agg canvas leaves pyplot's global state and the
    # user's backend alone, and works without a display.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    gt, est = _as_pair(gt_poses, est_poses, source)
    if rte_result is None:
        rte_result = kitti_rte(gt, est, source=source)
    p_gt, p_est = gt[:, :3, 3], est[:, :3, 3]
    ax0, ax1 = _plane_axes(p_gt, p_est)

    fig = Figure(figsize=(13.0, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 2, width_ratios=(1.3, 1.0))
    ax_traj = fig.add_subplot(grid[:, 0])
    ax_t = fig.add_subplot(grid[0, 1])
    ax_r = fig.add_subplot(grid[1, 1], sharex=ax_t)

    _trajectory_panel(ax_traj, p_gt, p_est, (ax0, ax1))
    ax_traj.set_title(
        f"t_err {rte_result.t_err_percent:.3f} %   "
        f"r_err {rte_result.r_err_deg_per_100m:.4f} deg/100m   "
        f"({rte_result.num_segments} segments)"
    )

    lens = sorted(rte_result.per_length)
    t_vals = [rte_result.per_length[k]["t_err_percent"] for k in lens]
    r_vals = [rte_result.per_length[k]["r_err_deg_per_100m"] for k in lens]
    ax_t.plot(lens, t_vals, "o-", color="tab:blue")
    ax_t.set_ylabel("translation error [%]")
    ax_r.plot(lens, r_vals, "o-", color="tab:orange")
    ax_r.set_ylabel("rotation error [deg/100m]")
    ax_r.set_xlabel("segment length [m]")
    for ax in (ax_t, ax_r):
        ax.set_ylim(bottom=0.0)
        ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)

    return write_figure(path, fig, dpi=110)
