"""Wall vs thread CPU of each k-d tree call inside the frame loop (gicp, val 403, 300 frames)."""

import collections
import os
import sys
import threading
import time

sys.path.insert(0, "scripts")
os.environ.setdefault("OMP_NUM_THREADS", "2")
from pathlib import Path

import bench_odometry as bench
import numpy as np

import gloam_jax.neighbors as nb
from gloam_jax import io
from gloam_jax.config import load_config

rec = collections.defaultdict(list)
orig_near, orig_init = nb.KdTree.nearest, nb.KdTree.__init__


def near(self, q, k, md=np.inf):
    w, c = time.perf_counter(), time.thread_time()
    r = orig_near(self, q, k, md)
    rec[(threading.current_thread().name, "query", len(self), k)].append(
        (time.perf_counter() - w, time.thread_time() - c)
    )
    return r


def init(self, p, s=None):
    w, c = time.perf_counter(), time.thread_time()
    orig_init(self, p, s)
    rec[(threading.current_thread().name, "build", len(p) > 50000)].append(
        (time.perf_counter() - w, time.thread_time() - c)
    )


nb.KdTree.nearest, nb.KdTree.__init__ = near, init
seq = io.KittiSequence("data/long", "403")
config = load_config(Path("gloam_jax/configs/gicp.yaml"))
poses, ms, extra = bench.run_ours(seq, 300, config, None, bench._CompileCounter())
print("median frame", np.median(ms[2:]))
agg = collections.defaultdict(list)
for key, v in rec.items():
    kk = key if key[1] == "build" else (key[0], key[1], "map" if key[2] > 50000 else "scan", key[3])
    agg[kk] += v
for key, v in sorted(agg.items(), key=str):
    w = np.array(v)
    print(
        key,
        "n/frame %.2f" % (len(v) / 300),
        "wall med %.2f ms" % (1e3 * np.median(w[:, 0])),
        "cpu med %.2f" % (1e3 * np.median(w[:, 1])),
        "wall mean %.2f" % (1e3 * w[:, 0].mean()),
    )
