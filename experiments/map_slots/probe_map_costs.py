"""The local map's costs on val 403 draw 0 after 60 frames of `gicp` (PLAN.md's numbers,
measured at `0266ca3`): its k-d tree's build and candidate queries; a tree of the map without
its newest keyframe plus one of that keyframe (their nearest against the whole tree's); the
padded device copy of the whole map; one keyframe's rows written into the map's arrays.

    python experiments/map_slots/probe_map_costs.py data/long
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax import io
from gloam_jax.config import load_config
from gloam_jax.neighbors import KdTree
from gloam_jax.odometry import Odometry
from gloam_jax.registration import device_cloud


def ms(f, n: int = 10) -> float:
    """Mean wall time of ``f()`` over ``n`` calls after one warm-up (ms)."""
    f()
    start = time.perf_counter()
    for _ in range(n):
        f()
    return 1e3 * (time.perf_counter() - start) / n


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("root")
    args = parser.parse_args()
    seq = io.KittiSequence(args.root, "403")
    odometry = Odometry(load_config("gicp"))
    for i in range(60):
        odometry.register_frame(seq.scan(i), None, 0.1)
    m, size = odometry.map.cloud, odometry.map.size
    newest = len(odometry.map.keyframes[-1]["points"])
    print(f"map rows {len(m.points)}, keyframes {len(odometry.map.keyframes)}, size {size}")
    T = odometry.poses[-1]
    q = odometry.previous.points @ T[:3, :3].T + T[:3, 3]
    whole = KdTree(m.points)
    older, new = KdTree(m.points[:-newest]), KdTree(m.points[-newest:])
    print(f"tree build {ms(lambda: KdTree(m.points)):.1f} ms")
    print(f"query k=1 {ms(lambda: whole.query(q, 1, 1.0)):.1f} ms, "
          f"k=5 {ms(lambda: whole.query(q, 5, 1.0)):.1f} ms")  # fmt: skip

    def two_trees():
        d_old, i_old = older.nearest(q, 1, 1.0)
        d_new, i_new = new.nearest(q, 1, 1.0)
        return np.minimum(d_old, d_new), np.where(d_new < d_old, i_new + len(older), i_old)

    d, _ = two_trees()
    print(f"two trees, query k=1 {ms(two_trees):.1f} ms (the newest keyframe's tree alone "
          f"{ms(lambda: new.nearest(q, 1, 1.0)):.1f}); same nearest distances: "
          f"{np.array_equal(d, whole.nearest(q, 1, 1.0)[0])}")  # fmt: skip
    copy = ms(lambda: device_cloud(m.points, m.covs, m.features, size), 5)
    print(f"padded device copy of the whole map {copy:.1f} ms")
    device = m.padded(size)
    write = jax.jit(lambda a, b, start: jax.lax.dynamic_update_slice_in_dim(a, b, start, 0))
    slot = size // odometry.config.max_keyframes
    for name in ("points", "covs"):
        a = getattr(device, name)
        b = jnp.zeros((slot, *a.shape[1:]), a.dtype)
        print(f"one keyframe's {name} written: "
              f"{ms(lambda a=a, b=b: write(a, b, slot).block_until_ready()):.2f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
