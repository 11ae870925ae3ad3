"""Models scored on the training problem itself: batched frame-to-frame registrations.

    python scripts/eval_batch.py --config configs/train_tpe.yaml --sequences 00,02,04 \\
        --model tpe=runs/tpe/model.npz --model grad=runs/grad/model.npz --out batch_eval.json
    python scripts/eval_batch.py --config configs/train_protocol.yaml --sequences 201,202 \\
        --data data/protocol2 --data data/val_worlds_s1 --model grad=runs/g0/model.npz

Prepares the windows as the config's training does (same preprocessing, candidate sets and
registrations, with the PCA of the first model) and prints each model's t_err (%) per window,
with hard association, next to plain GICP's; the windows are the sequences of the config's
training roots, or of the ``--data`` roots (validation worlds, simulation seeds). Tells
whether what training learned carries over to windows it did not see, before any odometry is
involved.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import jax
import numpy as np

from gloam_jax.config import load_config
from gloam_jax.io import write_atomic
from gloam_jax.learned import EigenvalueEstimationMLP, Learned, plane_output
from gloam_jax.models import GLOAMModel, learned_parts, load_model, with_mlps
from gloam_jax.training.batch import Evaluator
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.data import load_windows
from gloam_jax.training.grad import CHECKPOINT, load_checkpoint
from gloam_jax.training.problem import trainable_params


def _load(path: Path) -> GLOAMModel:
    """A model file, or a gradient run's ``checkpoint.npz``: the weights of its last step,
    which the run itself exports only when validation chose that step."""
    if path.name != CHECKPOINT:
        return load_model(path)
    run = load_config(path.parent / "config.yaml", TrainConfig)
    if run.grad.head_learning_rate is not None:
        # Its MLPs were trained on the fine-tuned layer's features, which the start lacks.
        raise SystemExit(f"{path}: a fine-tuning run's checkpoint; score its exported model.npz")
    start = load_model(path.parent / "init_model.npz")
    last = load_checkpoint(path, {"params": trainable_params(start, run.method)})[0]["params"]
    return with_mlps(start, last.conversion, last.eigenvalue, {"checkpoint": str(path)})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("configs/train_tpe.yaml"))
    parser.add_argument("--sequences", required=True, help="comma-separated ids")
    parser.add_argument("--model", action="append", required=True,
                        help="LABEL=FILE, a model file or a run's checkpoint.npz")  # fmt: skip
    parser.add_argument("--data", action="append", help="root (repeatable; default: the config's)")
    parser.add_argument("--method", default="gloam", help="parts to score: gicp_da,gicp_ce,gloam")
    parser.add_argument("--max-thickness", help="also each model with planes at most this thick "
                        "(its max_thickness; comma-separated)")  # fmt: skip
    parser.add_argument("--plane-eps", help="also GICP with these plane eps (comma-separated): "
                        "(eps, 1, 1) as a constant eigenvalue MLP")  # fmt: skip
    parser.add_argument("--cache", type=Path, default=Path("runs/cache"))
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    cfg = load_config(args.config, TrainConfig)
    config = dataclasses.replace(cfg.batch, association="hard")
    models = dict(m.split("=", 1) for m in args.model)
    loaded = {label: _load(Path(path)) for label, path in models.items()}
    first = next(iter(loaded.values()))
    for label, model in loaded.items():
        if not all(np.array_equal(a, b) for a, b in zip(model.pca, first.pca, strict=True)):
            raise SystemExit(f"{label}: its PCA differs from the first model's")
    names = args.sequences.split(",")
    roots = args.data or list(cfg.training_roots)
    data = load_windows(roots, names, cfg.preprocess, config, first.pca, first.backbone(),
                        frames=cfg.frames, cache_dir=args.cache)  # fmt: skip
    sequences = names if len(roots) == 1 else [f"{Path(r).name}/{n}" for r in roots for n in names]
    evaluate = Evaluator(data, config)
    rows = {"GICP": evaluate(Learned())}
    mlp = EigenvalueEstimationMLP.init(jax.random.PRNGKey(0))
    for eps in args.plane_eps.split(",") if args.plane_eps else []:
        plane = mlp.constant(plane_output(float(eps)))
        rows[f"GICP, plane eps {eps}"] = evaluate(Learned(eigenvalue=plane))
    methods = args.method.split(",")
    caps = args.max_thickness.split(",") if args.max_thickness else []
    for label, model in loaded.items():
        for method in methods:
            name = label if len(methods) == 1 else f"{label} ({method})"
            parts = learned_parts(model, method)
            rows[name] = evaluate(parts)
            for cap in caps if parts.eigenvalue is not None else []:
                bounded = parts._replace(max_thickness=float(cap))
                rows[f"{name}, planes <= {cap}"] = evaluate(bounded)
    print("| method | " + " | ".join(sequences) + " | mean |")
    print("|" + "---|" * (len(sequences) + 2))
    result = {}
    for label, r in rows.items():
        t = 100 * r.t_err
        result[label] = {"t_err": dict(zip(sequences, t.tolist(), strict=True)),
                         "mean": float(t.mean())}  # fmt: skip
        print(f"| {label} | " + " | ".join(f"{x:.2f}" for x in t) + f" | {t.mean():.2f} |")
    if args.out is not None:
        write_atomic(args.out, json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
