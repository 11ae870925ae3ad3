"""Simulation speed and points per frame, per sensor and scene style.

    python scripts/bench_simulator.py --frames 100 --out /tmp/simbench

Drives along a KITTI ground-truth window when ``--trajectory`` is given (default: the shared
sequence 00 poses if present, else a procedural drive). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from gloam_jax.simulate import simulate

DEFAULT_POSES = Path(__file__).resolve().parents[2] / "shared/data/kitti_gt_poses/00.txt"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--out", type=Path, default=Path("/tmp/gloam_simbench"))
    parser.add_argument("--trajectory", type=Path, default=DEFAULT_POSES)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--sensors", default="hdl64,vlp16,os1-64")
    parser.add_argument("--styles", default="urban")
    args = parser.parse_args()
    trajectory = args.trajectory if args.trajectory.exists() else None
    rows = []
    for style in args.styles.split(","):
        for sensor in args.sensors.split(","):
            out = args.out / f"{sensor}_{style}"
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            seq_dir = simulate(out, trajectory=trajectory, start=args.start, frames=args.frames,
                               sensor=sensor, style=style, seed=0)  # fmt: skip
            elapsed = time.perf_counter() - t0
            ppf = json.loads((seq_dir / "simulation.json").read_text())["points_per_frame"]
            rows.append((sensor, style, args.frames, elapsed, ppf))
            print(f"{sensor} {style}: {elapsed:.1f} s", flush=True)
    print("\n| sensor | style | frames | wall time (s) | frames/s | points/frame (mean, min-max) |")
    print("|---|---|---|---|---|---|")
    for sensor, style, n, elapsed, ppf in rows:
        print(f"| {sensor} | {style} | {n} | {elapsed:.1f} | {n / elapsed:.2f} | "
              f"{ppf['mean']:.0f} ({ppf['min']}-{ppf['max']}) |")  # fmt: skip


if __name__ == "__main__":
    main()
