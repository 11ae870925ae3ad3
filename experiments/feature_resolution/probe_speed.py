"""Milliseconds of the geometric backbone per scan at its shipped setting (0.25 m voxels, k =
10 and 30) against coarser ones nearer the registration's resolution (0.5 m voxels): the
speed half of issue 42's item 1, before any model is trained on them.

    python experiments/feature_resolution/probe_speed.py data/long 403 --frames 20 \
        --out experiments/feature_resolution/speed.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from gloam_jax import io
from gloam_jax.features.geometric import GeometricBackbone

SETTINGS = {
    "shipped (0.25 m; k 10, 30)": {},
    "0.25 m; k 10": {"scales": (10,)},
    "0.5 m; k 6, 12": {"voxel_size": 0.5, "scales": (6, 12)},
    "0.5 m; k 10": {"voxel_size": 0.5, "scales": (10,)},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("sequence")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    seq = io.KittiSequence(args.data, args.sequence)
    scans = [seq.scan(i) for i in range(0, len(seq), max(len(seq) // args.frames, 1))]
    result = {"data": str(args.data), "sequence": args.sequence, "scans": len(scans)}
    for name, options in SETTINGS.items():
        backbone = GeometricBackbone(**options)
        backbone(scans[0])  # warm caches
        ms = []
        for scan in scans:
            t0 = time.perf_counter()
            backbone(scan)
            ms.append(1e3 * (time.perf_counter() - t0))
        result[name] = {"median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95))}
        print(f"{name}: median {np.median(ms):.1f} ms, p95 {np.percentile(ms, 95):.1f} ms")
    io.write_atomic(args.out, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
