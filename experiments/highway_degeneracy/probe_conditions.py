"""Per world, the constraint condition of every registered frame (frames.json of gloam runs)
and the share below candidate degeneracy thresholds.

    python experiments/highway_degeneracy/probe_conditions.py \
        "results/long_val_step1/GICP/-/long-*/*/frames.json"
"""

from __future__ import annotations

import glob
import json
import sys

import numpy as np

THRESHOLDS = (4e-3, 2e-3, 1e-3, 5e-4)


def main() -> None:
    print(
        "| run | frames | min | median | max | " + " | ".join(f"< {t:g}" for t in THRESHOLDS) + " |"
    )
    print("|---|---|---|---|---|" + "---|" * len(THRESHOLDS))
    for path in sorted(glob.glob(sys.argv[1])):
        record = json.load(open(path))
        rows = record["frames"] if isinstance(record, dict) else record
        c = np.array([r.get("condition") for r in rows], float)
        c = c[np.isfinite(c)]  # frame 0 is not registered
        shares = " | ".join(f"{100 * np.mean(c < t):.0f} %" for t in THRESHOLDS)
        print(
            f"| {path} | {len(c)} | {c.min():.2e} | {np.median(c):.2e} | {c.max():.2e} | {shares} |"
        )


if __name__ == "__main__":
    main()
