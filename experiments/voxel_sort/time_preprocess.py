"""Time (min and median of 30, ms) of the voxel grouping, voxel_centres and the backbone on
val 403 scan 150, in whichever tree PYTHONPATH names (run it in both).

    PYTHONPATH=<tree> python experiments/voxel_sort/time_preprocess.py
"""

import time

import numpy as np

from gloam_jax import pointcloud as pc
from gloam_jax import preprocess as pp
from gloam_jax.features.geometric import GeometricBackbone
from gloam_jax.odometry import OdometryConfig

scan = np.fromfile("data/long/sequences/403/velodyne/000150.bin", np.float32).reshape(-1, 4)
xyz = scan[:, :3].astype(np.float64)
config = OdometryConfig().preprocess
backbone = GeometricBackbone()
for name, f in (
    ("range_mask", lambda: pc.range_mask(scan, 3.0, 100.0)),
    ("voxel_index 0.25 m", lambda: pc.voxel_index(xyz, 0.25)),
    ("voxel_centres", lambda: pp.voxel_centres(scan, None, config)),
    ("backbone", lambda: backbone(scan)),
):
    times = []
    for _ in range(30):
        start = time.perf_counter()
        f()
        times.append(time.perf_counter() - start)
    print(f"{name}: min {min(times) * 1e3:.1f} median {np.median(times) * 1e3:.1f}")
