"""Paper-style tables from odometry runs on the protocol's simulated windows.

    python scripts/make_tables.py --data data/protocol --model TPE=runs/tpe/model.npz \\
        --model grad=runs/grad/model.npz --model shipped --ablation shipped --out results/tables

* Table I: translational error (%) per sequence, training (01 03 05 07 09) and test (00 02 04
  06 08 10) windows, for GICP and each ``--model LABEL=FILE`` (a row "GLOAM (LABEL)";
  ``shipped`` is the package's model when no file is given).
* Table II: ablation on the test windows, t_err (%) and r_err (deg/100 m): GICP, +DA, +CE,
  +DA+CE (Generalized LOAM), the learned parts taken from the model labelled ``--ablation``.

Every run is the full odometry (``gloam run``: frame-to-model, deskew, keyframe map) with
``configs/<method>.yaml``; ``--mode frame_to_frame`` registers each scan to the previous one
instead, as training does. The windows are 70-300 m long, shorter than the devkit's 100-800 m
segments, so errors use the devkit's rule over segments of 10 %, 20 %, ..., 80 % of each
window's path length (whole metres). Each run's folder is kept; a rerun skips finished ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from gloam_jax import io, metrics
from gloam_jax.config import load_config
from gloam_jax.models import shipped_model_path
from gloam_jax.pipeline import run_sequence
from gloam_jax.training.losses import TRAINING_FRACTIONS, scaled_lengths
from gloam_jax.training.protocol import TEST_SEQUENCES, TRAIN_SEQUENCES

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def window_rte(gt: np.ndarray, est: np.ndarray) -> dict:
    """Devkit t_err (%) and r_err (deg/100 m) over segments scaled to the window."""
    lengths = sorted({max(1, round(x)) for x in scaled_lengths(gt, TRAINING_FRACTIONS)})
    r = metrics.kitti_rte(gt, est, lengths=lengths)
    return {"t_err": r.t_err_percent, "r_err": r.r_err_deg_per_100m, "lengths_m": lengths}


def run(data: Path, sequence: str, method: str, weights: Path | None, out: Path, mode: str) -> dict:
    """One odometry run (cached in ``out``), scored by :func:`window_rte`."""
    result_path = out / "table_metrics.json"
    if result_path.is_file():
        return json.loads(result_path.read_text())
    config = dataclasses.replace(load_config(CONFIGS / f"{method}.yaml"), mode=mode)
    if weights is not None:
        config = dataclasses.replace(config, model=str(weights))
    result = run_sequence(data, sequence, config, out)
    seq = io.KittiSequence(data, sequence)
    est = io.read_kitti_poses(out / f"{sequence}_poses_kitti.txt")
    row = {
        **window_rte(seq.gt_poses_cam[: len(est)], est),
        "median_ms_per_frame": result["median_ms_per_frame"],
        "median_ms_features": result.get("median_ms_features"),
        "degenerate_frames": len(result["degenerate_frames"]),
    }
    io.write_atomic(result_path, json.dumps(row, indent=2))
    return row


def fmt(x: float) -> str:
    return f"{x:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/protocol"))
    parser.add_argument("--model", action="append", default=[], help="LABEL=FILE, or shipped")
    parser.add_argument("--ablation", help="label of the --model for Table II")
    parser.add_argument("--mode", default="frame_to_model", help="or frame_to_frame")
    parser.add_argument("--sequences", default=None, help="only these (default: all 11)")
    parser.add_argument("--out", type=Path, default=Path("results/tables"))
    args = parser.parse_args()
    models = {}
    for item in args.model:
        label, _, path = item.partition("=")
        models[f"GLOAM ({label})"] = Path(path or shipped_model_path())
    if args.ablation is not None and f"GLOAM ({args.ablation})" not in models:
        raise SystemExit(f"--ablation {args.ablation}: no --model has that label")
    all_seqs = TRAIN_SEQUENCES + TEST_SEQUENCES
    chosen = all_seqs if args.sequences is None else tuple(args.sequences.split(","))
    results: dict[str, dict[str, dict]] = {}

    def do(label: str, method: str, weights: Path | None, sequences) -> None:
        for s in sequences:
            if s not in chosen:
                continue
            print(f"{label} {s} ...", flush=True)
            row = run(args.data, s, method, weights, args.out / label / s, args.mode)
            results.setdefault(label, {})[s] = row

    do("GICP", "gicp", None, all_seqs)
    for label, weights in models.items():
        do(label, "gloam", weights, all_seqs)
    ablation_rows = {"GICP": "GICP"}
    if args.ablation is not None:
        weights = models[f"GLOAM ({args.ablation})"]
        for label, method in (("GICP+DA", "gicp_da"), ("GICP+CE", "gicp_ce")):
            do(f"{label} ({args.ablation})", method, weights, TEST_SEQUENCES)
            ablation_rows[label] = f"{label} ({args.ablation})"
        ablation_rows["GICP+DA+CE (GLOAM)"] = f"GLOAM ({args.ablation})"

    lines = ["Table I: translational error (%), window-scaled devkit segments", ""]
    head = ["method", *TRAIN_SEQUENCES, "train avg", *TEST_SEQUENCES, "test avg"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, rows in results.items():
        if set(all_seqs) - set(rows):
            continue
        train = [rows[s]["t_err"] for s in TRAIN_SEQUENCES]
        test = [rows[s]["t_err"] for s in TEST_SEQUENCES]
        cells = [*map(fmt, train), fmt(np.mean(train)), *map(fmt, test), fmt(np.mean(test))]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "Table II: ablation on the test windows, t_err (%) / r_err (deg/100 m)", ""]
    head = ["method", *TEST_SEQUENCES, "mean"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, label in ablation_rows.items():
        rows = results.get(label, {})
        if set(TEST_SEQUENCES) - set(rows):
            continue
        t = [rows[s]["t_err"] for s in TEST_SEQUENCES]
        r = [rows[s]["r_err"] for s in TEST_SEQUENCES]
        cells = [f"{fmt(a)} / {fmt(b)}" for a, b in zip(t, r, strict=True)]
        cells.append(f"{fmt(np.mean(t))} / {fmt(np.mean(r))}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    print(text)
    io.write_atomic(args.out / "tables.md", text + "\n")
    io.write_atomic(args.out / "tables.json", json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
