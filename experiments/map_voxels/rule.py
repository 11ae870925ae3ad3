"""PLAN.md's rules 1-3 from make_tables' tables.json files: the candidate's runs against the
current map's (experiments/fast_features' for 401/403/404, map_voxels_base's for 402/405).

    python experiments/map_voxels/rule.py results/map_voxels_05 results/fast_features \
        results/map_voxels_base
"""

import json
import sys
from pathlib import Path


def cells(path: Path, label: str) -> dict[tuple[str, str], float]:
    """(world, data root) -> t_err (%) of the label's runs (GICP, or the one GLOAM label)."""
    runs = json.loads((path / "tables.json").read_text())["runs"]
    name = label if label in runs else next(k for k in runs if k.startswith("GLOAM"))
    return {(w, r["data"]): v["t_err"] for r in runs[name] for w, v in r["worlds"].items()}


candidate, *baselines = (Path(p) for p in sys.argv[1:])
for label in ("GICP", "GLOAM"):
    new = cells(candidate, label)
    old = {}
    for b in baselines:
        old |= cells(b, label)
    ratios = {k: new[k] / old[k] for k in sorted(new) if k in old}
    print(f"{label}: {len(ratios)} cells, mean ratio {sum(ratios.values()) / len(ratios):.3f}")
    for world in sorted({w for w, _ in ratios}):
        r = [v for (w, _), v in ratios.items() if w == world]
        print(f"  {world}: " + " / ".join(f"{x:.3f}" for x in r) + f"  mean {sum(r) / len(r):.3f}")
gicp, gloam = cells(candidate, "GICP"), cells(candidate, "GLOAM")
for world in sorted({w for w, _ in gicp}):
    g = [gloam[k] / gicp[k] for k in gicp if k[0] == world]
    print(f"candidate GLOAM / GICP {world}: {sum(g) / len(g):.3f}")
