"""How far other worlds or sensors move a backbone's features from those of training scans.

    python experiments/invariant_features/probe_feature_shift.py data/protocol2 \\
        --reference 101,103,104,106,107,109 --compare 202,203,204,201,205 \\
        --options '{max_height: 3.5, drop: [density]}' \\
        --out experiments/invariant_features/feature_shift

For each compared sequence: each feature's mean over every ``--every``-th scan, minus the
reference scans' mean, in reference standard deviations (absolute), and their average over
the features. Sequences of a sensor the reference does not have show how much of the backbone
describes the sensor rather than the scene. A fixed 4000 points per scan are drawn (seeded by
the scan index), so a scan weighs the same whatever its point count. Writes ``OUT.json`` and
``OUT.md`` with the command and commit.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))  # the user tools it uses

import numpy as np  # noqa: E402
from make_tables import commit  # noqa: E402

from gloam_jax.config import parse_mapping  # noqa: E402
from gloam_jax.datasets import open_dataset  # noqa: E402
from gloam_jax.features import get_backbone  # noqa: E402
from gloam_jax.io import write_atomic  # noqa: E402

POINTS_PER_SCAN = 4000


def sample_features(backbone, root: Path, sequence: str, every: int) -> np.ndarray:
    """Features (n, D) of ``POINTS_PER_SCAN`` points of every ``every``-th scan."""
    data = open_dataset(root, sequence)
    out = []
    for i in range(0, len(data), every):
        features = backbone(data.frame(i)[0], path=data.scan_path(i), frame=i)
        rng = np.random.default_rng(i)
        out.append(features[rng.choice(len(features), min(POINTS_PER_SCAN, len(features)), False)])
    return np.concatenate(out)


def shifts(reference: np.ndarray, compared: np.ndarray) -> np.ndarray:
    """|mean(compared) - mean(reference)| / std(reference) per feature (D,)."""
    scale = np.maximum(reference.std(axis=0), 1e-9)
    return np.abs(compared.mean(axis=0) - reference.mean(axis=0)) / scale


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--reference", required=True, help="comma-separated sequence ids")
    parser.add_argument("--compare", required=True, help="comma-separated sequence ids")
    parser.add_argument("--backbone", default="geometric")
    parser.add_argument("--options", default="{}", help="the backbone's options, as YAML")
    parser.add_argument("--every", type=int, default=10)
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.json and OUT.md")
    args = parser.parse_args()
    options = parse_mapping(args.options)
    if options is None:
        raise SystemExit(f"--options must be a YAML mapping, not {args.options!r}")
    backbone = get_backbone(args.backbone, **options)
    names = backbone.feature_names
    ref = np.concatenate(
        [sample_features(backbone, args.data, s, args.every) for s in args.reference.split(",")]
    )
    rows = {}
    for seq in args.compare.split(","):
        d = shifts(ref, sample_features(backbone, args.data, seq, args.every))
        rows[seq] = {"mean": float(d.mean()), "features": dict(zip(names, d.tolist(), strict=True))}
        top = max(rows[seq]["features"], key=rows[seq]["features"].get)
        print(f"{seq}: mean {d.mean():.2f}, largest {top} {d.max():.2f}", flush=True)
    command = "python " + " ".join(
        shlex.quote(a)
        for a in ["experiments/invariant_features/probe_feature_shift.py", *sys.argv[1:]]
    )
    meta = {"command": command, "commit": commit(), "backbone": [backbone.name, backbone.options()]}
    write_atomic(args.out.with_suffix(".json"), json.dumps({**meta, "sequences": rows}, indent=1))
    lines = [f"`{command}` at `{meta['commit']}`: mean absolute shift of each feature's mean, in "
             "the reference scans' standard deviations.", "",
             "| sequence | mean over features | largest |", "|---|---|---|"]  # fmt: skip
    for seq, row in rows.items():
        top = max(row["features"], key=row["features"].get)
        lines.append(f"| {seq} | {row['mean']:.2f} | {top} {row['features'][top]:.2f} |")
    write_atomic(args.out.with_suffix(".md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
