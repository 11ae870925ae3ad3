"""The shipped net backbone run on the registration's own 0.5 m voxel centres and their k-NN
(the odometry's k = 10) instead of its 0.3 m grid and k = 16, the shipped gloam_net model
unchanged. A probe, not the product: each raw point gets its 0.5 m voxel's embedding, which
the odometry's per-voxel mean then gives back exactly.

    python probe_grid.py compare DATA SEQ [--level1-k K]      # PCA features, both ways
    python probe_grid.py run DATA SEQ OUT [--level1-k K]      # gloam_net with the probe's net
"""

import argparse
import time

import numpy as np

from gloam_jax import pointcloud as pc
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset
from gloam_jax.features import net as N
from gloam_jax.models import load_model, shipped_model_path
from gloam_jax.neighbors import KdTree
from gloam_jax.pipeline import run_dataset, select_frames
from gloam_jax.preprocess import PreprocessConfig

PREP = PreprocessConfig()  # the shipped configs' range band, 0.5 m voxels, k = 10


def grid_inputs(scan: np.ndarray, config: N.NetConfig, level1_k: int):
    """The network's inputs on the registration's voxel centres of a raw scan, the rows kept
    in range (N,) bool and each kept row's voxel."""
    keep, _ = pc.range_mask(scan, PREP.min_range, PREP.max_range, None)
    points = np.compress(keep, scan[:, :3], axis=0).astype(np.float64)
    grid = pc.voxel_grid(points, PREP.downsampling_resolution)
    xyz = grid.means(points)
    intensity = grid.means(np.compress(keep, scan[:, 3]).astype(np.float64)[:, None])[:, 0]
    m, k0 = len(xyz), PREP.num_neighbors
    size = pc.bucket_size(m)
    nbr0 = KdTree(xyz).query(xyz, k0)[0]  # the covariances' own k-NN
    sub = N.sample_level1(m, config.ratio)
    tree1 = KdTree(xyz[sub])
    nbr1 = N._knn(tree1, xyz[sub], level1_k)
    up = N._knn(tree1, xyz, 1)[:, 0]
    features = np.stack([np.linalg.norm(xyz, axis=1) / N._RANGE_SCALE, xyz[:, 2] / N._HEIGHT_SCALE,
                         N.scan_intensity(intensity, config)], 1)  # fmt: skip
    n1 = -(-size // config.ratio)
    pad0, pad1 = np.arange(m, size, dtype=np.int32), np.arange(len(sub), n1, dtype=np.int32)
    inputs = N.NetInputs(
        xyz=pc.pad(xyz.astype(np.float32), size)[0],
        inputs=pc.pad(features.astype(np.float32), size)[0],
        nbr0=np.concatenate([nbr0, np.repeat(pad0[:, None], k0, 1)]),
        sub=np.concatenate([sub, np.zeros(len(pad1), np.int32)]),
        nbr1=np.concatenate([nbr1, np.repeat(pad1[:, None], level1_k, 1)]),
        up=np.concatenate([up, np.zeros(len(pad0), np.int32)]),
    )
    return inputs, keep, grid, m


def grid_backbone(level1_k: int):
    """A NetBackbone.__call__ replacement: per-point rows of the 0.5 m voxels' embeddings."""

    def call(self, scan, *, path=None, frame=None):
        inputs, keep, grid, m = grid_inputs(scan, self.net.config, level1_k)
        per_voxel = np.asarray(N._embedding(self.net, inputs))[:m]
        out = np.zeros((len(scan), self.net.config.embed), np.float32)
        out[keep] = np.take(per_voxel, grid.inverse, axis=0)
        return out

    return call


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["compare", "run"])
    ap.add_argument("data")
    ap.add_argument("sequence")
    ap.add_argument("out", nargs="?")
    ap.add_argument("--level1-k", type=int, default=16)
    args = ap.parse_args()
    dataset = open_dataset(args.data, sequence=args.sequence)
    if args.what == "run":
        N.NetBackbone.__call__ = grid_backbone(args.level1_k)
        metrics = run_dataset(dataset, load_config("gloam_net"), args.out,
                              select_frames(len(dataset)))  # fmt: skip
        print(f"t_err {metrics['t_err_percent']:.4f} %, features median "
              f"{metrics['median_ms_features']:.1f} ms, frame median "
              f"{metrics['median_ms_per_frame']:.1f} ms")  # fmt: skip
        return
    model = load_model(shipped_model_path("net"))
    backbone = model.backbone()
    ours, theirs, ms_ours, ms_theirs = [], [], [], []
    for i in range(0, len(dataset), max(1, len(dataset) // 20)):
        scan = dataset.frame(i)[0]
        for rows, ms, fn in ((theirs, ms_theirs, N.NetBackbone.__call__),
                             (ours, ms_ours, grid_backbone(args.level1_k))):  # fmt: skip
            fn(backbone, scan)  # compiled
            t0 = time.perf_counter()
            raw = fn(backbone, scan)
            ms.append(1e3 * (time.perf_counter() - t0))
            keep, _ = pc.range_mask(scan, PREP.min_range, PREP.max_range, None)
            points = np.compress(keep, scan[:, :3], axis=0).astype(np.float64)
            grid = pc.voxel_grid(points, PREP.downsampling_resolution)
            rows.append(grid.means(model.pca.transform(np.compress(keep, raw, axis=0))))
    a, b = np.concatenate(theirs), np.concatenate(ours)
    corr = [np.corrcoef(a[:, j], b[:, j])[0, 1] for j in range(a.shape[1])]
    rel = np.sqrt(((a - b) ** 2).mean(0)) / a.std(0)
    print(f"{len(a)} voxel centres, {len(theirs)} scans")
    print("PCA feature correlation, 0.3 m net vs on the 0.5 m grid:", np.round(corr, 3))
    print("RMS difference / std:", np.round(rel, 3))
    print(
        f"backbone ms a scan, median: 0.3 m {np.median(ms_theirs):.1f}, "
        f"0.5 m grid {np.median(ms_ours):.1f}"
    )


if __name__ == "__main__":
    main()
