"""Where the grid path of the shipped gloam_net backbone spends a scan, alone (issue 42):
python probe_grid_stages.py DATA [FRAME] (val 403 frames FRAME..FRAME+19; medians in ms)."""

import sys
import time

import numpy as np

from gloam_jax import pointcloud as pc
from gloam_jax.datasets import open_dataset
from gloam_jax.features import net as N
from gloam_jax.models import load_model, shipped_model_path
from gloam_jax.neighbors import KdTree

model = load_model(shipped_model_path("net"))
backbone = model.backbone()
g, c = backbone.grid, backbone.net.config
first = int(sys.argv[2]) if len(sys.argv) > 2 else 100
sequence = open_dataset(sys.argv[1], sequence="403")
scans = [sequence.frame(i)[0] for i in range(first, first + 20)]
ms: dict[str, list[float]] = {}


def timed(name, fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    ms.setdefault(name, []).append(1e3 * (time.perf_counter() - t0))
    return out


def prepare(scan):
    keep = pc.range_mask(scan, g["min_range"], g["max_range"], None)[0]
    xyz = np.compress(keep, scan[:, :3], axis=0).astype(np.float64)
    return xyz, np.compress(keep, scan[:, 3])


for scan in scans[:3]:  # compile every bucket seen
    xyz, inten = prepare(scan)
    grid = pc.voxel_grid(xyz, g["resolution"])
    backbone.voxel_features(xyz, inten, grid, grid.means(xyz))
for scan in scans:
    xyz, inten = prepare(scan)
    grid = timed("voxel grid (registration's)", pc.voxel_grid, xyz, g["resolution"])
    whole = lambda a, i, v: backbone.voxel_features(a, i, v, v.means(a))  # noqa: E731
    timed("voxel_features (all below)", whole, xyz, inten, grid)
    centres = timed("centres (means)", grid.means, xyz)
    values = timed("intensity means", grid.means, inten.astype(np.float64)[:, None])[:, 0]
    tree = timed("tree, level 0", KdTree, centres)
    nbr0 = timed("k-NN, level 0", N._knn, tree, centres, g["k"])
    sub = timed("sample level 1", N.sample_level1, len(centres), c.ratio)
    tree1 = timed("tree, level 1", KdTree, centres[sub])
    timed("k-NN, level 1", N._knn, tree1, centres[sub], c.k)
    timed("nearest level-1", N._knn, tree1, centres, 1)
    inputs = timed("build_inputs (level-1 queries and more)", N.build_inputs, centres,
                   N.scan_intensity(values, c), c, nbr0=nbr0)  # fmt: skip
    embedding = timed("network", lambda x: np.asarray(N._embedding(backbone.net, x)), inputs)
    timed("pca", model.pca.transform, embedding[: len(centres)])
print(f"{len(centres)} voxels in the last scan, {len(xyz)} points")
for name, values in ms.items():
    print(f"{name:42s} {np.median(values):6.1f}")
