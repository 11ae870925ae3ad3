"""Is the batch's pitch bias the odometry's once the batch's maps are placed as the odometry
places them? GICP's batch registrations against maps placed by the odometry's own estimated
poses, scored against the true ground truth.

    gloam run data/protocol_vlp16_drawn --sequence S --method gicp --out ODO/S   # S = 105, 108, 111
    python experiments/vlp16_drift/estimated_maps.py \\
        experiments/vlp16_drawn/train_vlp16_drawn.yaml runs/vlp16d_s0/model.npz \\
        --odometry ODO --sequences 105,108,111 --cache runs/estmap_cache

For each sequence it writes a KITTI-layout root whose scans are the data's (linked) and whose
"ground truth" is the odometry's estimate (``ODO/S/latest/S_poses_kitti.txt``): the batch
then places each pair's local map and first guess by the estimate, as the odometry does. Each
pair's rotation error is measured against the true ground truth. Prints, per sequence, the
mean per-pair pitch error (mdeg) with ground-truth maps, with estimated maps, and the
odometry's own mean per-frame pitch error. ``model`` only supplies the preprocessing's PCA (GICP
uses no features).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "vlp16_drawn"))
from train_bias import pair_errors  # noqa: E402

from gloam_jax import io  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402
from gloam_jax.metrics import frame_rotation_drift  # noqa: E402
from gloam_jax.models import load_model  # noqa: E402
from gloam_jax.training.config import TrainConfig  # noqa: E402
from gloam_jax.training.problem import setup, trainable_params  # noqa: E402


def batch_pitch(config: TrainConfig, model: str, cache: str, true_gt: dict) -> dict[str, float]:
    """Mean per-pair pitch error (mdeg) of GICP's batch registrations, per sequence."""
    with tempfile.TemporaryDirectory() as tmp:
        problem = setup(config, tmp, cache_dir=cache)
        params = trainable_params(load_model(model), config.method).as_gicp()
        T_rel = np.asarray(problem.evaluate_hard(params).T_rel, np.float64)
    windows = [dataclasses.replace(w, gt_cam=true_gt[w.name.split(":")[0]])
               for w in problem.data.windows]  # fmt: skip
    return {
        w.name: float(e[:, 0].mean())
        for w, e in zip(windows, pair_errors(T_rel, windows), strict=True)
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config")
    parser.add_argument("model")
    parser.add_argument("--odometry", type=Path, required=True)
    parser.add_argument("--sequences", required=True)
    parser.add_argument("--cache", required=True)
    args = parser.parse_args()
    config = load_config(args.config, TrainConfig)
    sequences = args.sequences.split(",")
    data = Path(config.training_roots[0])
    true_gt = {s: io.KittiSequence(data, s).gt_poses_cam for s in sequences}
    base = dataclasses.replace(
        config, init_model=args.model, validation=(), sequences=tuple(sequences)
    )
    with_gt = batch_pitch(base, args.model, args.cache, true_gt)
    with tempfile.TemporaryDirectory() as root:
        (Path(root) / "sequences").mkdir()
        (Path(root) / "poses").mkdir()
        odometry = {}
        for s in sequences:
            os.symlink((data / "sequences" / s).resolve(), Path(root) / "sequences" / s)
            est = io.read_kitti_poses(args.odometry / s / "latest" / f"{s}_poses_kitti.txt")
            io.write_kitti_poses(Path(root) / "poses" / f"{s}.txt", est)
            odometry[s] = frame_rotation_drift(true_gt[s][: len(est)], est)["mean_mdeg"][0]
        estimated = batch_pitch(
            dataclasses.replace(base, data=root), args.model, args.cache, true_gt
        )
    print("| sequence | batch, ground-truth maps | batch, estimated maps | odometry |")
    print("|---|---|---|---|")
    for name in with_gt:
        s = name.split(":")[0]
        print(f"| {name} | {with_gt[name]:+.2f} | {estimated[name]:+.2f} | {odometry[s]:+.2f} |")


if __name__ == "__main__":
    main()
