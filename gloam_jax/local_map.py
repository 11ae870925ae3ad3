"""The odometry's local map: the last keyframes in the world frame, merged into one prepared
cloud on a worker thread (:class:`LocalMap`), every keyframe's points or one keyframe's per
voxel (``map_resolution``)."""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

import jax
import numpy as np

from gloam_jax import pointcloud as pc
from gloam_jax.gicp import Cloud
from gloam_jax.neighbors import KdTree
from gloam_jax.registration import PreparedCloud, device_cloud


class LocalMap:
    """The last keyframes, in the world frame, merged into one prepared cloud.

    Merging (k-d tree, padded device arrays) runs on a worker thread: the next frame's
    preprocessing is mostly single-threaded NumPy, so the tree build overlaps it on another
    core instead of adding to the frame's time (the k-d tree is built without the GIL). The
    keyframes' rows are kept end to end (:class:`_Rows`), so a keyframe copies its own rows.
    On the device each keyframe has a slot of the keyframes' padded size, so a new keyframe
    rewrites its own slot instead of the whole map being copied again (5.5-8.8 ms for 245,760
    rows, experiments/map_slots).

    With a ``resolution`` (m), the map keeps one keyframe's points per voxel of that size, the
    newest keyframe's that has any there: the union of overlapping keyframes holds each
    surface once instead of once per keyframe, so the merge is incremental (drop the rows a
    new keyframe covers or that left the window) and the tree several times smaller. Its rows
    stay in keyframe order, so a map rebuilt from the same keyframes (a resume) is the same.
    """

    def __init__(self, max_keyframes: int, buckets: pc.StickyBuckets, resolution: float = 0.0):
        self.max_keyframes = max_keyframes
        self.buckets = buckets
        self.resolution = resolution
        # each keyframe's PreparedCloud columns (points, covs, features, normals, planarity),
        # in the world frame; features None for methods without learned association
        self.keyframes: list[dict[str, np.ndarray | None]] = []
        self.last_pose: np.ndarray | None = None
        self._merged: PreparedCloud | None = None
        # the merge in progress: a PreparedCloud, or with a resolution (rows, PreparedCloud),
        # rows being the map's columns with each row's voxel key and keyframe number
        self._pending: Future | None = None
        self._added = 0  # keyframes added since the map was (re)started: the next one's number
        self._rows = _Rows()  # without a resolution: the keyframes' columns, end to end
        self._merged_size = 0  # the padded size of the last merge's device arrays
        # One worker: merges run in the order of their keyframes.
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="local-map")

    def add(self, cloud: PreparedCloud, T_world_lidar: np.ndarray) -> None:
        R, t = T_world_lidar[:3, :3], T_world_lidar[:3, 3]
        keyframe = {
            "points": cloud.points @ R.T + t,
            "covs": R @ cloud.covs @ R.T,
            "features": cloud.features,
            "normals": cloud.normals @ R.T,
            "planarity": cloud.planarity,
        }
        self.keyframes = [*self.keyframes, keyframe][-self.max_keyframes :]
        self.last_pose = T_world_lidar
        if self.resolution:
            self._fold(keyframe)
            return
        self._rows.append(keyframe)
        self._rows.keep(self.max_keyframes)
        self._added += 1
        self._merge(keyframe)

    def _fold(self, keyframe: dict) -> None:
        """Queue the voxel map's merge of the next keyframe after the one pending."""
        self._pending = self._worker.submit(
            _voxel_merge, self._pending, keyframe, self._added, self.max_keyframes,
            self.resolution,
        )  # fmt: skip
        self._added += 1

    def restore(self, keyframes: list[dict], last_pose: np.ndarray) -> None:
        """The map of ``keyframes`` (world-frame columns, oldest first; the last ``max_keyframes``
        kept), the newest taken at ``last_pose`` (4, 4)."""
        self.keyframes = keyframes[-self.max_keyframes :]
        self.last_pose = last_pose
        if self.resolution:
            self._pending, self._added = None, 0
            for keyframe in self.keyframes:
                self._fold(keyframe)
            return
        self._rows = _Rows()
        for keyframe in self.keyframes:
            self._rows.append(keyframe)
        self._added = len(self.keyframes)
        self._merge()

    def _merge(self, new: dict | None = None) -> None:
        """Queue the merge of the keyframes' rows (k-d tree, padded device arrays); ``new``:
        the keyframe just added, written into its slot of the last merge's device arrays where
        those have the map's current size (None: all slots written). Keyframe number j has
        slot ``j mod max_keyframes``, so the window's keyframes hold distinct slots."""
        # A slot holds the largest keyframe seen (with headroom; never shrinking), so the map's
        # shape changes only when a larger one comes. Sized on this thread, not the worker's:
        # StickyBuckets is not thread-safe.
        self.buckets("scan", max(len(k["points"]) for k in self.keyframes))
        slot_size, size = self.buckets.floor("scan"), self.size
        previous = self._pending if self._pending is not None else self._merged
        if new is None or previous is None or size != self._merged_size:
            previous = new = None
        self._merged_size = size
        first = self._added - len(self.keyframes)  # the oldest keyframe's number
        slots = [j % self.max_keyframes for j in range(first, self._added)]
        lengths = [len(k["points"]) for k in self.keyframes]
        self._pending = self._worker.submit(
            _merge, self._rows.view(), slots, lengths, slot_size, size, previous, new
        )

    @property
    def size(self) -> int:
        """Rows of the padded map (0 before the first keyframe). Without a resolution: its
        capacity at the slots' size (the sticky "scan" bucket of the keyframes), which it
        follows as it grows; with one: the "map" bucket of the merged rows. Either way the
        solver compiles once per pair of source and map buckets, and a restored map is padded
        as the run that saved it had it (bit-exact resumes)."""
        if not self.keyframes:
            return 0
        if self.resolution:
            return self.buckets("map", len(self.cloud.points))
        return self.max_keyframes * self.buckets.floor("scan")

    def clear(self) -> None:
        """No keyframes (a merge still running is left to finish unread)."""
        self.keyframes, self.last_pose = [], None
        self._merged = self._pending = None
        self._added = self._merged_size = 0
        self._rows = _Rows()

    @property
    def cloud(self) -> PreparedCloud | None:
        """The merged map (waits for its merge), or None before the first keyframe."""
        if self._pending is not None:
            merged = self._pending.result()
            self._merged = merged[1] if self.resolution else merged
            if not self.resolution:
                self._pending = None
        return self._merged


class _Rows:
    """Keyframes' columns end to end, oldest first, as views of one buffer per column: a
    keyframe joins by a copy of its own rows and leaves by moving the start, where
    concatenating every keyframe again copied the whole map at each keyframe (9-11 ms for
    340,000 rows, experiments/map_rows). A full buffer is replaced by a new one, never
    overwritten, so the views an earlier merge holds (the map in use, its k-d tree) stay
    valid, and the rows are the concatenation's, bit for bit."""

    def __init__(self) -> None:
        self._buffers: dict[str, np.ndarray | None] = {}
        self._start = self._end = 0
        self._lengths: deque[int] = deque()

    def append(self, keyframe: dict[str, np.ndarray | None]) -> None:
        n = len(keyframe["points"])
        if not self._buffers or self._end + n > len(self._buffers["points"]):
            live = self._end - self._start
            grown = {}
            for name, column in keyframe.items():
                if column is None:
                    grown[name] = None
                    continue
                grown[name] = np.empty((2 * (live + n), *column.shape[1:]), column.dtype)
                if live:
                    grown[name][:live] = self._buffers[name][self._start : self._end]
            self._buffers, self._start, self._end = grown, 0, live
        for name, column in keyframe.items():
            if column is not None:
                self._buffers[name][self._end : self._end + n] = column
        self._end += n
        self._lengths.append(n)

    def keep(self, count: int) -> None:
        """Drop the oldest keyframes beyond the newest ``count``."""
        while len(self._lengths) > count:
            self._start += self._lengths.popleft()

    def view(self) -> dict[str, np.ndarray | None]:
        """The columns of the keyframes kept, oldest first (views, not copies)."""
        return {
            name: None if buffer is None else buffer[self._start : self._end]
            for name, buffer in self._buffers.items()
        }


def _merge(
    merged: dict[str, np.ndarray | None],
    slots: list[int],
    lengths: list[int],
    slot_size: int,
    size: int,
    previous: Future | PreparedCloud | None,
    new: dict | None,
) -> PreparedCloud:
    """The prepared cloud of the world-frame keyframes' columns ``merged`` (of ``lengths``
    rows each, oldest first), each keyframe at its slot of ``slot_size`` rows of device arrays
    ``size`` rows long (a scan bucket grown since lays them out again on first use). With a
    ``previous`` merge of that size, they are its arrays with the slot of the ``new`` (newest)
    keyframe written; else all are written."""
    starts = [s * slot_size for s in slots]
    rows = np.concatenate([np.arange(s, s + n, dtype=np.int32)
                           for s, n in zip(starts, lengths, strict=True)])  # fmt: skip
    cloud = PreparedCloud(tree=KdTree(merged["points"], "local map"), rows=rows, **merged)
    if previous is None:
        cloud.padded(size)
        return cloud
    before = (previous.result() if isinstance(previous, Future) else previous).padded(size)
    block = device_cloud(new["points"], new["covs"], new["features"], slot_size)
    cloud.place(size, _write(before, block, starts[-1]))
    return cloud


@jax.jit
def _write(device: Cloud, block: Cloud, start: int) -> Cloud:
    """``device`` with the rows from ``start`` on replaced by ``block``'s (one compilation per
    pair of sizes; ``start`` is traced)."""
    return Cloud(*(jax.lax.dynamic_update_slice_in_dim(a, b, start, 0)
                   for a, b in zip(device, block, strict=True)))  # fmt: skip


def _voxel_merge(
    previous: Future | None, keyframe: dict, number: int, max_keyframes: int, resolution: float
) -> tuple[dict, PreparedCloud]:
    """The voxel map's rows after keyframe ``number`` (see :class:`LocalMap`): the ``previous``
    merge's rows (None: none) still in the window and in no voxel the keyframe has points in,
    then the keyframe's; and their prepared cloud."""
    keys = pc.voxel_keys(keyframe["points"], resolution)
    new = {**keyframe, "key": keys, "keyframe": np.full(len(keys), number)}
    if previous is None:
        rows = new
    else:
        old = previous.result()[0]
        keep = (old["keyframe"] > number - max_keyframes) & ~np.isin(old["key"], keys)
        rows = {k: None if v is None else np.concatenate([old[k][keep], v]) for k, v in new.items()}
    columns = {k: v for k, v in rows.items() if k not in ("key", "keyframe")}
    return rows, PreparedCloud(tree=KdTree(rows["points"], "local map"), **columns)
