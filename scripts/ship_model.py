"""Choose a label's training seed on long validation and write it as a shipped model file.

    python scripts/ship_model.py results/long_val_step2/tables.json --label "GLOAM (a)" \\
        --worlds 401,403,404 --sensor-name hdl64 --out gloam_jax/data/gloam_hdl64.npz

Reads ``make_tables.py --split val_long``'s tables.json, or several (draws scored in separate
runs; ``--alias OLD=NEW`` where a model file was moved between them). For each of the label's
model files, its t_err over GICP's on the same world and simulation draw, averaged over
``--worlds`` x the draws; the file with the lowest mean is chosen. Prints every file's ratios;
with ``--out`` it writes the chosen file there with the selection in its provenance
(``selected_on``, ``selected_value``, ``selection``: every file's mean ratio, the worlds, draws
and commit) and its recorded sensors named ``--sensor-name``. ``--network FILE`` points a net
model at a network file (put it beside ``--out``, and the model names it relative to itself).
Listing the file in ``models.SHIPPED_MODELS`` is a code change of its own.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from make_tables import t_err_arrays

from gloam_jax.errors import InputError
from gloam_jax.io.files import read_text
from gloam_jax.models import load_model, save_model


def seed_ratios(tables: dict, label: str, worlds: list[str]) -> dict[str, dict[str, float]]:
    """Per model file of ``label``: its t_err over GICP's per (draw, world) cell, ``"data
    world"`` -> ratio (the cells of make_tables' Table III). One line naming what is missing
    where a cell has no run."""
    runs = tables["runs"]
    if label not in runs or "GICP" not in runs:
        raise InputError(None, f"tables.json has no runs of {label!r} and GICP (has {list(runs)})")
    for run in runs["GICP"] + runs[label]:
        missing = [w for w in worlds if w not in run["worlds"]]
        if missing:
            raise InputError(None, f"no run of world {missing[0]} on {run['data']} for "
                             f"{run['model'] or 'GICP'}")  # fmt: skip
    files, model, gicp = t_err_arrays(runs, tuple(worlds), label)
    ratio = model / gicp[None]
    draws = [r["data"] for r in runs["GICP"]]
    cells = [(j, k, f"{d} {w}") for j, d in enumerate(draws) for k, w in enumerate(worlds)]
    return {f: {name: float(ratio[i, j, k]) for j, k, name in cells} for i, f in enumerate(files)}


def merge_tables(tables: list[dict], aliases: dict[str, str]) -> dict:
    """One record of several tables.json of the same split, each scoring other draws: the runs
    of each label joined, model paths renamed by ``aliases`` (old -> new)."""
    splits = {t["split"] for t in tables}
    if len(splits) > 1:
        raise InputError(None, f"the tables score different splits: {sorted(splits)}")
    data = [d for t in tables for d in t["data"]]
    if len(set(data)) < len(data):
        raise InputError(None, f"a data root is scored in more than one table: {data}")
    runs: dict[str, list[dict]] = {}
    for t in tables:
        for label, rows in t["runs"].items():
            renamed = [{**r, "model": aliases.get(r["model"], r["model"])} for r in rows]
            runs.setdefault(label, []).extend(renamed)
    if len(tables) == 1:
        return {**tables[0], "runs": runs}
    joined = {k: [t[k] for t in tables] for k in ("commit", "date")}
    return {"split": splits.pop(), "data": data, "runs": runs, **joined}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", type=Path, nargs="+")
    parser.add_argument("--label", required=True, help='a row of the tables, "GLOAM (a)"')
    parser.add_argument("--worlds", required=True, help="comma-separated ids")
    parser.add_argument("--sensor-name", help="name for the file's recorded sensors")
    parser.add_argument("--out", type=Path, help="write the chosen file here")
    moved = "a model file's path in an earlier table, and its path now"
    parser.add_argument("--alias", action="append", default=[], metavar="OLD=NEW", help=moved)
    parser.add_argument("--network", type=Path, help="the network file the written model runs")
    args = parser.parse_args(argv)
    bad = [a for a in args.alias if a.count("=") != 1]
    if bad:
        raise InputError(None, f"--alias takes OLD=NEW, got {bad[0]!r}")
    if args.network is not None and not args.network.is_file():
        raise InputError(args.network, "no such network file")
    aliases = dict(a.split("=") for a in args.alias)
    tables = merge_tables([json.loads(read_text(t)[0]) for t in args.tables], aliases)
    worlds = args.worlds.split(",")
    ratios = seed_ratios(tables, args.label, worlds)
    means = {path: float(np.mean(list(cells.values()))) for path, cells in ratios.items()}
    for path, cells in ratios.items():
        detail = ", ".join(f"{k} {v:.3f}" for k, v in cells.items())
        print(f"{path}: mean t_err / GICP {means[path]:.4f} ({detail})")
    chosen = min(means, key=means.get)
    print(f"chosen: {chosen}")
    if args.out is None:
        return
    model = load_model(chosen)
    selection = {"tables": [str(t) for t in args.tables], "label": args.label, "worlds": worlds,
                 "data": tables["data"], "commit": tables["commit"], "date": tables["date"],
                 "files": means}  # fmt: skip
    provenance = {**model.provenance, "selected_on": tables["split"],
                  "objective": "mean t_err / GICP", "selected_value": means[chosen],
                  "validation_gicp": 1.0, "selection": selection}  # fmt: skip
    sensors = model.sensors
    if args.sensor_name and sensors is not None:
        sensors = tuple(dataclasses.replace(s, name=args.sensor_name) for s in sensors)
    options = model.backbone_options
    if args.network is not None:
        options = {**options, "weights": str(args.network)}
    shipped = dataclasses.replace(model, provenance=provenance, sensors=sensors,
                                  backbone_options=options)  # fmt: skip
    save_model(args.out, shipped)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
