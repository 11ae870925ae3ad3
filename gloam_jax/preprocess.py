"""One raw scan -> the voxel centres that registration sees, as the odometry and training do.

The steps, in order: drop NaN / inf points and crop to a range band, carry per-point times
(given, or from the azimuth) and PCA features through the voxel grid (averaged per voxel),
thin evenly to a frozen padded size, and deskew the voxel centres to the scan's reference
time with a constant velocity.

Times are seconds from the scan's reference time (KITTI: mid-sweep, when the camera
triggers); the velocity is the se(3) motion per frame interval, in
:mod:`gloam_jax.geometry`'s tangent order (rho, phi).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Literal

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax import geometry as geo
from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError

if TYPE_CHECKING:
    from gloam_jax.features.pca import FeaturePCA


@dataclass(frozen=True)
class PreprocessConfig:
    """How a raw scan becomes registration input (the odometry's and the training's)."""

    min_range: float = 3.0  # m; closer returns hit the vehicle itself
    max_range: float = 100.0  # m
    downsampling_resolution: float = 0.5  # m, voxel size of each scan
    num_neighbors: int = 10  # k of the k-NN covariances (small_gicp's default)
    # plain GICP's eigenvalues (1, 1, eps) or the raw ones floored at eps; methods with learned
    # covariances replace it by Algorithm 1
    regularizer: Literal["plane", "raw_eps"] = "plane"
    deskew: bool = True  # undo motion distortion with the current velocity
    sweep_duration: float = 0.1  # s, for azimuth times when scans carry no per-point times

    # Settings that change the prepared scans themselves (not how they are registered).
    SCAN_FIELDS: ClassVar[tuple[str, ...]] = (
        "min_range", "max_range", "downsampling_resolution", "num_neighbors", "deskew",
        "sweep_duration",
    )  # fmt: skip


def azimuth_times(points: np.ndarray, sweep_duration: float) -> np.ndarray:
    """Per-point time (s) from mid-sweep, for a sensor that turns clockwise from behind.

    ``-atan2(y, x) / (2 pi)`` is the fraction of the sweep since the forward-facing moment,
    as KITTI's HDL-64E turns (the convention KISS-ICP uses). Returns (N,).
    """
    return -np.arctan2(points[:, 1], points[:, 0]) / (2 * np.pi) * sweep_duration


@jax.jit
def _deskew(points: jax.Array, fraction: jax.Array, xi: jax.Array) -> jax.Array:
    """Move each point into the mid-sweep frame: ``exp(fraction * xi) @ p`` (P, 3)."""
    T = geo.se3_exp(fraction[:, None] * xi[None, :])
    return jnp.einsum("nij,nj->ni", T[:, :3, :3], points) + T[:, :3, 3]


def deskew(
    points: np.ndarray,
    times: np.ndarray,
    xi_per_frame: np.ndarray,
    frame_dt: float,
    size: int | None = None,
) -> np.ndarray:
    """Undo motion distortion with constant velocity: points (N, 3), times (N,) s -> (N, 3).
    ``size``: pad to this many rows (default: the bucket size)."""
    size = pc.bucket_size(len(points)) if size is None else size
    padded, _ = pc.pad(np.asarray(points, np.float64), size)
    frac, _ = pc.pad(np.asarray(times, np.float64) / frame_dt, size)
    # float32 unless JAX runs in x64 mode: jnp.asarray picks the default precision.
    xi = np.asarray(xi_per_frame, np.float64)
    out = _deskew(jnp.asarray(padded), jnp.asarray(frac), jnp.asarray(xi))
    return np.asarray(out, dtype=np.float64)[: len(points)]


def preprocess_scan(
    scan: np.ndarray,
    times: np.ndarray | None,
    config: PreprocessConfig,
    *,
    velocity: np.ndarray | None = None,
    frame_dt: float = 0.1,
    pca: FeaturePCA | None = None,
    features: np.ndarray | None = None,
    buckets: pc.StickyBuckets | None = None,
    source: str | None = None,
) -> tuple[np.ndarray, np.ndarray | None, int, int]:
    """One raw scan (N, 3+) -> its voxel centres (M, 3) float64, deskewed with ``velocity``
    (se(3) per ``frame_dt``; None: not deskewed), their PCA features (M, 6) when ``pca`` is
    given (from the backbone's ``features`` (N, D)), the number of NaN / inf points dropped
    and the number of voxel centres thinned out.

    ``times`` (N,) s from the reference time, or None for times from the azimuth. ``buckets``
    size the deskew's padding (role "scan"); once frozen, centres beyond their limit are
    thinned evenly along the voxel order (so evenly in space). Raises InputError for scans
    without points in range and for features of the wrong shape.
    """
    keep, dropped = pc.range_mask(scan, config.min_range, config.max_range, source)
    points = scan[keep, :3].astype(np.float64)
    if len(points) == 0:
        raise InputError(source, f"no points between {config.min_range} and {config.max_range} m")
    t = times[keep] if times is not None else azimuth_times(points, config.sweep_duration)
    columns = [np.column_stack([points, t])]
    if pca is not None:
        if features is None or len(features) != len(scan):
            rows = "no" if features is None else len(features)
            raise InputError(source, f"features have {rows} rows but the scan has {len(scan)}")
        if features.shape[-1] != pca.input_dim:
            raise InputError(
                source,
                f"features have {features.shape[-1]} columns, the model's PCA expects "
                f"{pca.input_dim}",
            )
        # The PCA is affine, so it commutes with the voxel mean: carry 6 columns, not D.
        columns.append(pca.transform(features)[keep])
    # Downsample first (a voxel's points share a place, so nearly a time), then deskew the
    # few voxel centres with their mean time; features are averaged per voxel alike.
    columns = pc.voxel_means(points, config.downsampling_resolution, columns)
    limit = None if buckets is None else buckets.limit("scan")
    thinned = 0
    if limit is not None and len(columns[0]) > limit:
        thinned = len(columns[0]) - limit
        rows = np.linspace(0, len(columns[0]) - 1, limit).round().astype(np.int64)
        columns = [c[rows] for c in columns]
    reduced, pca_features = columns[0], (columns[1] if pca is not None else None)
    points = reduced[:, :3]
    if config.deskew and velocity is not None:
        size = None if buckets is None else buckets("scan", len(points))
        points = deskew(points, reduced[:, 3], velocity, frame_dt, size)
    return points, pca_features, dropped, thinned
