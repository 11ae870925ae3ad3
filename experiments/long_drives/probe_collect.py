"""Every finished run under a make_tables.py --out folder, as one JSON and a Markdown table of
t_err (%) per label, draw and world (runs still going are absent).

    python experiments/long_drives/probe_collect.py results/long_val_step2 \
        experiments/long_drives/step2_runs
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def main() -> None:
    root, out = Path(sys.argv[1]), Path(sys.argv[2])
    runs = {}
    for path in sorted(root.glob("*/*/*/*/table_metrics.json")):
        label, model, data, world = path.parts[-5:-1]
        runs[f"{label}|{model}|{data}|{world}"] = json.loads(path.read_text())
    out.with_suffix(".json").write_text(json.dumps(runs, indent=2) + "\n")
    lines = ["| label | model file | draw (data) | world | t_err (%) | degenerate frames |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for key, r in runs.items():
        label, model, data, world = key.split("|")
        lines.append(f"| {label} | {model} | {data} | {world} | {r['t_err']:.3f} | "
                     f"{r.get('degenerate_frames')} |")  # fmt: skip
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
