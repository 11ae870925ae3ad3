"""Main-thread work alone and beside a thread doing other work, in one process: which work
holds Python's GIL (numpy calls on small arrays) and which does not (pykdtree's build and
query, large-array sorts). OMP_NUM_THREADS=1, so each call is one thread.

    python experiments/layered_map/probe_threads.py > experiments/layered_map/probe_threads.txt
"""

import os
import threading
import time

os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np  # noqa: E402
from pykdtree.kdtree import KDTree  # noqa: E402

rng = np.random.default_rng(0)
points = rng.uniform(-50, 50, (225000, 3)) * [1.0, 1.0, 0.05]  # a local map's size
queries = points[rng.integers(0, len(points), 10500)] + rng.normal(0, 0.1, (10500, 3))
tree = KDTree(points, leafsize=32)
small = [rng.normal(size=(100, 3)) for _ in range(50)]
WORK = {
    "query": lambda: tree.query(queries, k=1, distance_upper_bound=1.0),
    "build": lambda: KDTree(points, leafsize=32),
    "numpy-small": lambda: [np.concatenate([s, s]).sum() for s in small * 20],
    "voxel": lambda: np.argsort(np.floor(points[:, 0] * 2).astype(np.int64), kind="stable"),
}


def per_call(work, seconds: float = 3.0) -> float:
    """Milliseconds per call of ``work``, run for ``seconds``."""
    end, calls, start = time.time() + seconds, 0, time.perf_counter()
    while time.time() < end:
        work()
        calls += 1
    return 1e3 * (time.perf_counter() - start) / calls


for main in ("query", "numpy-small", "voxel"):
    alone = per_call(WORK[main])
    for other in ("build", "query", "numpy-small"):
        stop = threading.Event()

        def background(work=WORK[other], stop=stop):
            while not stop.is_set():
                work()

        thread = threading.Thread(target=background)
        thread.start()
        beside = per_call(WORK[main])
        stop.set()
        thread.join()
        print(f"main {main:12s} alone {alone:7.2f} ms, beside {other:12s} {beside:7.2f} ms "
              f"({beside / alone:.2f}x)")  # fmt: skip
