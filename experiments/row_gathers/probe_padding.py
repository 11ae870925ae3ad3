"""PreparedCloud.padded for a local map of 180,000 rows (random points, unit-ish covariances):
the padded device arrays' time (min and median of 10, ms), in whichever tree PYTHONPATH names.

    PYTHONPATH=<tree> python experiments/row_gathers/probe_padding.py
"""

import time

import jax
import numpy as np

from gloam_jax.registration import PreparedCloud

rng = np.random.default_rng(0)
n, size = 180000, 229376
points = rng.normal(0, 30, (n, 3))
covs = np.tile(np.eye(3), (n, 1, 1)) + 0.01
normals, planarity = rng.normal(size=(n, 3)), rng.random(n)
times = []
for _ in range(10):
    cloud = PreparedCloud(points, covs, None, None, normals=normals, planarity=planarity)
    start = time.perf_counter()
    jax.block_until_ready(cloud.padded(size))
    times.append(time.perf_counter() - start)
print(f"padded: min {min(times) * 1e3:.1f} median {np.median(times) * 1e3:.1f}")
