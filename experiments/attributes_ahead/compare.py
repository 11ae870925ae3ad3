"""Each cell's t_err against a reference make_tables.py output: GICP's change (%), and the
model's t_err ratio to GICP against the reference's.

    python experiments/attributes_ahead/compare.py REFERENCE_OUT OUT [OUT ...] [--label LABEL]
"""

import argparse
import json
from pathlib import Path

import numpy as np


def cells(out: Path, label: str) -> dict[tuple[str, str], float]:
    """t_err (%) per (world, data folder) of one method's runs under a make_tables --out."""
    found = {}
    for metrics in sorted((out / label).glob("*/*/*/metrics.json")):
        record = json.loads(metrics.read_text())
        if "t_err_percent" in record:
            found[(metrics.parent.name, metrics.parent.parent.name.split("-")[0])] = record[
                "t_err_percent"
            ]
    return found


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("reference", type=Path)
    parser.add_argument("outs", type=Path, nargs="+")
    parser.add_argument("--label", default="GLOAM (hdl64)")
    args = parser.parse_args()
    ref_gicp, ref_model = cells(args.reference, "GICP"), cells(args.reference, args.label)
    for out in args.outs:
        gicp, model = cells(out, "GICP"), cells(out, args.label)
        print(out)
        for key in sorted(gicp):
            change = 100 * (gicp[key] / ref_gicp[key] - 1)
            line = f"  {key[0]} {key[1]}: GICP {gicp[key]:.4f} ({change:+.2f} %)"
            if key in model:
                ratio, ref = model[key] / gicp[key], ref_model[key] / ref_gicp[key]
                line += f", model/GICP {ratio:.3f} (ref {ref:.3f})"
            print(line)
        change = np.mean([gicp[k] / ref_gicp[k] for k in gicp])
        ratios = [model[k] / gicp[k] for k in model]
        ref_ratios = [ref_model[k] / ref_gicp[k] for k in model]
        print(
            f"  mean GICP ratio {change:.4f}; model/GICP mean {np.mean(ratios):.3f} "
            f"(ref {np.mean(ref_ratios):.3f})"
            if ratios
            else f"  mean GICP ratio {change:.4f}"
        )


if __name__ == "__main__":
    main()
