"""Does what gradient training learned on the training worlds carry over to the validation
worlds, more than a move of the same size in another direction would?

    python experiments/bounded_planes/probe_transfer.py --run runs/thin/grad_s0 \\
        --cache runs/warm/cache --directions 8 --out results/transfer_thin_s0.json

Takes a finished (or stopped) gradient run: its start and its last step's weights, whose
update from the start is D. Scores, with the run's own objective on its training and
validation windows (hard association, as the run's history does): the start, the trained
weights (start + D), the reversed update (start - D), ``--scales`` fractions of D (the
trained direction, a shorter way along it), and ``--directions`` updates with D's entries under
random signs (the same size per weight, other directions). If the trained update
lowers the training objective far below the random ones but the validation objective no lower
than theirs, what was learned does not carry over; if every update raises the validation
objective alike, the validation objective penalises any move from GICP.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax.config import load_config
from gloam_jax.io import write_atomic
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.grad import CHECKPOINT, load_checkpoint
from gloam_jax.training.problem import Problem, setup


def signed(start, update, signs):
    """``start + signs * update``, leaf by leaf (None leaves, the untrained parts, stay)."""
    return jax.tree_util.tree_map(lambda s, d, k: s + k * d, start, update, signs)


def load_run(run: Path, cache: Path | None) -> Problem:
    """The prepared problem of a gradient run of the MLPs alone (its start, its windows)."""
    config = load_config(run / "config.yaml", TrainConfig)
    if config.mode != "grad" or config.grad.head_learning_rate is not None:
        raise SystemExit(f"{run}: not a gradient run of the MLPs alone")
    return setup(config, run, cache_dir=cache)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, required=True, help="a gradient run's folder")
    parser.add_argument("--directions", type=int, default=8, help="random-sign updates")
    parser.add_argument("--scales", help="also start + s * D for these s (comma-separated)")
    parser.add_argument("--seed", type=int, default=0, help="of the random signs")
    parser.add_argument("--cache", type=Path, help="prepared windows (default: the run's)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if not (args.run / CHECKPOINT).is_file():
        raise SystemExit(f"{args.run}: no {CHECKPOINT}")
    problem = load_run(args.run, args.cache)
    config = problem.config
    start = problem.init_params
    trees, meta = load_checkpoint(args.run / CHECKPOINT, {"params": start})
    update = jax.tree_util.tree_map(lambda a, b: a - b, trees["params"], start)
    leaves, treedef = jax.tree_util.tree_flatten(update)
    rng = np.random.default_rng(args.seed)

    def signs(draw) -> object:
        return jax.tree_util.tree_unflatten(
            treedef, [jnp.asarray(draw(np.shape(x)), jnp.float32) for x in leaves]
        )

    candidates = {
        "start": start,
        "trained (start + D)": signed(start, update, signs(np.ones)),
        "reversed (start - D)": signed(start, update, signs(lambda s: -np.ones(s))),
    }
    for scale in args.scales.split(",") if args.scales else []:
        ones = signs(lambda s, scale=float(scale): np.full(s, scale))
        candidates[f"scaled (start + {scale} D)"] = signed(start, update, ones)
    for k in range(args.directions):
        draw = signs(lambda s: rng.choice([-1.0, 1.0], size=s))
        candidates[f"random signs {k}"] = signed(start, update, draw)
    rows = {}
    print(f"{args.run}: step {meta['step']}, objective '{config.objective}' (GICP 1.000)")
    print("| weights | training objective | validation objective (worse root) |")
    print("|---|---|---|")
    for label, params in candidates.items():
        train, val = problem.training_loss(params), problem.validation_loss(params)
        rows[label] = {
            "train_objective": train.objective,
            "train_t_err": train.t_err,
            "val_objective": None if val is None else val.objective,
            "val_t_err": None if val is None else val.t_err,
        }
        shown = "-" if val is None else f"{val.objective:.3f}"
        print(f"| {label} | {train.objective:.3f} | {shown} |", flush=True)
    if args.out is not None:
        result = {"run": str(args.run), "step": meta["step"], "rows": rows}
        write_atomic(args.out, json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
