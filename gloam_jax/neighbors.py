"""k-d tree neighbour sets on the host, returned as fixed-shape index arrays for JAX.

The tree (scipy's cKDTree) is built once per cloud; queries return ``(N, K)`` int32 indices
and a boolean mask (False where a neighbour is farther than ``max_distance`` or absent), so
everything downstream works on static shapes and chooses among the candidates in JAX.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from gloam_jax.errors import InputError


class KdTree:
    """Nearest-neighbour queries over a fixed (M, 3) point set."""

    def __init__(self, points: np.ndarray, source: str | None = None) -> None:
        self.points = np.ascontiguousarray(points[:, :3], dtype=np.float64)
        self.source = source
        self.tree = cKDTree(self.points, leafsize=32, balanced_tree=False, compact_nodes=False)

    def __len__(self) -> int:
        return len(self.points)

    def query(
        self, queries: np.ndarray, k: int, max_distance: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """K nearest points of each query: ((N, k) int32 indices, (N, k) bool valid mask)."""
        if k > len(self):
            raise InputError(
                self.source, f"too few points for {k} neighbours: the cloud has {len(self)}"
            )
        dist, idx = self.tree.query(
            np.asarray(queries[:, :3], dtype=np.float64),
            k=k,
            distance_upper_bound=max_distance,
            workers=-1,
        )
        dist, idx = dist.reshape(len(queries), k), idx.reshape(len(queries), k)
        valid = np.isfinite(dist)
        return np.where(valid, idx, 0).astype(np.int32), valid
