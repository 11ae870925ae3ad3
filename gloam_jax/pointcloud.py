"""Point-cloud preprocessing on the host: validity, range crop, voxel grid, padding buckets.

Everything here is numpy: it runs once per scan, before the jitted stages, and decides the
static shapes those stages see. Padding to a few bucket sizes (with a mask) keeps the number
of distinct shapes, and so of compilations, small.
"""

from __future__ import annotations

import numpy as np

from gloam_jax.errors import InputError

# Padded sizes: powers of two from 1 Ki to 256 Ki points.
BUCKETS = tuple(1 << k for k in range(10, 19))


def drop_invalid(points: np.ndarray, source: str | None = None) -> tuple[np.ndarray, int]:
    """Remove rows with NaN or inf: (N, D) -> ((M, D), number removed). Empty input is an error."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(source, f"expected an (N, 3+) point array, got shape {points.shape}")
    if len(points) == 0:
        raise InputError(source, "empty scan (0 points)")
    finite = np.all(np.isfinite(points[:, :3]), axis=1)
    kept = points[finite]
    if len(kept) == 0:
        raise InputError(source, f"all {len(points)} points are NaN or infinite")
    return kept, int(len(points) - len(kept))


def crop_range(points: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    """Keep points whose distance from the sensor lies in [min_range, max_range]: (N, D)."""
    r = np.linalg.norm(points[:, :3], axis=1)
    return points[(r >= min_range) & (r <= max_range)]


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Mean of the rows (all columns) falling in each voxel of ``voxel_size`` metres: (N, D).

    Output order follows the voxels' first occurrence in the input, so it is deterministic.
    """
    if voxel_size <= 0:
        return points
    keys = np.floor(points[:, :3] / voxel_size).astype(np.int64)
    # 21 bits per axis: +-1e6 voxels, i.e. +-100 km at 0.1 m.
    keys = keys + (1 << 20)
    flat = (keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2]
    _, first, inverse, counts = np.unique(
        flat, return_index=True, return_inverse=True, return_counts=True
    )
    order = np.argsort(first)  # voxel ids in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    inverse = rank[inverse.ravel()]
    sums = [np.bincount(inverse, weights=col, minlength=len(first)) for col in points.T]
    return (np.stack(sums, axis=1) / counts[order][:, None]).astype(points.dtype)


def bucket_size(n: int, buckets: tuple[int, ...] = BUCKETS) -> int:
    """Smallest bucket holding n points (the largest power of two above n past the last)."""
    for b in buckets:
        if n <= b:
            return b
    return 1 << int(np.ceil(np.log2(n)))


class StickyBuckets:
    """Bucket sizes that never shrink, per role ("source", "target", ...): once a stream of
    scans has warmed up, shapes, and so compilations, stop changing."""

    def __init__(self) -> None:
        self._floor: dict[str, int] = {}

    def __call__(self, role: str, n: int) -> int:
        size = max(bucket_size(n), self._floor.get(role, 0))
        self._floor[role] = size
        return size


def pad(array: np.ndarray, size: int, fill: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pad the leading axis to ``size``: (N, ...) -> ((size, ...), mask (size,) True for real)."""
    n = len(array)
    if n > size:
        raise ValueError(f"cannot pad {n} rows into {size}")
    out = np.full((size, *array.shape[1:]), fill, dtype=array.dtype)
    out[:n] = array
    mask = np.zeros(size, dtype=bool)
    mask[:n] = True
    return out, mask
