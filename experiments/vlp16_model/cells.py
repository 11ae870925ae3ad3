"""Per cell (world x draw) t_err of GICP and each model file in a make_tables --out folder, the
ratio to GICP, each file's mean ratio and its cells above 1.02.

    python experiments/vlp16_model/cells.py results/vlp16_model
"""

import json
import sys
from collections import defaultdict
from pathlib import Path

root = Path(sys.argv[1])
cells = defaultdict(dict)  # (label, file) -> {(draw, world): t_err}
for path in sorted(root.glob("*/*/*/*/table_metrics.json")):
    label, file, data, world = path.parts[-5:-1]
    draw = "d1" if data.startswith("long_d1") or data.startswith("test_long_d1") else "d0"
    cells[(label, file)][(draw, world)] = json.loads(path.read_text())["t_err"]
gicp = next(v for (label, _), v in cells.items() if label == "GICP")
keys = sorted(gicp, key=lambda k: (k[1], k[0]))
print("| run | " + " | ".join(f"{w} {d}" for d, w in keys) + " | mean ratio | cells > 1.02 |")
print("|---" * (len(keys) + 3) + "|")
print("| GICP | " + " | ".join(f"{gicp[k]:.3f}" for k in keys) + " | | |")
for (label, file), v in cells.items():
    if label == "GICP":
        continue
    ratios = [v[k] / gicp[k] if k in v else None for k in keys]
    done = [r for r in ratios if r is not None]
    mean = sum(done) / len(done) if done else float("nan")
    worse = sum(r > 1.02 for r in done)
    row = " | ".join(f"{v[k]:.3f} ({r:.2f})" if r is not None else "-" for k, r in zip(keys, ratios))
    print(f"| {label} {file} | {row} | {mean:.3f} ({len(done)} cells) | {worse} |")
