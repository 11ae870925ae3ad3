"""The geometric backbone's features of four val_long scans, saved for comparison between trees.

    PYTHONPATH=<tree> python experiments/pykdtree/compare_features.py OUT.npz   # from that tree
"""

import sys
import time

import numpy as np

from gloam_jax.features.geometric import GeometricBackbone

backbone = GeometricBackbone()
out = {}
for seq, frame in (("403", 150), ("402", 300), ("405", 10), ("401", 500)):
    path = f"data/long/sequences/{seq}/velodyne/{frame:06d}.bin"
    scan = np.fromfile(path, np.float32).reshape(-1, 4)
    backbone(scan)
    start = time.perf_counter()
    out[seq] = backbone(scan)
    print(seq, len(scan), f"{(time.perf_counter() - start) * 1e3:.1f} ms")
np.savez(sys.argv[1], **out)
