"""Odometry on scans whose intensity is not the simulator's: each method's t_err on the same
simulated drives with intensity as simulated, set to zero, and mapped onto real scans'.

    python experiments/net_intensity/probe_intensity_odometry.py --data data/netodo \
        --sequences 00,02,04 --real ../shared/data/real_kitti16 \
        --methods gicp,gloam,gloam_net --out results/intensity_odometry

Each variant is a KITTI-layout copy under ``--out`` whose scans differ only in their fourth
column (the rest linked to the original). Runs are ``make_tables.run`` (``configs/<method>.yaml``,
window-scaled devkit segments), cached per variant, method and sequence, so a rerun resumes.
Writes ``intensity_odometry.json`` and ``.md`` under ``--out`` with the command and commit.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))  # the user tools it uses

import numpy as np  # noqa: E402
from make_tables import commit, run  # noqa: E402
from probe_net_domain import quantile_map, zero_intensity  # noqa: E402

from gloam_jax.datasets import open_dataset  # noqa: E402
from gloam_jax.io import KittiSequence, write_atomic  # noqa: E402


def variant_root(data: Path, sequences: list[str], out: Path, transform) -> Path:
    """A KITTI root at ``out`` with ``transform`` applied to every scan of ``sequences``."""
    for s in sequences:
        src, dst = data / "sequences" / s, out / "sequences" / s
        (dst / "velodyne").mkdir(parents=True, exist_ok=True)
        (out / "poses").mkdir(exist_ok=True)
        if not (out / "poses" / f"{s}.txt").exists():
            os.symlink((data / "poses" / f"{s}.txt").resolve(), out / "poses" / f"{s}.txt")
        for item in src.iterdir():
            if item.name not in ("velodyne", "labels") and not (dst / item.name).exists():
                os.symlink(item.resolve(), dst / item.name)
        for scan in sorted((src / "velodyne").glob("*.bin")):
            target = dst / "velodyne" / scan.name
            if not target.exists():
                points = np.fromfile(scan, np.float32).reshape(-1, 4)
                write_atomic(target, transform(points).astype(np.float32).tobytes())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--sequences", default="00,02,04")
    parser.add_argument("--real", type=Path, required=True, help="real scans (any dataset)")
    parser.add_argument("--methods", default="gicp,gloam,gloam_net")
    parser.add_argument("--weights", type=Path, default=None, help="model for learned methods")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    sequences = args.sequences.split(",")
    real = open_dataset(args.real)
    real_intensity = np.concatenate([real.frame(i)[0][:, 3] for i in range(len(real))])
    sim_intensity = np.concatenate(
        [KittiSequence(args.data, s).scan(i)[:, 3] for s in sequences for i in (0, 30)]
    )
    variants = {
        "as simulated": args.data,
        "zero": variant_root(args.data, sequences, args.out / "data_zero", zero_intensity),
        "mapped onto the real scans'": variant_root(
            args.data,
            sequences,
            args.out / "data_real",
            quantile_map(sim_intensity, real_intensity),
        ),  # fmt: skip
    }
    results: dict[str, dict[str, dict[str, float]]] = {}
    for variant, root in variants.items():
        tag = "as_is" if root == args.data else root.name
        for method in args.methods.split(","):
            for s in sequences:
                weights = None if method == "gicp" else args.weights
                row = run(root, s, method, weights, args.out / tag / method / s, "frame_to_model")
                results.setdefault(method, {}).setdefault(variant, {})[s] = row["t_err"]
                print(variant, method, s, f"{row['t_err']:.3f} %", flush=True)

    weights = None if args.weights is None else str(args.weights)
    record = {"command": "python " + " ".join(sys.argv), "commit": commit(),
              "data": str(args.data), "weights": weights, "t_err_percent": results}  # fmt: skip
    write_atomic(args.out / "intensity_odometry.json", json.dumps(record, indent=1))
    lines = [f"`{record['command']}` at `{record['commit']}`", "",
             "| method | intensity | " + " | ".join(sequences) + " | mean |",
             "|---|---|" + "---|" * (len(sequences) + 1)]  # fmt: skip
    for method, rows in results.items():
        for variant, cells in rows.items():
            values = [cells[s] for s in sequences]
            lines.append(f"| {method} | {variant} | " + " | ".join(f"{v:.3f}" for v in values)
                         + f" | {np.mean(values):.3f} |")  # fmt: skip
    write_atomic(args.out / "intensity_odometry.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
