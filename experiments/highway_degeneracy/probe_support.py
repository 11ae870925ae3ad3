"""Candidate degeneracy measures per registered frame, on the calibration's degenerate scenes,
its healthy procedural drives and the first frames of long validation worlds.

    python experiments/highway_degeneracy/probe_support.py --out support.json

For each frame the odometry registers (flag off, so every scene runs unremapped), the
constraint matrix's weakest direction v (coordinates (rho, lever_arm * phi)) and, besides the
condition (weakest over strongest eigenvalue), how much of the planar points' weight *faces*
v: sum of planarity over points whose scaled row r makes |r.v| / |r| above 0.3 / 0.5. Normal
noise on a tunnel's walls tilts every row a little towards v (the condition's floor); only real
structure (a car's back, a sign, a post) tilts rows a lot.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import gloam_jax.registration as reg
from gloam_jax.datasets import open_dataset
from gloam_jax.gicp import GICPConfig
from gloam_jax.io import write_atomic
from gloam_jax.odometry import Odometry, OdometryConfig
from gloam_jax.simulate.degenerate import DEGENERATE_KINDS

# The calibration's drives (the same scenes, seeds and sensors).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "degeneracy_calibration"))
from calibrate_degeneracy import drive  # noqa: E402

COSINES = (0.3, 0.5, 0.7, 0.85, 0.95)
RECORDS: list[dict] = []
_conditioning = reg.conditioning


def _recording_conditioning(rows, weight, lever_arm, threshold, support):
    """registration.conditioning, recording the candidate measures of its rows."""
    scaled = rows / np.array([1.0, 1.0, 1.0, lever_arm, lever_arm, lever_arm])
    values, vectors = np.linalg.eigh((scaled * weight[:, None]).T @ scaled)
    v = vectors[:, 0]
    proj = np.abs(scaled @ v) / np.maximum(np.linalg.norm(scaled, axis=1), 1e-12)
    RECORDS.append(
        {
            "condition": float(max(values[0], 0) / values[-1]),
            "lambda_min": float(values[0]),
            "weight": float(weight.sum()),
            **{f"support_{c:g}": float(weight[proj > c].sum()) for c in COSINES},
            "v": np.round(v, 3).tolist(),
        }
    )
    return _conditioning(rows, weight, lever_arm, threshold, support)


def run_simulated(kind: str, frames: int, seed: int, beams: int, columns: int) -> list[dict]:
    start = len(RECORDS)
    flag_off = OdometryConfig(gicp=GICPConfig(degeneracy_threshold=1e-9))
    drive(kind, frames, seed, beams, columns, flag_off)
    return RECORDS[start:]


def run_recorded(root: str, sequence: str, frames: int) -> list[dict]:
    data = open_dataset(Path(root), sequence)
    odometry = Odometry(OdometryConfig(gicp=GICPConfig(degeneracy_threshold=1e-9)))
    start = len(RECORDS)
    for i in range(frames):
        scan, _ = data.frame(i)  # raw scans without per-point times, as users run them
        odometry.register_frame(scan, None, 0.1)
    return RECORDS[start:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--long-frames", type=int, default=120)
    args = parser.parse_args()
    reg.conditioning = _recording_conditioning
    out = json.loads(args.out.read_text()) if args.out.is_file() else {}
    cases = [(f"{k}{b}", ("sim", k, b, 1024)) for b in (32, 16, 64)
             for k in (*DEGENERATE_KINDS, "highway", "urban")]  # fmt: skip
    cases += [(f"{k}64x2048", ("sim", k, 64, 2048)) for k in ("tunnel", "corridor", "highway")]
    cases += [(f"long{s}_d{d}", ("long", root, s)) for d, root in ((0, "data/long"),
              (1, "data/long_d1")) for s in ("401", "402", "403", "405")]  # fmt: skip
    for name, case in cases:
        if name in out:
            continue
        if case[0] == "sim":
            rows = run_simulated(case[1], args.frames, 3, case[2], case[3])
        else:
            rows = run_recorded(case[1], case[2], args.long_frames)
        out[name] = rows
        c = np.array([r["condition"] for r in rows])
        line = "  ".join(f">{k:g} {np.min(v):.1f}..{np.max(v):.1f}" for k in COSINES
                         if (v := np.array([r[f"support_{k:g}"] for r in rows])).size)  # fmt: skip
        print(f"{name}: condition {c.min():.2e}..{c.max():.2e}  support {line}", flush=True)
        write_atomic(args.out, json.dumps(out))


if __name__ == "__main__":
    main()
