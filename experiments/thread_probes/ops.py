"""Isolated costs of a gicp frame's operations at frame N of val 403 d0 (single thread caller)."""

import statistics
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import gloam_jax.pointcloud as pc
from gloam_jax import geometry as geo
from gloam_jax import gicp, io
from gloam_jax import registration as reg
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset
from gloam_jax.neighbors import KdTree
from gloam_jax.pipeline import open_odometry
from gloam_jax.preprocess import deskew_centres

seq = io.KittiSequence("data/long", "403")
config = load_config(Path("gloam_jax/configs/gicp.yaml"))
N = int(sys.argv[1]) if len(sys.argv) > 1 else 120
setup = open_odometry(open_dataset(seq.root, seq.sequence), config, range(N + 1), None)
odo = setup.odometry
for i in range(N):
    odo.register_frame(seq.scan(i), seq.point_times(i), 0.1)


def t(f, n=15):
    r = []
    for _ in range(n):
        s = time.perf_counter()
        f()
        r.append(time.perf_counter() - s)
    return 1e3 * statistics.median(r)


scan, times = seq.scan(N), seq.point_times(N)
print("raw points", len(scan))
print("voxel_centres ms", t(lambda: odo.voxel_centres(scan, times)))
c = odo.voxel_centres(scan, times)
v = odo._velocity(0.1)
print("deskew ms", t(lambda: deskew_centres(c, v, 0.1)))
pts = deskew_centres(c, v, 0.1)
print("points", len(pts), "bucket", pc.bucket_size(len(pts)))
print("tree build ms", t(lambda: KdTree(pts)))
tree = KdTree(pts)
print("self knn k=10 ms", t(lambda: tree.query(pts, 10)))
size = pc.bucket_size(len(pts))
print("build_cloud ms", t(lambda: reg.build_cloud(pts, 10, "plane", None, size)))
cloud = reg.build_cloud(pts, 10, "plane", None, size)
target = odo.map.cloud
print("map points", len(target.points), "map size", odo.map.size)
T = odo._predict(0.1)
moved = pts @ T[:3, :3].T + T[:3, 3]
print("map query k=1 d=1 ms", t(lambda: target.tree.query(moved, 1, 1.0)))
print("map tree build ms", t(lambda: KdTree(target.points), 5))
src, tgt = cloud.padded(size), target.padded(odo.map.size)
hits = target.tree.query(moved, 1, 1.0)
rows = hits[0] if target.rows is None else target.rows[hits[0]]
cand, valid = (jnp.asarray(pc.pad(x, size)[0]) for x in (rows, hits[1]))
max_d2 = jnp.asarray(1.0, dtype=geo.real_dtype())


def rnd():
    _, xi, system = gicp.solve_round(
        jnp.asarray(T, dtype=geo.real_dtype()), src, tgt, cand, valid, max_d2, 2, "unrolled"
    )
    np.asarray(xi)
    [np.asarray(x) for x in system]


print("solve_round ms", t(rnd))
print(
    "align_prepared ms",
    t(lambda: reg.align_prepared(target, cloud, T, config.gicp, (size, odo.map.size)), 7),
)
r = reg.align_prepared(target, cloud, T, config.gicp, (size, odo.map.size))
print("iterations", r.iterations, "queries", r.queries)
rows_, w = reg.constraint_rows(target, cloud, T, 1.0)
print(
    "constraint_rows ms",
    t(lambda: reg.constraint_rows(target, cloud, T, 1.0, (hits[0][:, 0], hits[1][:, 0]))),
)
print("conditioning ms", t(lambda: reg.conditioning(rows_, w, 10.0, 0.004, 3.0)))
np.savez("/tmp/thread_probes_mapscan.npz", map=target.points, scan=moved)
