"""Calibrate degeneracy detection: the odometry's per-frame conditioning on scenes that leave a
direction unconstrained (a tunnel, a corridor, a highway between noise barriers, a bare plane)
and on healthy simulated drives (urban, suburban, highway), and the flag rates per threshold.

    python experiments/degeneracy_calibration/calibrate_degeneracy.py --out degeneracy.json

Writes every frame's condition (the weakest over the strongest constraint, see
``gloam_jax.registration.conditioning``) and support (planar points facing the weakest
direction) per scene, and for a grid of thresholds and supports the share of frames flagged on
each scene; a setting detects the degenerate scenes (flagged frames, to be high) without
flagging the healthy ones (to be low). Scans are simulated in memory.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from gloam_jax.io import write_atomic
from gloam_jax.odometry import Odometry, OdometryConfig
from gloam_jax.simulate import (
    ErrorSwitches,
    SweepSimulator,
    build_scene,
    get_sensor,
    procedural_trajectory,
)
from gloam_jax.simulate.degenerate import DEGENERATE_KINDS, degenerate_scene, straight_trajectory

HEALTHY = ("urban", "suburban", "highway")
THRESHOLDS = (2e-4, 5e-4, 1e-3, 2e-3, 3e-3, 4e-3, 5e-3)
SUPPORTS = (1.0, 2.0, 3.0, 4.0, 6.0, float("inf"))  # inf: the condition alone


def drive(kind: str, frames: int, seed: int, beams: int, columns: int,
          config: OdometryConfig = OdometryConfig()) -> Odometry:  # fmt: skip
    """The odometry after registering every frame of one simulated drive: a degenerate scene
    on a straight 10 m/s drive, or a procedural drive of a healthy style."""
    sensor = get_sensor("hdl64", num_beams=beams, num_columns=columns)
    if kind in DEGENERATE_KINDS:
        traj = straight_trajectory(frames, 10.0)
        scene = degenerate_scene(kind, traj, sensor.mount_height)
    else:
        traj = procedural_trajectory(frames, seed)
        scene = build_scene(traj, kind, seed, mount_height=sensor.mount_height)
    sim = SweepSimulator(scene, traj, sensor, seed, ErrorSwitches())
    sim.plan_padding(np.unique(np.linspace(0, frames - 1, 6).astype(int)))
    odometry = Odometry(config)
    for i in range(frames):
        scan = sim.frame(i)
        odometry.register_frame(scan.points, scan.times, 0.1)
    return odometry


def conditions(kind: str, frames: int, seed: int, beams: int, columns: int) -> list[list[float]]:
    """The condition and support of every registered frame of one simulated drive."""
    odometry = drive(kind, frames, seed, beams, columns)
    return [[s.condition, s.support] for s in odometry.status[1:]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--degenerate-frames", type=int, default=40)
    parser.add_argument("--healthy-frames", type=int, default=80)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--beams", type=int, default=32)
    parser.add_argument("--columns", type=int, default=1024)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    out = json.loads(args.out.read_text()) if args.out.is_file() else {"scenes": {}}
    for kind in (*DEGENERATE_KINDS, *HEALTHY):
        if kind in out["scenes"]:  # resumes: scenes already measured are kept
            continue
        frames = args.degenerate_frames if kind in DEGENERATE_KINDS else args.healthy_frames
        t0 = time.perf_counter()
        values = conditions(kind, frames, args.seed, args.beams, args.columns)
        out["scenes"][kind] = {"degenerate": kind in DEGENERATE_KINDS, "frames": values}
        c, s = np.asarray(values).T
        print(
            f"{kind}: {len(values)} frames, condition {c.min():.2e}..{c.max():.2e}, support "
            f"{s.min():.1f}..{s.max():.1f}, {time.perf_counter() - t0:.0f} s",
            flush=True,
        )
        write_atomic(args.out, json.dumps(out, indent=1))
    out["settings"] = vars(args) | {"out": str(args.out)}
    # The weakest direction decides whether any is weak: (condition, support) of that one.
    out["flag_rates"] = {
        f"{t:g}, {m:g}": {
            k: float(np.mean([c < t and s < m for c, s in v["frames"]]))
            for k, v in out["scenes"].items()
        }
        for t in THRESHOLDS for m in SUPPORTS
    }  # fmt: skip
    write_atomic(args.out, json.dumps(out, indent=1))
    for key, rates in out["flag_rates"].items():
        print(key, "  ".join(f"{k} {100 * r:.0f} %" for k, r in rates.items()))


if __name__ == "__main__":
    main()
