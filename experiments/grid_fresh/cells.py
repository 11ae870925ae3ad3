"""Per cell (draw, world) of make_tables.py outputs: GICP's t_err and each model file's t_err
ratio to it; then each model's mean ratio, its worst cell, and the plan's rule for seed 1.

    python experiments/grid_fresh/cells.py results/grid_fresh_d2 results/grid_fresh_d3
"""

import argparse
import json
from pathlib import Path

import numpy as np

SHIPPED, CANDIDATE = "gloam_hdl64.npz", "grid_s1.npz"


def runs(out: Path) -> dict[tuple[str, str], dict[str, float]]:
    """t_err (%) per cell (data folder, world) and run (GICP, or a model's folder: the file's
    name and a hash of its path)."""
    found: dict[tuple[str, str], dict[str, float]] = {}
    for metrics in sorted(out.glob("*/**/metrics.json")):
        record = json.loads(metrics.read_text())
        if "t_err_percent" not in record:
            continue
        world, data = metrics.parent.name, metrics.parent.parent.name.rsplit("-", 1)[0]
        label = metrics.relative_to(out).parts[0]
        run = "GICP" if label == "GICP" else metrics.parent.parent.parent.name
        found.setdefault((data, world), {})[run] = record["t_err_percent"]
    return found


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("outs", type=Path, nargs="+")
    args = parser.parse_args()
    cells = {k: v for out in args.outs for k, v in runs(out).items()}
    models = sorted({r for v in cells.values() for r in v} - {"GICP"})
    print("| cell | GICP t_err (%) | " + " | ".join(models) + " |")
    print("|---" * (len(models) + 2) + "|")
    ratios = {m: [] for m in models}
    for key in sorted(cells):
        gicp = cells[key]["GICP"]
        row = []
        for m in models:
            ratio = cells[key][m] / gicp if m in cells[key] else np.nan
            ratios[m].append(ratio)
            row.append(f"{ratio:.3f}")
        print(f"| {key[1]} {key[0]} | {gicp:.3f} | " + " | ".join(row) + " |")
    means = {m: float(np.mean(r)) for m, r in ratios.items()}
    print("| mean ratio | | " + " | ".join(f"{means[m]:.3f}" for m in models) + " |")
    print("| worst cell | | " + " | ".join(f"{np.max(ratios[m]):.3f}" for m in models) + " |")
    grid = [m for m in models if m.startswith("grid_s")]
    shipped = next((m for m in models if m.startswith(SHIPPED)), None)
    candidate = next((m for m in models if m.startswith(CANDIDATE)), None)
    if grid:
        print(f"grid seeds' mean ratio {np.mean([means[m] for m in grid]):.3f} ({len(grid)})")
    if shipped and candidate:
        rule1 = means[candidate] <= means[shipped] + 0.03
        rule2 = np.max(ratios[candidate]) <= 1.02
        print(f"rule 1 ({CANDIDATE} {means[candidate]:.3f} <= {SHIPPED} {means[shipped]:.3f} "
              f"+ 0.03): {rule1}; rule 2 (no cell over 1.02): {rule2}; "
              f"cells: {len(ratios[candidate])}")  # fmt: skip


if __name__ == "__main__":
    main()
