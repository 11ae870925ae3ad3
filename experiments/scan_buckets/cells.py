"""Each cell's t_err change against the reference runs, for GICP and the model, and the
plan's rule (a): every cell within 1 %, the model's mean ratio to GICP at most 0.801.

    python experiments/scan_buckets/cells.py results/shared_knn_d2 results/scan_buckets_d2 \
        results/shared_knn_d3 results/scan_buckets_d3
"""

import json
import sys
from pathlib import Path

LABELS = ("GICP", "GLOAM (grid)")


def cells(out: Path, label: str) -> dict[tuple[str, str], float]:
    """t_err (%) per (world, data folder) of one method's runs under a make_tables --out."""
    found = {}
    for metrics in sorted((out / label).glob("*/*/*/metrics.json")):
        record = json.loads(metrics.read_text())
        if "t_err_percent" in record:
            key = (metrics.parent.name, metrics.parent.parent.name.split("-")[0])
            found[key] = record["t_err_percent"]
    return found


pairs = [(Path(a), Path(b)) for a, b in zip(sys.argv[1::2], sys.argv[2::2], strict=True)]
changes, ratios = [], []
for before, after in pairs:
    runs = {(label, side): cells(out, label) for label in LABELS
            for side, out in (("before", before), ("after", after))}  # fmt: skip
    for key in sorted(runs[("GICP", "after")]):
        line = [f"{key[0]} {key[1]}:"]
        for label in LABELS:
            old, new = runs[(label, "before")][key], runs[(label, "after")][key]
            changes.append(100 * (new / old - 1))
            line.append(f"{label} {old:.4f} -> {new:.4f} ({changes[-1]:+.2f} %)")
        model, gicp = runs[(LABELS[1], "after")][key], runs[("GICP", "after")][key]
        ratios.append(model / gicp)
        print("  ".join(line), f" model/GICP {ratios[-1]:.3f}")
worst = max(changes, key=abs)
mean = sum(ratios) / len(ratios)
print(
    f"largest change {worst:+.2f} %, model/GICP mean {mean:.4f}; rule (a) "
    f"{'met' if abs(worst) <= 1 and mean <= 0.801 else 'NOT met'}"
)
