"""One raw scan -> the voxel centres that registration sees, as the odometry and training do.

The steps, in order: drop NaN / inf points and crop to a range band, carry per-point times
(given, or from the azimuth) and PCA features through the voxel grid (averaged per voxel),
and deskew the voxel centres to the scan's reference time with a constant velocity. Every
voxel centre is kept: each scan is padded to the smallest size bucket that holds it.

Deskew policy (``PreprocessConfig.deskew``): ``timestamps`` uses the scan's per-point times,
``azimuth`` derives them from each point's azimuth (a spinning sensor, KITTI's HDL-64E),
``off`` leaves the scan as it is. ``auto`` is resolved by the data: per-point times when the
scans have them, azimuth times for the KITTI layout (its raw scans are motion-distorted), off
otherwise (:func:`resolve_deskew`); given to :func:`preprocess_scan` directly, ``auto`` uses
the times when given and the azimuth otherwise.

Per-point times may come in any common convention (seconds from the sweep's start or from
mid-sweep, a [0, 1] fraction, absolute seconds or nanoseconds): as KISS-ICP does, they are
normalised by their span onto one sweep (:func:`normalise_times`), and the convention found is
reported. Internally, times are seconds from the scan's reference time (mid-sweep, when KITTI's
camera triggers); the velocity is the se(3) motion per frame interval, in
:mod:`gloam_jax.geometry`'s tangent order (rho, phi).
"""

from __future__ import annotations

import math
from contextlib import nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Literal, Protocol, get_args

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax import geometry as geo
from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError

if TYPE_CHECKING:
    from gloam_jax.features.pca import FeaturePCA
    from gloam_jax.timing import StageTimer


class GridFeatures(Protocol):
    """A backbone whose features are per voxel of the preprocessing's own grid
    (:meth:`gloam_jax.features.GeometricBackbone.voxel_features`)."""

    def shares_grid(self, resolution: float, min_range: float, max_range: float) -> bool: ...

    def voxel_features(
        self,
        xyz: np.ndarray,
        intensity: np.ndarray | None,
        grid: pc.VoxelGrid,
        centres: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]: ...


def on_grid(backbone: object, config: PreprocessConfig) -> GridFeatures | None:
    """``backbone`` where its features can come from ``config``'s own voxel grid (the same
    voxels and range band: :func:`voxel_centres` then needs no per-point features), else
    None."""
    shares = getattr(backbone, "shares_grid", None)
    if shares is None or config.downsampling_resolution <= 0:
        return None
    ok = shares(config.downsampling_resolution, config.min_range, config.max_range)
    return backbone if ok else None  # type: ignore[return-value]


DeskewPolicy = Literal["auto", "timestamps", "azimuth", "off"]
DESKEW_POLICIES: tuple[str, ...] = get_args(DeskewPolicy)


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class PreprocessConfig:
    """How a raw scan becomes registration input (the odometry's and the training's)."""

    min_range: float = 3.0  # m; closer returns (the vehicle itself) are dropped; 0 keeps all
    max_range: float = 100.0  # m; farther returns are dropped; above min_range
    # m, voxel size of each scan (one point per voxel, their mean); 0 turns downsampling off
    downsampling_resolution: float = 0.5
    num_neighbors: int = 10  # k of the k-NN covariances (small_gicp's default), at least 3
    # plain GICP's eigenvalues (1, 1, eps) or the raw ones floored at eps; methods with learned
    # covariances replace it by Algorithm 1
    regularizer: Literal["plane", "raw_eps"] = "plane"
    # undo motion distortion with the current velocity: auto (by the data), timestamps (the
    # scans' per-point times), azimuth (times from each point's azimuth) or off; true and false
    # from older files are read as auto and off
    deskew: DeskewPolicy | bool = "auto"
    # s, one sweep: per-point times are normalised onto it, and azimuth times span it
    sweep_duration: float = 0.1

    # Settings that change the prepared scans themselves (not how they are registered).
    SCAN_FIELDS: ClassVar[tuple[str, ...]] = (
        "min_range", "max_range", "downsampling_resolution", "num_neighbors", "deskew",
        "sweep_duration",
    )  # fmt: skip

    def __post_init__(self) -> None:
        def fail(name: str, rule: str) -> None:
            raise InputError(None, f"preprocess.{name} must be {rule}, not {getattr(self, name)!r}")

        if isinstance(self.deskew, bool):  # settings files written before the policies
            object.__setattr__(self, "deskew", "auto" if self.deskew else "off")
        if self.deskew not in DESKEW_POLICIES:
            fail("deskew", f"one of {list(DESKEW_POLICIES)}")
        if not (_number(self.min_range) and self.min_range >= 0):
            fail("min_range", "a number >= 0")
        if not (_number(self.max_range) and self.max_range > 0):
            fail("max_range", "positive")
        if self.min_range >= self.max_range:
            raise InputError(
                None,
                f"preprocess.min_range ({self.min_range}) must be below preprocess.max_range "
                f"({self.max_range}): no point would be kept",
            )
        if not (_number(self.downsampling_resolution) and self.downsampling_resolution >= 0):
            fail("downsampling_resolution", "a voxel size > 0 (m), or 0 for no downsampling")
        n = self.num_neighbors
        if not (isinstance(n, int) and not isinstance(n, bool) and n >= 3):
            fail("num_neighbors", "an integer >= 3")
        if not (_number(self.sweep_duration) and self.sweep_duration > 0):
            fail("sweep_duration", "positive")


# Time units a per-point time column may come in, by how many of them make a second.
_UNITS = (("s", 1.0), ("ms", 1e3), ("us", 1e6), ("ns", 1e9))
# All per-point times equal: the sweep is one instant (deskewed already, or a simulator
# without motion distortion); deskewing by times then moves no point.
ONE_INSTANT = "one instant"


def detect_time_convention(times: np.ndarray, sweep_duration: float, source=None) -> str:
    """Which convention per-point times follow, from their range: ``fraction [0, 1]``,
    ``s from start``, ``s from mid-sweep``, ``s before end``, ``absolute s``, and the same with
    ``ms``, ``us`` or ``ns``; or ``one instant`` when all are equal (a scan already deskewed,
    or taken without motion distortion: nothing to undo). Otherwise the span must be one sweep
    (a quarter to four times ``sweep_duration``) in some unit, or [0, 1]; anything else is an
    InputError."""
    t = np.asarray(times)
    if t.size == 0:
        raise InputError(source, "no per-point times")
    if t.dtype.kind not in "fiu":
        raise InputError(source, f"per-point times are not numbers (dtype {t.dtype})")
    lo, hi = t.min(), t.max()
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise InputError(source, "per-point times contain NaN or infinite values")
    span = float(hi - lo)  # before float conversion: int64 nanoseconds stay exact
    lo, hi = float(lo), float(hi)
    if span == 0:
        return ONE_INSTANT
    if lo >= -1e-6 and hi <= 1 + 1e-6 and span >= 0.5:
        return "fraction [0, 1]"
    for unit, per_second in _UNITS:
        if 0.25 <= span / per_second / sweep_duration <= 4:
            tol = 0.05 * span
            if abs(lo) <= tol:
                where = "from start"
            elif abs(hi) <= tol:
                where = "before end"
            elif abs(lo + hi) <= 2 * tol:
                where = "from mid-sweep"
            elif lo > 1e6 * per_second:  # after 1970-01-12: a clock, not an offset
                return f"absolute {unit}"
            else:
                where = "with an offset"
            return f"{unit} {where}"
    raise InputError(
        source,
        f"per-point times span {span:g} (from {lo:g} to {hi:g}), which fits no convention: "
        f"a [0, 1] fraction, or one sweep of {sweep_duration} s (preprocess.sweep_duration) "
        "in s, ms, us or ns",
    )


def normalise_times(
    times: np.ndarray, sweep_duration: float, source=None
) -> tuple[np.ndarray, str]:
    """Per-point times in any convention -> (seconds from mid-sweep (N,) float64, convention).
    Times that are all equal stay one instant: zeros, the scan is not deskewed.

    As KISS-ICP does, the times are mapped by their span onto one sweep: the earliest point
    at ``-sweep_duration / 2``, the latest at ``+sweep_duration / 2``, whatever their unit or
    origin (see :func:`detect_time_convention`).
    """
    convention = detect_time_convention(times, sweep_duration, source)
    t = np.asarray(times)
    if convention == ONE_INSTANT:
        return np.zeros(t.shape), convention
    offset = t - t.min()  # in the stored type first: int64 nanoseconds stay exact
    fraction = offset.astype(np.float64) / float(offset.max())
    return (fraction - 0.5) * sweep_duration, convention


def resolve_deskew(policy: str, has_times: bool, distorted_layout: bool) -> tuple[str, str]:
    """The concrete policy (``timestamps``, ``azimuth`` or ``off``) for data with or without
    per-point times, from a layout known to be motion-distorted (KITTI) or not, and why.
    ``timestamps`` without times is an InputError."""
    if policy == "timestamps" and not has_times:
        raise InputError(
            None,
            "preprocess.deskew is 'timestamps' but the scans have no per-point times "
            "(use auto, azimuth or off)",
        )
    if policy != "auto":
        return policy, f"deskew: {policy} (as configured)"
    if has_times:
        return "timestamps", "deskew: auto -> timestamps (the scans carry per-point times)"
    if distorted_layout:
        return "azimuth", (
            "deskew: auto -> azimuth (KITTI layout without per-point times: raw scans are "
            "motion-distorted, times taken from each point's azimuth; set preprocess.deskew: "
            "off for scans deskewed already, which this would distort)"
        )
    return "off", (
        "deskew: auto -> off (no per-point times and not the KITTI layout; set "
        "preprocess.deskew: azimuth to deskew a spinning sensor's scans)"
    )


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
) -> np.ndarray:
    """Undo motion distortion with constant velocity: points (N, 3), times (N,) s -> (N, 3),
    padded on the device to their size bucket."""
    size = pc.bucket_size(len(points))
    padded, _ = pc.pad(np.asarray(points, np.float64), size)
    frac, _ = pc.pad(np.asarray(times, np.float64) / frame_dt, size)
    # float32 unless JAX runs in x64 mode: jnp.asarray picks the default precision.
    xi = np.asarray(xi_per_frame, np.float64)
    out = _deskew(jnp.asarray(padded), jnp.asarray(frac), jnp.asarray(xi))
    return np.asarray(out, dtype=np.float64)[: len(points)]


# A scan whose median range is beyond this (m) is not in metres.
MAX_MEDIAN_RANGE = 1000.0


def check_units(scan: np.ndarray, config: PreprocessConfig, source=None) -> None:
    """InputError when a scan (N, 3+) looks like millimetres rather than metres: its median
    range is over 1 km, or 99 % of its (finite) points lie beyond ``config.max_range``."""
    with np.errstate(invalid="ignore", over="ignore"):  # a damaged file's garbage values
        ranges = np.linalg.norm(scan[:, :3].astype(np.float64), axis=1)
    ranges = ranges[np.isfinite(ranges)]
    if len(ranges) == 0:
        return  # nothing to judge: the odometry reports a scan without points
    median, beyond = float(np.median(ranges)), float(np.mean(ranges > config.max_range))
    if median > MAX_MEDIAN_RANGE or beyond >= 0.99:
        raise InputError(
            source,
            f"median range {median:.0f} m, {100 * beyond:.1f} % of points beyond "
            f"preprocess.max_range ({config.max_range:g} m): the scan looks like millimetres, "
            "not metres (scale it by 0.001)",
        )


def centre_rows(
    scan: np.ndarray, config: PreprocessConfig, source: str | None = None
) -> np.ndarray:
    """Which voxel centre of :func:`preprocess_scan` each raw point (N,) went into, -1 for
    points it dropped: the map that averages per-point quantities onto the centres (the
    fine-tuned backbone's features in training)."""
    band = pc.range_band(scan, config.min_range, config.max_range, source)
    rows = np.full(len(scan), -1, np.int64)
    if config.downsampling_resolution <= 0:
        rows[band.keep] = np.arange(len(band.xyz))
    elif len(band.xyz):
        rows[band.keep] = pc.voxel_index(band.xyz, config.downsampling_resolution)[0]
    return rows


@dataclass(frozen=True)
class VoxelCentres:
    """A scan prepared up to its deskew: the part of :func:`preprocess_scan` that does not
    depend on the motion, so it can run ahead of the registration (on the prefetch thread).

    ``points`` (M, 3) float64 voxel centres as measured; ``times`` (M,) their mean per-point
    time, s from the scan's reference time (zeros when the policy is off); ``features``
    (M, 6) their mean PCA features or None; ``dropped``: NaN / inf points removed;
    ``deskew``: whether the policy moves them (not ``off``); ``neighbours`` (M, k) int32:
    each centre's ``num_neighbors`` nearest centres as measured, nearest first, where a grid
    backbone queried them for its features, else None.

    Where given, the covariances take these neighbourhoods instead of querying the deskewed
    centres again: the deskew moves neighbouring points alike (measured within about a
    millisecond of each other), except across the sweep's seam, so the sets differ little,
    and the query is not paid twice (experiments/shared_knn).
    """

    points: np.ndarray
    times: np.ndarray
    features: np.ndarray | None
    dropped: int
    deskew: bool
    neighbours: np.ndarray | None = None


def voxel_centres(
    scan: np.ndarray,
    times: np.ndarray | None,
    config: PreprocessConfig,
    *,
    pca: FeaturePCA | None = None,
    features: np.ndarray | None = None,
    backbone: GridFeatures | None = None,
    source: str | None = None,
    timer: StageTimer | None = None,
) -> VoxelCentres:
    """One raw scan (N, 3+) -> its voxel centres before the deskew (:func:`preprocess_scan`
    has the arguments). With ``pca``, the centres' features come either from ``features``
    (N, D), averaged per voxel, or from ``backbone`` on this grid (the same values: the
    backbone must share the grid, ``shares_grid``), timed as stage ``features`` of ``timer``."""
    band = pc.range_band(scan, config.min_range, config.max_range, source)
    keep, points, dropped = band.keep, band.xyz, band.invalid
    if len(points) == 0:
        raise InputError(source, f"no points between {config.min_range} and {config.max_range} m")
    policy = config.deskew
    if policy == "auto":
        policy = "timestamps" if times is not None else "azimuth"
    if policy == "timestamps":
        if times is None:
            raise InputError(source, "preprocess.deskew is 'timestamps' but no per-point times")
        if len(times) != len(scan):
            raise InputError(source, f"{len(times)} per-point times for {len(scan)} points")
        t = normalise_times(times, config.sweep_duration, source)[0][keep]
    elif policy == "azimuth":
        t = azimuth_times(points, config.sweep_duration)
    else:
        t = np.zeros(len(points))
    columns = [np.column_stack([points, t])]
    grid_features = pca is not None and backbone is not None
    if grid_features and on_grid(backbone, config) is None:
        raise ValueError("the backbone does not share this preprocessing's voxel grid")
    if pca is not None and not grid_features:
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
        columns.append(np.compress(keep, pca.transform(features), axis=0))
    # Downsample first (a voxel's points share a place, so nearly a time), then deskew the
    # few voxel centres with their mean time; features are averaged per voxel alike.
    if config.downsampling_resolution > 0:
        grid = pc.voxel_grid(points, config.downsampling_resolution)
        columns = [grid.means(a) for a in columns]
    neighbours, reduced = None, columns[0]
    if grid_features:
        with nullcontext() if timer is None else timer("features"):
            # the voxel means of the points, already in the first column block
            grid_rows, nearest = backbone.voxel_features(
                points, band.intensity(), grid, reduced[:, :3]
            )
            columns.append(pca.transform(grid_rows))
        if nearest.shape[1] >= config.num_neighbors:
            neighbours = nearest[:, : config.num_neighbors]
    return VoxelCentres(
        points=reduced[:, :3],
        times=reduced[:, 3],
        features=columns[1] if pca is not None else None,
        dropped=dropped,
        deskew=policy != "off",
        neighbours=neighbours,
    )


def deskew_centres(
    centres: VoxelCentres,
    velocity: np.ndarray | None,
    frame_dt: float = 0.1,
) -> np.ndarray:
    """The centres (M, 3) moved to the scan's reference time with ``velocity`` (se(3) per
    ``frame_dt``; None: as measured), padded to their own size bucket on the device."""
    if not centres.deskew or velocity is None:
        return centres.points
    return deskew(centres.points, centres.times, velocity, frame_dt)


def preprocess_scan(
    scan: np.ndarray,
    times: np.ndarray | None,
    config: PreprocessConfig,
    *,
    velocity: np.ndarray | None = None,
    frame_dt: float = 0.1,
    pca: FeaturePCA | None = None,
    features: np.ndarray | None = None,
    backbone: GridFeatures | None = None,
    source: str | None = None,
) -> tuple[np.ndarray, np.ndarray | None, int]:
    """One raw scan (N, 3+) -> its voxel centres (M, 3) float64, deskewed with ``velocity``
    (se(3) per ``frame_dt``; None: not deskewed), their PCA features (M, 6) when ``pca`` is
    given (from the backbone's ``features`` (N, D), or from ``backbone`` on the voxel grid,
    :func:`voxel_centres`), and the number of NaN / inf points
    dropped: :func:`voxel_centres`, then :func:`deskew_centres`.

    ``times`` (N,) per-point times in any convention (normalised by :func:`normalise_times`),
    or None; ``config.deskew`` says whether they, the azimuth or nothing deskews (``auto``:
    the times when given, else the azimuth; see :func:`resolve_deskew`). Raises InputError
    for scans without points in range and for features of the wrong shape.
    """
    centres = voxel_centres(
        scan, times, config, pca=pca, features=features, backbone=backbone, source=source
    )
    points = deskew_centres(centres, velocity, frame_dt)
    return points, centres.features, centres.dropped
