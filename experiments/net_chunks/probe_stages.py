"""Where the net backbone's time goes on one scan, alone: python probe_stages.py DATA [FRAME]
(val 403 frames FRAME..FRAME+9, default 100; medians in ms, each stage warm)."""

import sys
import time

import jax
import numpy as np

from gloam_jax.datasets import open_dataset
from gloam_jax.features import get_backbone
from gloam_jax.features import net as N
from gloam_jax.models import load_model, shipped_model_path
from gloam_jax.neighbors import KdTree

# the shipped network on its own 0.3 m voxels, as measured here (since net_grid the shipped
# model runs it on the registration's grid)
backbone = get_backbone("net", weights=load_model(shipped_model_path("net")).backbone().weights)
c, first = backbone.net.config, int(sys.argv[2]) if len(sys.argv) > 2 else 100
sequence = open_dataset(sys.argv[1], sequence="403")
scans = [sequence.frame(i)[0] for i in range(first, first + 10)]
ms: dict[str, list[float]] = {}
# the embedding alone; before net_chunks (e1bf74d) the whole forward pass, logits included
network = getattr(N, "_embedding", N._forward)


def timed(name, fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    ms.setdefault(name, []).append(1e3 * (time.perf_counter() - t0))
    return out


for scan in scans[:2]:  # compile
    backbone(scan)
for scan in scans:
    timed("whole backbone", backbone, scan)
    xyz, intensity, _ = timed("voxels (0.3 m)", N.voxelize, scan, c.voxel_size)
    tree = timed("tree, level 0", KdTree, xyz)
    timed("k-NN, level 0", N._knn, tree, xyz, c.k)
    sub = N.sample_level1(len(xyz), c.ratio)
    tree1 = timed("tree, level 1", KdTree, xyz[sub])
    timed("k-NN, level 1", N._knn, tree1, xyz[sub], c.k)
    timed("nearest level-1", N._knn, tree1, xyz, 1)
    inputs = timed("inputs (the k-NN above and more)", N.build_inputs, xyz,
                   N.scan_intensity(intensity, c), c)  # fmt: skip
    timed("network", lambda x: jax.block_until_ready(network(backbone.net, x)), inputs)
print(f"{len(xyz)} voxels in the last scan")
for name, values in ms.items():
    print(f"{name:34s} {np.median(values):6.1f}")
