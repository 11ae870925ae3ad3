"""TPE against gradient training on the same problem: training loss against wall time.

    python scripts/compare_training.py runs/tpe runs/grad --plot results/training.png \\
        --out results/bench_training.json

Reads each run folder's ``history.json`` (the training t_err with hard association, measured
identically by both modes, and the wall time of the training work). Reports TPE's best loss and
total time, and when the gradient run first reached that loss: the issue's target is at most a
fifth of TPE's wall time.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from gloam_jax.io import write_atomic
from gloam_jax.training.problem import plot_histories


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tpe", type=Path)
    parser.add_argument("grad", type=Path)
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    tpe = json.loads((args.tpe / "history.json").read_text())
    grad = json.loads((args.grad / "history.json").read_text())
    best = min(h["t_err"] for h in tpe)
    best_at = next(h for h in tpe if h["t_err"] == best)
    reached = next((h for h in grad if h["t_err"] <= best), None)
    summary = {
        "start_t_err": tpe[0]["t_err"],
        "tpe_trials": len(tpe),
        "tpe_best_t_err": best,
        "tpe_best_trial": best_at["trial"],
        "tpe_wall_s": tpe[-1]["wall_s"],
        "tpe_wall_to_best_s": best_at["wall_s"],
        "grad_steps": grad[-1]["step"],
        "grad_best_t_err": min(h["t_err"] for h in grad),
        "grad_wall_s": grad[-1]["wall_s"],
        "grad_wall_to_tpe_best_s": None if reached is None else reached["wall_s"],
        "grad_step_to_tpe_best": None if reached is None else reached["step"],
    }
    if reached is not None:
        summary["ratio_to_tpe_wall"] = reached["wall_s"] / summary["tpe_wall_s"]
    for k, v in summary.items():
        print(f"{k}: {v}")
    if args.out is not None:
        write_atomic(args.out, json.dumps(summary, indent=2))
    if args.plot is not None:
        plot_histories(
            {
                "TPE, best so far": (
                    [h["wall_s"] for h in tpe], [100 * h["best_t_err"] for h in tpe]),
                "gradient (Adam)": ([h["wall_s"] for h in grad], [100 * h["t_err"] for h in grad]),
            },
            args.plot,
            "training loss: TPE vs gradients through GICP",
        )  # fmt: skip


if __name__ == "__main__":
    main()
