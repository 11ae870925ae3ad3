"""Wall and CPU time of the shipped geometric backbone per scan and of its k = 30 query, with
OpenMP at 1 and 2 threads, and of small_gicp's k-d tree for the same query (issue 42, item 1).

    OMP_NUM_THREADS=1 python experiments/feature_budget/probe_backbone_cpu.py data/long 403 300
    OMP_NUM_THREADS=2 python experiments/feature_budget/probe_backbone_cpu.py data/long 403 300
"""

import os
import resource
import sys
import time

import numpy as np
import small_gicp

from gloam_jax.datasets import open_dataset
from gloam_jax.features.geometric import GeometricBackbone, _voxelize
from gloam_jax.neighbors import KdTree


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(name: str, f, repeats: int = 10) -> None:
    f()
    w0, c0 = time.perf_counter(), cpu()
    for _ in range(repeats):
        f()
    wall, used = (time.perf_counter() - w0) / repeats, (cpu() - c0) / repeats
    print(f"{name}: wall {1e3 * wall:.1f} ms, cpu {1e3 * used:.1f} ms "
          f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')})")  # fmt: skip


root, sequence, frame = sys.argv[1], sys.argv[2], int(sys.argv[3])
scan = open_dataset(root, sequence).frame(frame)[0]
voxels = _voxelize(scan[:, :3].astype(np.float64), 0.25)[0]
tree = KdTree(voxels)
print(f"{len(scan)} points, {len(voxels)} voxels of 0.25 m")
timed("k = 30 query", lambda: tree.nearest(voxels, 30))
timed("backbone", lambda: GeometricBackbone()(scan))
other = small_gicp.KdTree(voxels, num_threads=1)
timed("k = 30 query, small_gicp's tree, 1 thread", lambda: other.batch_knn_search(voxels, 30, 1))
