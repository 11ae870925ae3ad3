"""Do the training worlds and the validation worlds pull the weights the same way at the start?

    python experiments/bounded_planes/probe_gradients.py --run runs/thin/grad_s0 \\
        --cache runs/warm/cache --out results/gradients_thin_s0.json

Takes a gradient run's start (its ``init_model.npz`` and prepared windows) and computes, for
every training and validation window, the gradient of that window's error ratio to plain GICP
(its term of the ``gicp_ratio`` objective without the penalty's kink) with respect to the MLP
weights, with the run's own training loss (soft association where the run trains with it).
Prints the cosine between the mean training gradient and each validation root's mean, each
window's cosine with the training mean, and the share of weights on whose sign at least 80 %
of the training windows agree; then the same cosines for the training windows' common
direction (the shortest vector in their gradients' convex hull, MGDA's: minus it lowers every
training window's loss at once where it is not zero). Two random directions among the MLPs'
weights have a cosine of about +-1/sqrt(n), n the number of weights; a first step helps a
validation window only where its gradient points with the step's direction.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from probe_transfer import load_run

from gloam_jax.io import write_atomic
from gloam_jax.learned import Learned
from gloam_jax.training import batch


def window_gradients(problem, data: batch.BatchData, reference: np.ndarray) -> np.ndarray:
    """d(t_err_w / reference_w) / d(MLP weights) at the start, one row per window (W, n)."""
    mesh = batch.pair_mesh()
    scans, pairs = batch.place(data.scans, data.pairs, mesh)
    placed = batch.BatchData(scans, pairs, data.windows, data.regularizer, data.head)
    ref = jnp.asarray(reference, jnp.float32)

    @jax.jit
    def gradient(params: Learned, w: jax.Array) -> Learned:
        def ratio(p: Learned) -> jax.Array:
            return (batch.window_t_err(p, placed, problem.config.batch, mesh) / ref)[w]

        return jax.grad(ratio)(params)

    start = problem.init_params
    rows = []
    for w in range(len(data.windows)):
        g = gradient(start, jnp.int32(w))
        mlps = [m for m in (g.conversion, g.eigenvalue) if m is not None]
        rows.append(np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(mlps)]))
    return np.stack(rows)


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def common_direction(rows: np.ndarray) -> np.ndarray:
    """The shortest vector in the convex hull of the gradient rows (W, n) (MGDA's min-norm
    point): where it is not zero, minus it lowers every row's loss at once."""
    from scipy.optimize import minimize

    gram = rows @ rows.T
    w = len(rows)
    found = minimize(lambda a: a @ gram @ a, np.full(w, 1.0 / w), jac=lambda a: 2 * gram @ a,
                     bounds=[(0.0, 1.0)] * w, method="SLSQP",
                     constraints=[{"type": "eq", "fun": lambda a: a.sum() - 1.0}])  # fmt: skip
    return found.x @ rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, required=True, help="a gradient run's folder")
    parser.add_argument("--cache", type=Path, help="prepared windows (default: the run's)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    problem = load_run(args.run, args.cache)
    if problem.reference is None or problem.validation is None:
        raise SystemExit(f"{args.run}: needs the gicp_ratio objective and validation windows")
    train = window_gradients(problem, problem.data, problem.reference)
    names = [w.name for w in problem.data.windows]
    mean, common = train.mean(axis=0), common_direction(train)
    agree = np.mean(np.abs(np.sign(train).mean(axis=0)) >= 0.6)  # >= 80 % of one sign
    result = {
        "weights": int(train.shape[1]),
        "sign_agreement_80": float(agree),
        "train": {n: cosine(g, mean) for n, g in zip(names, train, strict=True)},
        "train_common": {n: cosine(g, common) for n, g in zip(names, train, strict=True)},
        "val": {},
        "gradients": {"train": train.tolist()},
    }
    roots = problem.config.validation_roots
    for root, evaluate, ref in zip(
        roots, problem.validation.evaluate, problem.validation.references, strict=True
    ):
        val = window_gradients(problem, evaluate.data, ref)
        val_names = [w.name for w in evaluate.data.windows]
        result["val"][root] = {
            "mean_cosine": cosine(val.mean(axis=0), mean),
            "windows": {n: cosine(g, mean) for n, g in zip(val_names, val, strict=True)},
            "common": {n: cosine(g, common) for n, g in zip(val_names, val, strict=True)},
        }
        result["gradients"][root] = val.tolist()
    n = result["weights"]
    print(f"{args.run}: {n} weights; a random cosine is about +-{1 / np.sqrt(n):.2f}")
    print(f"weights whose sign >= 80 % of the training windows share: {100 * agree:.0f} %")
    print("training windows, cosine with the training mean: "
          + ", ".join(f"{k} {v:+.2f}" for k, v in result["train"].items()))  # fmt: skip
    print("training windows, cosine with their common direction: "
          + ", ".join(f"{k} {v:+.2f}" for k, v in result["train_common"].items()))  # fmt: skip
    for root, r in result["val"].items():
        print(f"validation {root}: mean gradient's cosine {r['mean_cosine']:+.2f}; windows "
              + ", ".join(f"{k} {v:+.2f}" for k, v in r["windows"].items())
              + "; with the common direction "
              + ", ".join(f"{k} {v:+.2f}" for k, v in r["common"].items()))  # fmt: skip
    if args.out is not None:
        write_atomic(args.out, json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
