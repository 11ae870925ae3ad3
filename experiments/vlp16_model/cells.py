"""Per cell (world x draw) t_err of GICP and of each model file in a make_tables.py
tables.json, the ratio to GICP's, each file's mean ratio and its cells more than
make_tables.WORSE worse (the plan's rules 1 and 2), as a Markdown table.

    python experiments/vlp16_model/cells.py results/vlp16_model/tables.json > cells.md
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
from make_tables import WORSE, t_err_arrays  # noqa: E402

tables = json.loads(Path(sys.argv[1]).read_text())
worlds, runs = tuple(tables["worlds"]), tables["runs"]
draws = [f"d{i}" for i in range(len(runs["GICP"]))]  # in the order of --data
cells = [(d, w) for w in range(len(worlds)) for d in range(len(draws))]
print("| run | " + " | ".join(f"{worlds[w]} {draws[d]}" for d, w in cells)
      + " | mean ratio | cells > 1.02 |")  # fmt: skip
print("|---" * (len(cells) + 3) + "|")
rows = []
for label in (label for label in runs if label != "GICP"):
    files, model, gicp = t_err_arrays(runs, worlds, label)
    for name, t_err in zip(files, model, strict=True):
        ratio = t_err / gicp
        row = " | ".join(f"{t_err[d, w]:.3f} ({ratio[d, w]:.2f})" for d, w in cells)
        worse = int((ratio > 1 + WORSE).sum())
        rows.append(f"| {label} {name} | {row} | {ratio.mean():.3f} | {worse} |")
print("| GICP | " + " | ".join(f"{gicp[d, w]:.3f}" for d, w in cells) + " | | |")
print("\n".join(rows))
