"""Point-cloud preprocessing on the host: validity, range crop, voxel grid, padding buckets.

Everything here is numpy: it runs once per scan, before the jitted stages, and decides the
static shapes those stages see. Padding to a few bucket sizes (with a mask) keeps the number
of distinct shapes, and so of compilations, small.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from gloam_jax.errors import InputError

# Padded sizes from 1 Ki to 448 Ki points, four per octave (1, 1.25, 1.5, 1.75 times a power
# of two): at most 25 % padding, where powers of two alone waste up to half the work.
BUCKETS = tuple(m << k for k in range(8, 17) for m in (4, 5, 6, 7))
# Coordinates beyond this (m) are not measurements (float32 resolution there is metres, and
# UTM-sized coordinates stay below 1e7): such points are dropped as invalid, like NaN.
MAX_COORDINATE = 1e8


def _valid_rows(xyz: np.ndarray) -> np.ndarray:
    """Rows of (N, 3) that are finite and within MAX_COORDINATE on every axis: (N,) bool."""
    with np.errstate(invalid="ignore"):
        return np.all(np.abs(xyz) <= MAX_COORDINATE, axis=1)  # NaN compares False


def check_points(points: np.ndarray, source: str | None = None) -> np.ndarray:
    """``points`` as an array, or an InputError naming ``source`` unless it is (N, 3+), N > 0."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(source, f"expected an (N, 3+) point array, got shape {points.shape}")
    if len(points) == 0:
        raise InputError(source, "empty scan (0 points)")
    return points


def drop_invalid(points: np.ndarray, source: str | None = None) -> tuple[np.ndarray, int]:
    """Remove rows with NaN, inf or coordinates beyond MAX_COORDINATE: (N, D) -> ((M, D),
    number removed). Empty input is an error."""
    points = check_points(points, source)
    kept = points[_valid_rows(points[:, :3])]
    if len(kept) == 0:
        raise InputError(
            source, f"all {len(points)} points are NaN, infinite or beyond {MAX_COORDINATE:g} m"
        )
    return kept, int(len(points) - len(kept))


def range_mask(
    points: np.ndarray, min_range: float, max_range: float, source: str | None = None
) -> tuple[np.ndarray, int]:
    """Points of an (N, 3+) scan whose distance from the sensor lies in [min_range, max_range]:
    (mask (N,), number of invalid points (see :func:`drop_invalid`), which the mask also
    drops). One pass over the scan, for the per-frame path; bad shapes and empty or all-invalid
    scans are errors."""
    points = check_points(points, source)
    xyz = points[:, :3]
    # In float64: float32 squares of valid coordinates (up to 1e8) would overflow to inf.
    r2 = np.einsum("ij,ij->i", xyz, xyz, dtype=np.float64)
    # Within MAX_COORDINATE of the origin every axis is too: only the rest (NaN, inf, far)
    # needs the per-axis test, which costs more than the squared range itself.
    valid = r2 <= MAX_COORDINATE * MAX_COORDINATE
    unsure = np.flatnonzero(~valid)
    valid[unsure] = _valid_rows(xyz[unsure])
    invalid = int(np.count_nonzero(~valid))
    if invalid == len(points):
        raise InputError(
            source, f"all {len(points)} points are NaN, infinite or beyond {MAX_COORDINATE:g} m"
        )
    return valid & (r2 >= min_range * min_range) & (r2 <= max_range * max_range), invalid


@dataclass(frozen=True)
class RangeBand:
    """The rows of a raw scan (N, 3+) within a range band: ``keep`` (N,) bool, their xyz
    (M, 3) float64 and the number of invalid rows (:func:`range_mask`)."""

    scan: np.ndarray
    keep: np.ndarray
    xyz: np.ndarray
    invalid: int

    def intensity(self) -> np.ndarray | None:
        """The kept rows' fourth column (M,), None where the scan has three."""
        return np.compress(self.keep, self.scan[:, 3]) if self.scan.shape[1] > 3 else None


def range_band(
    scan: np.ndarray, min_range: float, max_range: float, source: str | None = None
) -> RangeBand:
    """The points of a raw scan (N, 3+) between ``min_range`` and ``max_range`` m, as the
    preprocessing and the grid backbones select them; errors as :func:`range_mask`."""
    scan = np.asarray(scan)
    keep, invalid = range_mask(scan, min_range, max_range, source)
    # np.compress: the rows of scan[keep, :3], selected faster than a boolean index does.
    xyz = np.compress(keep, scan[:, :3], axis=0).astype(np.float64)
    return RangeBand(scan, keep, xyz, invalid)


def crop_range(points: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    """Keep points whose distance from the sensor lies in [min_range, max_range]: (N, D)."""
    return points[range_mask(points, min_range, max_range)[0]]


def _argsort_keys(key: np.ndarray) -> np.ndarray:
    """Stable argsort (N,) of non-negative integer keys below 2**32: two passes of NumPy's
    radix sort of 16-bit keys, low half first (a scan's sort in 1.7 ms where the default
    argsort of the same keys as uint32 takes 5.5, experiments/voxel_sort)."""
    order = np.argsort((key & 0xFFFF).astype(np.uint16), kind="stable")
    return order[np.argsort((key[order] >> 16).astype(np.uint16), kind="stable")]


def _voxel_groups(
    points: np.ndarray, voxel_size: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points grouped by voxel: an order (N,) that sorts them by voxel key (x, then y, then
    z), where each voxel's run starts (M,), and the points per voxel (M,)."""
    # Per-axis 1-D arrays: reductions along the short axis of an (N, 3) array are slow.
    cells = [np.floor(points[:, i] * (1.0 / voxel_size)) for i in range(3)]
    if not all(np.isfinite(c).all() for c in cells):
        raise ValueError("cannot voxelise NaN or infinite points")
    lows = [c.min() for c in cells]
    dims = [int(c.max() - lo) + 1 for c, lo in zip(cells, lows, strict=True)]
    if dims[0] * dims[1] * dims[2] >= 1 << 62:
        raise InputError(
            None, f"points spanning {dims} voxels of {voxel_size} m are too far apart to voxelise"
        )
    x, y, z = ((c - lo).astype(np.int64) for c, lo in zip(cells, lows, strict=True))
    # One integer per voxel in mixed radix keeps the (x, y, z) order.
    key = (x * dims[1] + y) * dims[2] + z
    order = _argsort_keys(key) if dims[0] * dims[1] * dims[2] < 1 << 32 else np.argsort(key)
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    return order, starts, counts


@dataclass(frozen=True)
class VoxelGrid:
    """Points grouped by voxel (:func:`voxel_grid`), voxels in sorted key order: ``order``
    (N,) sorts the points by voxel, ``starts`` (M,) is where each voxel's run begins in it,
    ``counts`` (M,) its points."""

    order: np.ndarray
    starts: np.ndarray
    counts: np.ndarray

    @property
    def inverse(self) -> np.ndarray:
        """Each point's voxel (N,) int64."""
        inverse = np.empty(len(self.order), np.int64)
        inverse[self.order] = np.repeat(np.arange(len(self.counts)), self.counts)
        return inverse

    def means(self, a: np.ndarray) -> np.ndarray:
        """Per-voxel means (M, ...) of a row-aligned array (N, ...), in its dtype."""
        # np.take gathers rows several times faster than a[order] (same values).
        sums = np.add.reduceat(np.take(a, self.order, axis=0), self.starts, axis=0)
        return (sums / self.counts.reshape(-1, *([1] * (a.ndim - 1)))).astype(a.dtype)


def voxel_grid(points: np.ndarray, voxel_size: float) -> VoxelGrid:
    """The voxels of ``voxel_size`` metres (> 0) that ``points`` (N >= 1, 3+) fall in."""
    return VoxelGrid(*_voxel_groups(points, voxel_size))


def voxel_index(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Each point's voxel (N,) and the points per voxel (M,), voxels in sorted key order."""
    grid = voxel_grid(points, voxel_size)
    return grid.inverse, grid.counts


def voxel_means(
    points: np.ndarray, voxel_size: float, columns: Sequence[np.ndarray]
) -> list[np.ndarray]:
    """Per-voxel means of row-aligned arrays (N, D_i), each in its own dtype, the voxels of
    ``voxel_size`` metres taken from ``points`` (N, 3+) in sorted key order: [(M, D_i)].
    A size of 0 (no downsampling) or no points returns the arrays as they are."""
    if voxel_size <= 0 or len(points) == 0:
        return list(columns)
    grid = voxel_grid(points, voxel_size)
    return [grid.means(a) for a in columns]


# Bits per axis of a voxel key (voxel_keys): cells within 2**20 of the origin each way.
KEY_BITS = 21


def voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Each point's voxel of ``voxel_size`` metres as one int64 (N,), on a grid fixed to the
    points' frame, so that keys compare across clouds in that frame (unlike voxel_index's)."""
    cells = np.floor(points[:, :3] * (1.0 / voxel_size)).astype(np.int64)
    half = 1 << (KEY_BITS - 1)
    if len(cells) and np.abs(cells).max() >= half:
        raise ValueError(
            f"points lie more than {half * voxel_size / 1e3:.0f} km from the origin: beyond "
            f"what {voxel_size} m voxel keys cover"
        )
    cells += half
    return (cells[:, 0] << (2 * KEY_BITS)) | (cells[:, 1] << KEY_BITS) | cells[:, 2]


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Mean of the rows (all columns) falling in each voxel of ``voxel_size`` metres: (N, D).

    Output rows follow the voxels' sorted keys, so they are deterministic.
    """
    return voxel_means(points, voxel_size, [np.asarray(points, np.float64)])[0].astype(points.dtype)


def bucket_size(n: int, buckets: tuple[int, ...] = BUCKETS) -> int:
    """Smallest bucket holding n points (the largest power of two above n past the last)."""
    for b in buckets:
        if n <= b:
            return b
    return 1 << int(np.ceil(np.log2(n)))


class StickyBuckets:
    """Bucket sizes per role ("scan", ...) that grow with the inputs and never shrink: a
    larger input moves its role up to a larger bucket (one compilation, the first time), a
    smaller one keeps the size it has, so shapes do not flap between buckets frame to frame.
    The sizes are :data:`BUCKETS`, the same in every run, so JAX's persistent compilation
    cache keeps their programs across runs."""

    def __init__(self) -> None:
        self._floor: dict[str, int] = {}

    def __call__(self, role: str, n: int) -> int:
        """The padded size for ``n`` rows of ``role``, grown to hold them if needed."""
        floor = self._floor.get(role, 0)
        if n > floor:
            # 20 % headroom over the largest seen: scans vary by a few percent, and each
            # growth step costs a compilation.
            floor = self._floor[role] = bucket_size(int(n * 1.2))
        return floor

    def floor(self, role: str) -> int:
        """The current size of ``role`` without growing it; 0 before its first input."""
        return self._floor.get(role, 0)

    def state(self) -> dict[str, int]:
        """The sizes per role (for :meth:`restore`)."""
        return dict(self._floor)

    def restore(self, floors: dict[str, int]) -> None:
        self._floor = dict(floors)


def pad(
    array: np.ndarray,
    size: int,
    fill: float = 0.0,
    dtype: npt.DTypeLike = None,
    rows: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pad the leading axis to ``size``: (N, ...) -> ((size, ...), mask (size,) True for real),
    in ``dtype`` (default: the array's); ``rows`` (N,) places row i at ``rows[i]`` (default:
    at i)."""
    n = len(array)
    end = n if rows is None else (int(rows.max()) + 1 if n else 0)
    if end > size:
        raise ValueError(f"cannot pad {n} rows ending at {end} into {size}")
    place = slice(0, n) if rows is None else rows
    out = np.full((size, *array.shape[1:]), fill, dtype=array.dtype if dtype is None else dtype)
    out[place] = array
    mask = np.zeros(size, dtype=bool)
    mask[place] = True
    return out, mask
