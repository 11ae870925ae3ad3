"""Feature extraction time per scan: the ``geometric`` and ``net`` backbones in one run.

    python scripts/bench_backbones.py data/netodo --sequence 00 --out results/bench_backbones.json

Each backbone extracts features of the same full scans (raw ``(N, 4)``, as the odometry
hands them over), taking turns scan by scan so that both see the same machine load; the
first scan of each is a warm-up (the net compiles for its size bucket there) and is not
counted. Prints a markdown table (median and mean ms per scan, and the ratio net /
geometric) and writes it with the machine, the commit and the command to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np
from make_tables import commit, machine

from gloam_jax.features import get_backbone
from gloam_jax.io import KittiSequence, write_atomic


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root")
    parser.add_argument("--sequence", default="00")
    parser.add_argument("--scans", type=int, default=10)
    parser.add_argument("--weights", default="default", help="the net backbone's weights")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    seq = KittiSequence(args.root, args.sequence)
    frames = np.linspace(0, len(seq) - 1, args.scans + 1).astype(int)  # +1: the warm-up
    backbones = {"geometric": get_backbone("geometric"),
                 "net": get_backbone("net", weights=args.weights)}  # fmt: skip
    times: dict[str, list[float]] = {name: [] for name in backbones}
    points = []
    for k, i in enumerate(frames):
        scan = seq.scan(i)
        points.append(len(scan))
        for name, backbone in backbones.items():
            t0 = time.perf_counter()
            backbone(scan)
            if k > 0:
                times[name].append(1000 * (time.perf_counter() - t0))
    rows = {name: {"median_ms": float(np.median(t)), "mean_ms": float(np.mean(t))}
            for name, t in times.items()}  # fmt: skip
    ratio = rows["net"]["median_ms"] / rows["geometric"]["median_ms"]
    table = ["| backbone | median ms / scan | mean ms / scan |", "|---|---|---|"]
    table += [f"| {n} | {r['median_ms']:.0f} | {r['mean_ms']:.0f} |" for n, r in rows.items()]
    table.append(f"\nnet / geometric (medians): {ratio:.2f}; {args.scans} scans of "
                 f"{int(np.mean(points[1:]))} points on average")  # fmt: skip
    print("\n".join(table))
    if args.out:
        record = {
            "command": "python " + " ".join(sys.argv),
            "commit": commit(),
            "machine": machine(),
            "jax_device": jax.devices()[0].device_kind,
            "scans": args.scans,
            "mean_points": float(np.mean(points[1:])),
            "backbones": rows,
            "ratio_net_geometric": ratio,
        }
        write_atomic(args.out, json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
