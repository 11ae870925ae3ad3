"""Where the local map's merge goes (concatenation, k-d tree, padded device copy), timed on
its worker thread during a `gicp` run; the code before `9940476` (run it from a worktree of
`5cc5c14`, as `PYTHONPATH=... python probe_merge.py data/long 409 300`)."""

import collections
import sys
import time

import numpy as np

from gloam_jax import odometry
from gloam_jax.neighbors import KdTree

parts = collections.defaultdict(list)


def merge(keyframes, size):
    """odometry._merge as it was, timed by part."""
    t0 = time.perf_counter()
    merged = {
        k: None if keyframes[0][k] is None else np.concatenate([f[k] for f in keyframes])
        for k in keyframes[0]
    }
    t1 = time.perf_counter()
    tree = KdTree(merged["points"], "local map")
    t2 = time.perf_counter()
    cloud = odometry.PreparedCloud(tree=tree, **merged)
    cloud.padded(size)
    parts["rows"].append(len(merged["points"]))
    for name, ms in (
        ("concatenate", t1 - t0),
        ("tree", t2 - t1),
        ("padded", time.perf_counter() - t2),
    ):
        parts[name].append(1e3 * ms)
    return cloud


odometry._merge = merge
from gloam_jax import pipeline  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402
from gloam_jax.datasets import open_dataset  # noqa: E402

root, sequence, frames = sys.argv[1], sys.argv[2], int(sys.argv[3])
dataset = open_dataset(root, sequence)
m = pipeline.run_dataset(dataset, load_config("gicp"), f"runs/map_rows/merge_{sequence}",
                         pipeline.select_frames(len(dataset), 0, frames))  # fmt: skip
print(sequence, "registration ms", round(m["median_ms_per_frame"], 1), "map wait",
      m["stage_ms"]["map"]["median"])  # fmt: skip
print(" merges", len(parts["rows"]), "median rows", int(np.median(parts["rows"])),
      {k: round(float(np.median(v)), 1) for k, v in parts.items() if k != "rows"})  # fmt: skip
