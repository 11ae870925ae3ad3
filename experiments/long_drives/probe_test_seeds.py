"""The HDL-64 candidate's seed spread on the long test split: seeds 0 and 1 from their own
make_tables.py --out, seed 2 from the `model: default` runs (the shipped gloam_hdl64.npz holds
seed 2's weights), Table III (make_tables.gains) over the worlds and draws the seeds ran on.

    python experiments/long_drives/probe_test_seeds.py results/test_long results/test_long_seeds \
        experiments/long_drives/test_seeds
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
from make_tables import gains, gains_markdown, summarize  # noqa: E402

SEED_2 = "seed 2 (gloam_hdl64.npz, via model: default)"


def main() -> None:
    default_out, seeds_out, out = (Path(a) for a in sys.argv[1:4])
    default = json.loads((default_out / "tables.json").read_text())
    seeds = json.loads((seeds_out / "tables.json").read_text())
    worlds = tuple(seeds["worlds"])  # the HDL-64 worlds
    draws = sorted({r["data"] for r in seeds["runs"]["GLOAM (a)"]})

    def keep(runs: list[dict], model: str | None = None) -> list[dict]:
        return [
            {**r, "model": model or r["model"], "worlds": {w: r["worlds"][w] for w in worlds}}
            for r in runs
            if r["data"] in draws
        ]

    runs = {
        "GICP": keep(default["runs"]["GICP"]),
        "GLOAM (a)": keep(seeds["runs"]["GLOAM (a)"]) + keep(default["runs"]["GLOAM (d)"], SEED_2),
    }
    record = {"split": "test_long", "worlds": list(worlds), "runs": runs, "data": draws}
    record["summary"] = {label: summarize(rs, worlds) for label, rs in runs.items()}
    record["gains"] = gains(record, "GLOAM (a)")
    record["per_run_ratio"] = [
        {"model": r["model"], "data": r["data"],
         "ratio": {w: r["worlds"][w]["t_err"] / g["worlds"][w]["t_err"] for w in worlds}}
        for r in runs["GLOAM (a)"] for g in runs["GICP"] if g["data"] == r["data"]
    ]  # fmt: skip
    out.with_suffix(".json").write_text(json.dumps(record, indent=2) + "\n")
    lines = [f"draws: {', '.join(draws)}; worlds: {', '.join(worlds)}", "",
             "| model | draw | " + " | ".join(worlds) + " |",
             "|---|---|" + "---|" * len(worlds)]  # fmt: skip
    for row in record["per_run_ratio"]:
        cells = [f"{100 * (row['ratio'][w] - 1):+.1f} %" for w in worlds]
        lines.append(f"| {row['model']} | {row['data']} | " + " | ".join(cells) + " |")
    lines += gains_markdown("GLOAM (a)", record["gains"])
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
