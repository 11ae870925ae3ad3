"""pykdtree's build and query times by leaf size and precision on the map and scan that
ops.py saved (run it first): the local map's tree (k = 1 within 1 m) and the scan's own
(k = 10).

    OMP_NUM_THREADS=2 python experiments/thread_probes/leaf.py
"""

import statistics
import time

import numpy as np
from pykdtree.kdtree import KDTree

saved = np.load("/tmp/thread_probes_mapscan.npz")


def ms(f, n=9):
    runs = []
    for _ in range(n):
        start = time.perf_counter()
        f()
        runs.append(time.perf_counter() - start)
    return 1e3 * statistics.median(runs)


def row(dtype, leaf):
    m, s = saved["map"].astype(dtype), saved["scan"].astype(dtype)
    tree_map, tree_scan = KDTree(m, leafsize=leaf), KDTree(s, leafsize=leaf)
    return (
        f"{np.dtype(dtype).name} {leaf} map build {ms(lambda: KDTree(m, leafsize=leaf)):.2f} "
        f"map q1 {ms(lambda: tree_map.query(s, k=1, distance_upper_bound=1.0)):.2f} "
        f"scan build {ms(lambda: KDTree(s, leafsize=leaf)):.2f} "
        f"scan q10 {ms(lambda: tree_scan.query(s, k=10)):.2f}"
    )


for dtype in (np.float64, np.float32):
    for leaf in (16, 32, 64, 128):
        print(row(dtype, leaf))
