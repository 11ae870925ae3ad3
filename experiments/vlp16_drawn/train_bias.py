"""The mean per-pair rotation error (a bias) and its spread on the training windows, for plain
GICP and trained models: does the training data show the pitch bias seen on long drives?

    python experiments/vlp16_drawn/train_bias.py experiments/vlp16_drawn/train_vlp16_drawn.yaml \
        runs/vlp16d_s0/model.npz [...] --cache runs/vlp16d_cache [--batch map_scans=10 ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile

import numpy as np
from scipy.spatial.transform import Rotation

from gloam_jax.config import load_config
from gloam_jax.io import frame_motions
from gloam_jax.models import load_model
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.problem import setup, trainable_params


def pair_errors(T_rel: np.ndarray, windows) -> list[np.ndarray]:
    """Per window, each pair's rotation error (n-1, 3) in millidegrees about camera x, y, z."""
    out = []
    for w in windows:
        est = T_rel[w.start : w.stop]
        Tr, Tr_inv = w.Tr_cam_velo, np.linalg.inv(w.Tr_cam_velo)
        d_est = Tr @ est @ Tr_inv  # camera-0 frame motion of each pair
        d_gt = frame_motions(w.gt_cam)
        err = np.linalg.inv(d_gt) @ d_est
        out.append(Rotation.from_matrix(err[:, :3, :3]).as_rotvec(degrees=True) * 1e3)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config")
    parser.add_argument("models", nargs="+")
    parser.add_argument("--cache", required=True)
    parser.add_argument(
        "--batch", action="append", default=[], metavar="KEY=INT",
        help="a batch setting instead of the config's (rounds, map_scans, map_stride, "
        "max_source_points)",
    )  # fmt: skip
    args = parser.parse_args()
    config = load_config(args.config, TrainConfig)
    batch = {k: int(v) for k, v in (item.split("=", 1) for item in args.batch)}
    config = dataclasses.replace(config, batch=dataclasses.replace(config.batch, **batch))
    b = config.batch
    print(f"rounds {b.rounds}, map_scans {b.map_scans}, map_stride {b.map_stride}, "
          f"max_source_points {b.max_source_points}")  # fmt: skip
    for name in ["gicp", *args.models]:
        model = args.models[0] if name == "gicp" else name
        cfg = dataclasses.replace(config, init_model=model, validation=())
        with tempfile.TemporaryDirectory() as tmp:
            problem = setup(cfg, tmp, cache_dir=args.cache)
            params = trainable_params(load_model(model), cfg.method)
            params = params.as_gicp() if name == "gicp" else params
            result = problem.evaluate_hard(params)
        errs = pair_errors(np.asarray(result.T_rel, np.float64), problem.data.windows)
        for w, e in zip(problem.data.windows, errs, strict=True):
            m, s = e.mean(0), e.std(0, ddof=1)
            print(f"{name} {w.name}: pitch mean {m[0]:+.2f} yaw {m[1]:+.2f} roll {m[2]:+.2f} "
                  f"pitch std {s[0]:.1f} mdeg/pair")  # fmt: skip
        print(f"{name} t_err {np.mean(result.t_err):.4f} r_err {np.mean(result.r_err):.6f}")


if __name__ == "__main__":
    main()
