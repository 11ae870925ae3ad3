"""k-d tree neighbour sets on the host, returned as fixed-shape index arrays for JAX.

The tree (pykdtree's: the same exact neighbours as scipy's cKDTree, built and queried 1.6-1.9
times faster, experiments/pykdtree) is built once per cloud; queries return ``(N, K)`` int32
indices and a boolean mask (False where a neighbour is farther than ``max_distance`` or
absent), so everything downstream works on static shapes and chooses among the candidates in
JAX. It releases the GIL and runs on OpenMP's threads (``OMP_NUM_THREADS``).
"""

from __future__ import annotations

import os

import numpy as np

# OpenMP's threads otherwise spin for a while after each query, waiting for the next; on two
# cores shared with the prefetch thread, the map's worker and XLA that spin was a fifth of the
# odometry's CPU time (experiments/pykdtree). Read when pykdtree's OpenMP library loads, so set
# before its import; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pykdtree.kdtree import KDTree  # noqa: E402

from gloam_jax.errors import InputError  # noqa: E402


class KdTree:
    """Nearest-neighbour queries over a fixed (M, 3) point set."""

    def __init__(self, points: np.ndarray, source: str | None = None) -> None:
        self.points = np.ascontiguousarray(points[:, :3], dtype=np.float64)
        self.source = source
        self.tree = KDTree(self.points, leafsize=32)

    def __len__(self) -> int:
        return len(self.points)

    def query(
        self, queries: np.ndarray, k: int, max_distance: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """K nearest points of each query: ((N, k) int32 indices, (N, k) bool valid mask)."""
        dist, idx = self.nearest(queries, k, max_distance)
        valid = np.isfinite(dist)
        return np.where(valid, idx, 0).astype(np.int32), valid

    def nearest(
        self, queries: np.ndarray, k: int, max_distance: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """K nearest points of each query, closest first: ((N, k) distances, inf where none
        within ``max_distance``, and (N, k) indices, ``len(self)`` there)."""
        if k > len(self):
            raise InputError(
                self.source, f"too few points for {k} neighbours: the cloud has {len(self)}"
            )
        dist, idx = self.tree.query(
            np.ascontiguousarray(queries[:, :3], dtype=np.float64),
            k=k,
            distance_upper_bound=None if np.isinf(max_distance) else max_distance,
        )
        return dist.reshape(len(queries), k), idx.reshape(len(queries), k)
