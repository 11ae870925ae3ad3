"""The prefetch thread's work per scan (ms, median over scans spread along a drive): the voxel
centres alone (gicp), with the shipped backbone's per-point features, with the grid backbone's
per-point features, and with the grid backbone on the preprocessing's own grid.

    python experiments/grid_features/probe_features.py data/long 403 20 [--out FILE]
"""

import argparse
import json
import time

import numpy as np

from gloam_jax import io
from gloam_jax.features import GeometricBackbone, fit_pca
from gloam_jax.preprocess import PreprocessConfig, voxel_centres


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("root")
    parser.add_argument("sequence")
    parser.add_argument("scans", type=int)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out")
    args = parser.parse_args()
    seq = io.KittiSequence(args.root, args.sequence)
    config = PreprocessConfig()
    shipped = GeometricBackbone()
    grid = GeometricBackbone(voxel_size=0.5, scales=[10], min_range=3.0, max_range=100.0)
    frames = np.linspace(0, len(seq) - 1, args.scans).astype(int)
    scans = [seq.scan(i) for i in frames]
    pca_shipped = fit_pca([shipped(s) for s in scans[:2]], 6)
    pca_grid = fit_pca([grid(s) for s in scans[:2]], 6)
    paths = {
        "voxel centres (gicp)": lambda s: voxel_centres(s, None, config),
        "shipped backbone, per point": lambda s: voxel_centres(
            s, None, config, pca=pca_shipped, features=shipped(s)
        ),
        "grid backbone, per point": lambda s: voxel_centres(
            s, None, config, pca=pca_grid, features=grid(s)
        ),
        "grid backbone, on the grid": lambda s: voxel_centres(
            s, None, config, pca=pca_grid, backbone=grid
        ),
    }
    result: dict[str, list[float]] = {name: [] for name in paths}
    for _ in range(args.repeats):
        for name, work in paths.items():
            times = []
            for s in scans:
                t0 = time.perf_counter()
                work(s)
                times.append(1e3 * (time.perf_counter() - t0))
            result[name].append(round(float(np.median(times)), 2))
    for name, ms in result.items():
        print(f"{name:30s}", " ".join(f"{x:7.1f}" for x in ms))
    if args.out:
        record = {"sequence": args.sequence, "frames": frames.tolist(), "median_ms": result,
                  "points_per_scan": float(np.mean([len(s) for s in scans]))}  # fmt: skip
        with open(args.out, "w") as f:
            json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
