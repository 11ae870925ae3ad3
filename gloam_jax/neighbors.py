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

    def _check(self, k: int) -> None:
        if k > len(self):
            raise InputError(
                self.source, f"too few points for {k} neighbours: the cloud has {len(self)}"
            )

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
        self._check(k)
        dist, idx = self.tree.query(
            np.ascontiguousarray(queries[:, :3], dtype=np.float64),
            k=k,
            distance_upper_bound=None if np.isinf(max_distance) else max_distance,
        )
        return dist.reshape(len(queries), k), idx.reshape(len(queries), k)


# A part of a PartedTree: a tree and the row of the whole set that its row 0 is (negative:
# its first rows are not in the set).
Part = tuple[KdTree, int]


class PartedTree(KdTree):
    """The same queries over (M, 3) ``points`` answered by trees over parts of them, so that
    a set that changes a part at a time (the local map's keyframes) needs no new tree of the
    whole before it is queried. ``parts()`` gives, at each query, trees whose rows, shifted by
    their offsets, cover rows 0..M-1 once; rows shifted below 0 are not in the set. The
    answers are one tree's over ``points`` (up to the order of equally distant points)."""

    def __init__(self, points: np.ndarray, parts, source: str | None = None) -> None:
        self.points, self.source, self._parts = points, source, parts

    def nearest(
        self, queries: np.ndarray, k: int, max_distance: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        self._check(k)
        found = [_part_nearest(tree, offset, queries, k, max_distance)
                 for tree, offset in self._parts()]  # fmt: skip
        dist = np.concatenate([d for d, _ in found], axis=1)
        idx = np.concatenate([i for _, i in found], axis=1)
        if dist.shape[1] > k:  # the k nearest of the parts' k nearest
            order = np.argsort(dist, axis=1, kind="stable")[:, :k]
            dist, idx = (np.take_along_axis(x, order, axis=1) for x in (dist, idx))
        return dist, np.where(np.isfinite(dist), idx, len(self))


def _part_nearest(
    tree: KdTree, offset: int, queries: np.ndarray, k: int, max_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """A part's k nearest in the set's rows ((N, k) distances, inf where none, and rows). Where
    rows outside the set were among a point's nearest, that point is asked again for more,
    until it has k in the set or the tree has none left within ``max_distance``."""
    wanted = min(k, len(tree))
    dist, idx = _shifted(tree, offset, queries, wanted, max_distance)
    if offset < 0:
        short = np.flatnonzero(((idx < 0) & np.isfinite(dist)).any(1))
        more = wanted
        while len(short) and more < len(tree):
            more = min(2 * more, len(tree))
            d, i = _shifted(tree, offset, queries[short], more, max_distance)
            exhausted = ~np.isfinite(d[:, -1])  # every row within the distance returned
            d = np.where(i < 0, np.inf, d)
            order = np.argsort(d, axis=1, kind="stable")[:, :wanted]
            dist[short] = np.take_along_axis(d, order, axis=1)
            idx[short] = np.take_along_axis(i, order, axis=1)
            short = short[(np.isfinite(dist[short]).sum(1) < wanted) & ~exhausted]
        dist = np.where(idx < 0, np.inf, dist)
    if wanted < k:  # a part smaller than k
        pad = np.full((len(queries), k - wanted), np.inf)
        dist = np.concatenate([dist, pad], axis=1)
        idx = np.concatenate([idx, np.zeros(pad.shape, idx.dtype)], axis=1)
    return dist, idx


def _shifted(
    tree: KdTree, offset: int, queries: np.ndarray, k: int, max_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """The tree's k nearest, its rows shifted by ``offset`` (int64)."""
    dist, idx = tree.nearest(queries, k, max_distance)
    return dist, idx.astype(np.int64) + offset
