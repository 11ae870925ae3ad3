"""Probe: how many of the local map's points share a voxel, and what the tree costs each way.

Runs `gicp` over the first N frames of val 403 d0 (`probe_map.py data/long N`), then times
the k-d tree build and one k = 1 and k = 5 query of the last scan against the map as it is
(every keyframe's points) and with one point per voxel kept (the newest keyframe's), at 0.5
and 0.25 m.
"""

import sys
import time

import numpy as np
from scipy.spatial import cKDTree

from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset
from gloam_jax.odometry import Odometry


def newest_per_voxel(points: np.ndarray, resolution: float) -> np.ndarray:
    keys = np.floor(points / resolution).astype(np.int64)
    keys -= keys.min(axis=0)
    packed = (keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2]
    _, first = np.unique(packed[::-1], return_index=True)
    return np.sort(len(points) - 1 - first)


def best(f, n=5):
    times = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return 1e3 * min(times)


root, frames = sys.argv[1], int(sys.argv[2])
config = load_config("gicp")
seq = open_dataset(root, "403")
odo = Odometry(config)
for i in range(frames):
    scan, times = seq.frame(i)
    odo.register_frame(scan, times, source=str(i))
map_points = np.concatenate([k["points"] for k in odo.map.keyframes])
query = odo.previous.points @ odo.poses[-1][:3, :3].T + odo.poses[-1][:3, 3]
print(f"keyframes {len(odo.map.keyframes)}, map points {len(map_points)}, scan {len(query)}")
for label, pts in [("all", map_points)] + [
    (f"voxel {r}", map_points[newest_per_voxel(map_points, r)]) for r in (0.5, 0.25)
]:
    tree = cKDTree(pts, leafsize=32, balanced_tree=False, compact_nodes=False)
    build = best(lambda p=pts: cKDTree(p, leafsize=32, balanced_tree=False, compact_nodes=False))
    q1 = best(lambda tree=tree: tree.query(query, k=1, distance_upper_bound=1.0, workers=-1))
    q5 = best(lambda tree=tree: tree.query(query, k=5, distance_upper_bound=1.0, workers=-1))
    print(f"{label}: {len(pts)} points, build {build:.1f} ms, query k1 {q1:.1f} ms, k5 {q5:.1f} ms")
dedup = best(lambda: newest_per_voxel(map_points, 0.5))
print(f"dedup 0.5 m: {dedup:.1f} ms")
