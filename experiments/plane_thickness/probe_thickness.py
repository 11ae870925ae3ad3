"""How thick the planes of learned covariances are, world by world.

    python experiments/plane_thickness/probe_thickness.py --data data/protocol2 \\
        --sequences 201,202,203,204,205 --model shipped=gloam_jax/data/gloam_default.npz \\
        --model step60=runs/warm/grad_s0/checkpoint.npz

Plain GICP gives every point the eigenvalues (eps, 1, 1): a plane whose thickness, the
smallest eigenvalue over the middle one, is eps = 0.001. Algorithm 1's learned eigenvalues give
each point its own. For every ``--every``-th scan of each world this prints the median
thickness of the voxel centres and the share of them thicker than ``--thick`` (the plane
thickness at which GICP's batch error on the val worlds starts to move:
experiments/plane_thickness/README.md), then the median in-plane ratio, the middle eigenvalue
over the largest (GICP: 1, a disc; near 0, a line); under "all", the same of every listed
world's points together.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))  # the user tools it uses

import numpy as np  # noqa: E402
from eval_batch import _load  # noqa: E402

from gloam_jax import covariance as cov  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402
from gloam_jax.datasets import open_dataset  # noqa: E402
from gloam_jax.io import write_atomic  # noqa: E402
from gloam_jax.preprocess import preprocess_scan  # noqa: E402
from gloam_jax.training.config import TrainConfig  # noqa: E402


def learned_values(model, scan: np.ndarray, config) -> np.ndarray:
    """Algorithm 1's ascending eigenvalues (M, 3) at one raw scan's voxel centres."""
    features = model.backbone()(scan)
    _, pca_features, _ = preprocess_scan(scan, None, config, pca=model.pca, features=features)
    return np.asarray(
        cov.learned_values(model.eigenvalue(pca_features), model.eps, model.max_thickness)
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--sequences", required=True, help="comma-separated ids")
    parser.add_argument("--model", action="append", required=True,
                        help="LABEL=FILE: a model file or a gradient run's checkpoint")  # fmt: skip
    parser.add_argument("--config", type=Path, default=Path("configs/train_protocol.yaml"))
    parser.add_argument("--every", type=int, default=10)
    parser.add_argument("--thick", type=float, default=0.0025)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    config = load_config(args.config, TrainConfig).preprocess
    models = {label: _load(Path(path)) for label, path in (m.split("=", 1) for m in args.model)}
    names, result = args.sequences.split(","), {}
    print("| model | " + " | ".join(names) + " | all |")
    print("|" + "---|" * (len(names) + 2))

    def stats(v: np.ndarray) -> dict:
        t = v[:, 0] / v[:, 1]
        return {
            "median": float(np.median(t)),
            "thick_share": float(np.mean(t > args.thick)),
            "in_plane_median": float(np.median(v[:, 1] / v[:, 2])),
        }

    for label, model in models.items():
        row, pooled = {}, []
        for name in names:
            dataset = open_dataset(args.data, name)
            v = np.concatenate([learned_values(model, dataset.frame(i)[0], config)
                                for i in range(0, len(dataset), args.every)])  # fmt: skip
            row[name] = stats(v)
            pooled.append(v)
        row["all"] = stats(np.concatenate(pooled))  # the worlds' points together
        result[label] = row
        print(
            f"| {label} | "
            + " | ".join(
                f"{r['median']:.4f} ({100 * r['thick_share']:.0f} %), {r['in_plane_median']:.2f}"
                for r in row.values()
            )
            + " |"
        )
    if args.out is not None:
        write_atomic(args.out, json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
