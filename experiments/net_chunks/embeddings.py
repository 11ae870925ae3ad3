"""Embeddings of the shipped net backbone on val 403 frames 0, 50, ..., 950, with whichever
gloam_jax is on the path, and the backbone's median ms a scan (a second pass, every padded
shape compiled in the first): python embeddings.py DATA OUT.npz; with a third argument
(another such file), the largest difference relative to its largest value."""

import sys
import time

import numpy as np

from gloam_jax.datasets import open_dataset
from gloam_jax.features import get_backbone
from gloam_jax.models import load_model, shipped_model_path

data, out = sys.argv[1], sys.argv[2]
# the shipped network on its own 0.3 m voxels, as measured here (since net_grid the shipped
# model runs it on the registration's grid)
backbone = get_backbone("net", weights=load_model(shipped_model_path("net")).backbone().weights)
sequence = open_dataset(data, sequence="403")
scans = {f"f{i}": sequence.frame(i)[0] for i in range(0, 1000, 50)}
rows = {k: backbone(scan) for k, scan in scans.items()}
ms = []
for scan in scans.values():
    t0 = time.perf_counter()
    backbone(scan)
    ms.append(1e3 * (time.perf_counter() - t0))
np.savez(out, **rows)
print(f"backbone median {np.median(ms):.1f} ms a scan, {min(ms):.1f}-{max(ms):.1f}")
if len(sys.argv) > 3:
    with np.load(sys.argv[3]) as other:
        diff = max(float(np.abs(rows[k] - other[k]).max()) for k in rows)
        scale = max(float(np.abs(other[k]).max()) for k in rows)
    print(f"largest difference {diff:.3g}, largest value {scale:.3g}, relative {diff / scale:.3g}")
