"""scipy's cKDTree against pykdtree on val 403's local map (20 scans at 0.5 m) and scan 150:
build and query times (ms) and whether the neighbours agree.

    OMP_NUM_THREADS=2 python experiments/pykdtree/probe_map_queries.py
"""

import time

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from gloam_jax import pointcloud as pc

poses = np.loadtxt("data/long/poses/403.txt").reshape(-1, 3, 4)


def load(i):
    s = np.fromfile(f"data/long/sequences/403/velodyne/{i:06d}.bin", np.float32)
    s = s.reshape(-1, 4)[:, :3].astype(np.float64)
    r = np.linalg.norm(s, axis=1)
    return pc.voxel_downsample(s[(r > 3) & (r < 100)], 0.5)


# Camera-frame poses applied to LiDAR points: a map for timing, not a registered one.
world = [load(i) @ poses[i][:, :3].T + poses[i][:, 3] for i in range(130, 151)]
local_map, src = np.concatenate(world[:20]), world[20]
print("map", len(local_map), "scan", len(src))


def tm(f, n=3):
    f()
    t = time.perf_counter()
    for _ in range(n):
        r = f()
    return (time.perf_counter() - t) / n * 1e3, r


tb, tc = tm(lambda: cKDTree(local_map, leafsize=32, balanced_tree=False, compact_nodes=False))
tpb, tp = tm(lambda: KDTree(local_map, leafsize=32))
print(f"map build: cKDTree {tb:.1f}, pykdtree {tpb:.1f}")
for k in (1, 5, 10):
    a, (d1, i1) = tm(lambda k=k: tc.query(src, k=k, distance_upper_bound=1.0, workers=-1))
    b, (d2, i2) = tm(lambda k=k: tp.query(src, k=k, distance_upper_bound=1.0))
    print(f"map query k={k}: cKDTree {a:.1f}, pykdtree {b:.1f}, same {(i1 == i2).mean()}")
a, (_, i1) = tm(lambda: cKDTree(src, leafsize=32, balanced_tree=False).query(src, k=10, workers=-1))
b, (_, i2) = tm(lambda: KDTree(src, leafsize=32).query(src, k=10))
same = (i1 == i2).mean()
print(f"scan's own k=10, build and query: cKDTree {a:.1f}, pykdtree {b:.1f}, same {same}")
