"""How much the net backbone's classes rest on intensity, the input real scans differ in most.

    python experiments/net_intensity/probe_net_domain.py --sim data/netodo --sequences 00,02,04 \
        --every 6 --real ../shared/data/real_kitti16 --out experiments/net_intensity/net_domain.json

On labelled simulated scans (worlds the network never saw) it scores the network's
mIoU and point accuracy with the intensity as simulated, set to zero, and mapped quantile by
quantile onto the real scans' intensity distribution. On the real scans (no labels) it gives
the share of points per class as they are and with their intensity mapped onto the simulated
distribution, and how many points change class. Writes JSON and a markdown table (``--out``
with ``.md``) with the command and commit.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))  # the user tools it uses

import numpy as np  # noqa: E402
from make_tables import commit  # noqa: E402

from gloam_jax.datasets import open_dataset  # noqa: E402
from gloam_jax.features import NetBackbone  # noqa: E402
from gloam_jax.features.net import CLASSES, class_index  # noqa: E402
from gloam_jax.io import KittiSequence, write_atomic  # noqa: E402
from gloam_jax.training.segmentation import evaluate  # noqa: E402

QUANTILES = np.linspace(0.0, 1.0, 101)


def quantile_map(source: np.ndarray, target: np.ndarray):
    """Scan (N, 4) -> scan whose intensity has ``target``'s quantiles where it had ``source``'s."""
    src, dst = np.quantile(source, QUANTILES), np.quantile(target, QUANTILES)

    def transform(scan: np.ndarray) -> np.ndarray:
        out = scan.copy()
        out[:, 3] = np.interp(scan[:, 3], src, dst)
        return out

    return transform


def zero_intensity(scan: np.ndarray) -> np.ndarray:
    out = scan.copy()
    out[:, 3] = 0.0
    return out


def shares(labels: np.ndarray) -> dict[str, float]:
    idx = class_index(labels)
    counts = np.bincount(idx[idx >= 0], minlength=len(CLASSES))
    return {CLASSES[j]: float(counts[j] / counts.sum()) for j in np.argsort(-counts) if counts[j]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim", type=Path, required=True, help="labelled KITTI-layout root")
    parser.add_argument("--sequences", default="00,02,04")
    parser.add_argument("--every", type=int, default=6)
    parser.add_argument("--real", type=Path, required=True, help="real scans (any dataset)")
    parser.add_argument("--weights", default="default", help="the network (train-backbone file)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    backbone = NetBackbone(args.weights)
    names = tuple(args.sequences.split(","))
    seqs = [KittiSequence(args.sim, s) for s in names]
    frames = {s.sequence: range(0, len(s), args.every) for s in seqs}
    real = open_dataset(args.real)
    real_scans = [real.frame(i)[0] for i in range(len(real))]
    sim_intensity = np.concatenate([s.scan(i)[:, 3] for s in seqs for i in frames[s.sequence]])
    real_intensity = np.concatenate([r[:, 3] for r in real_scans])

    sim_rows = {}
    for name, transform in (
        ("as simulated", None),
        ("zero", zero_intensity),
        ("mapped onto the real scans'", quantile_map(sim_intensity, real_intensity)),
    ):
        scores = evaluate(backbone.net, str(args.sim), names, args.every, transform)
        sim_rows[name] = {
            "miou": scores["miou"],
            "iou": scores["iou"],
            "point_accuracy": scores["accuracy"],
        }
        print(name, f"mIoU {100 * scores['miou']:.1f} %", flush=True)

    to_sim = quantile_map(real_intensity, sim_intensity)
    as_is = np.concatenate([backbone.segment(s) for s in real_scans])
    mapped = np.concatenate([backbone.segment(to_sim(s)) for s in real_scans])
    truth_shares = shares(np.concatenate([s.labels(i) for s in seqs for i in frames[s.sequence]]))
    record = {
        "command": "python " + " ".join(sys.argv),
        "commit": commit(),
        "weights": args.weights,
        "sim": {
            "root": str(args.sim),
            "sequences": names,
            "every": args.every,
            "scans": sum(len(f) for f in frames.values()),
            "rows": sim_rows,
            "truth_shares": truth_shares,
        },  # fmt: skip
        "intensity_quantiles_5_50_95": {
            "sim": np.quantile(sim_intensity, [0.05, 0.5, 0.95]).tolist(),
            "real": np.quantile(real_intensity, [0.05, 0.5, 0.95]).tolist(),
        },
        "real": {
            "root": str(args.real),
            "scans": len(real_scans),
            "shares_as_is": shares(as_is),
            "shares_intensity_mapped_to_sim": shares(mapped),
            "changed_class": float(np.mean(as_is != mapped)),
        },  # fmt: skip
    }
    write_atomic(args.out, json.dumps(record, indent=1))

    lines = [f"`{record['command']}` at `{record['commit']}`", ""]
    lines += ["| simulated scans, intensity | mIoU (%) | point accuracy (%) |", "|---|---|---|"]
    lines += [f"| {n} | {100 * r['miou']:.1f} | {100 * r['point_accuracy']:.1f} |"
              for n, r in sim_rows.items()]  # fmt: skip
    classes = list(record["real"]["shares_as_is"])
    lines += ["", "| class | simulated, truth (%) | real, as is (%) | real, intensity mapped (%) |",
              "|---|---|---|---|"]  # fmt: skip
    for c in classes:
        lines.append(
            f"| {c} | {100 * truth_shares.get(c, 0):.1f} | "
            f"{100 * record['real']['shares_as_is'][c]:.1f} | "
            f"{100 * record['real']['shares_intensity_mapped_to_sim'].get(c, 0):.1f} |"
        )
    lines.append(f"\nreal points that change class: {100 * record['real']['changed_class']:.1f} %")
    write_atomic(args.out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
