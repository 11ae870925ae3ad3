"""Where on a VLP-16 scan the model thickens GICP's planes: ground, walls, or the rest.

    python experiments/vlp16_shrink/probe_ground.py data/long_d1 408 \\
        --model inc=gloam_jax/data/gloam_default.npz --model a010=runs/vlp16_shrink/a010.npz

For every ``--every``-th scan: the voxel centres (``configs/gicp.yaml``'s preprocessing, not
deskewed), their k-NN covariances' eigenvectors, and each model's Algorithm 1 eigenvalues. A
point is "ground" when its plane normal (smallest eigenvector) is within 25 deg of the LiDAR's
z axis, "wall" when within 25 deg of horizontal, "other" else. Prints, per class, its share of
the points and the median thickness (smallest over middle eigenvalue; GICP: 0.001) and the
median normal weight relative to GICP's (GICP's thickness over the model's, 1 = as GICP).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from gloam_jax import covariance as cov
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset
from gloam_jax.models import load_model
from gloam_jax.neighbors import KdTree
from gloam_jax.odometry import OdometryConfig
from gloam_jax.preprocess import preprocess_scan

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "gicp.yaml"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("sequence")
    parser.add_argument("--model", action="append", required=True, help="LABEL=FILE")
    parser.add_argument("--every", type=int, default=100)
    args = parser.parse_args(argv)
    config = load_config(CONFIG, OdometryConfig).preprocess
    models = {label: load_model(path) for label, path in (m.split("=", 1) for m in args.model)}
    dataset = open_dataset(args.data, args.sequence)
    stats: dict[tuple[str, str], list[np.ndarray]] = {}
    for k in range(0, len(dataset.times), args.every):
        scan = dataset.frame(k)[0]
        for label, model in models.items():
            points, f, _ = preprocess_scan(scan, None, config, pca=model.pca,
                                           features=model.backbone()(scan))  # fmt: skip
            idx, _ = KdTree(points).query(points, config.num_neighbors)
            _, vectors = cov.eigendecompose(cov.knn_covariances(points, idx))
            normal_z = np.abs(np.asarray(vectors)[:, 2, 0])  # smallest eigenvector's z
            values = np.asarray(cov.learned_values(model.eigenvalue(f), model.eps, None))
            thickness = values[:, 0] / values[:, 1]
            classes = {"ground": normal_z > np.cos(np.radians(25)),
                       "wall": normal_z < np.sin(np.radians(25))}  # fmt: skip
            classes["other"] = ~(classes["ground"] | classes["wall"])
            for name, mask in classes.items():
                stats.setdefault((label, name), []).append(thickness[mask])
            stats.setdefault((label, "all"), []).append(thickness)
    print(f"{args.data} {args.sequence}, every {args.every}th scan")
    print("| model | class | share | median thickness | median normal weight vs GICP |")
    print("|---|---|---|---|---|")
    for (label, name), parts in stats.items():
        t = np.concatenate(parts)
        share = len(t) / len(np.concatenate(stats[(label, "all")]))
        print(f"| {label} | {name} | {share:.2f} | {np.median(t):.4f} | "
              f"{np.median(cov.PLANE_EPS / t):.3f} |")  # fmt: skip


if __name__ == "__main__":
    main()
