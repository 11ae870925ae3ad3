"""NumPy row gathers and selections at a scan's sizes: fancy / boolean indexing against
np.take / np.compress (min of 30, ms), and the reduceat that follows them in voxel_means.

    python experiments/row_gathers/probe_gathers.py
"""

import time

import numpy as np

rng = np.random.default_rng(0)


def tm(name, fn):
    fn()
    ts = []
    for _ in range(30):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    print(name, f"{min(ts) * 1e3:.2f}")


n = 115000
order = rng.permutation(n)
for shape, dt in (((n, 4), np.float64), ((n, 6), np.float32)):
    a = rng.random(shape).astype(dt)
    tm(f"{shape} {dt.__name__} a[order]", lambda a=a: a[order])
    tm(f"{shape} {dt.__name__} np.take", lambda a=a: np.take(a, order, axis=0))
m, n = 27000, 122000
per_voxel = rng.random((m, 17)).astype(np.float32)
inverse = rng.integers(0, m, n)
keep = rng.random(n) < 0.95
features = rng.random((n, 20)).astype(np.float32)
tm("per_voxel[inverse]", lambda: per_voxel[inverse])
tm("np.take(per_voxel, inverse)", lambda: np.take(per_voxel, inverse, axis=0))
tm("features[keep]", lambda: features[keep])
tm("np.compress(keep, features)", lambda: np.compress(keep, features, axis=0))
