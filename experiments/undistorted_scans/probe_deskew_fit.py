"""Probe: does the fit to the local map tell motion-distorted scans from undistorted ones?

    python experiments/undistorted_scans/probe_deskew_fit.py data/val_worlds:202 \\
        data/val_worlds:204 ../shared/data/real_kitti16 --frames 16 \\
        --out experiments/undistorted_scans/probe_deskew_fit

Each dataset (``ROOT:SEQUENCE`` of the KITTI layout, or a folder of scans) runs twice through
``gicp.yaml``'s odometry without per-point times, deskewed from the azimuth and not deskewed.
For frames 3 on (after the start-up redo), it compares GICP's cost per inlier at each
solution (``FrameStatus.residual``): if azimuth deskew fits the map better on distorted scans
and worse on undistorted ones, a raw scan's distortion could be detected instead of assumed
from its layout (experiments/undistorted_scans/README.md). ``OUT.json`` / ``OUT.md``: per
dataset, the mean cost of each policy, their ratio and the frames on which azimuth fits better.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))  # the user tools it uses

import numpy as np  # noqa: E402
from make_tables import commit  # noqa: E402

from gloam_jax.config import build_dataclass, load_config  # noqa: E402
from gloam_jax.datasets import open_dataset  # noqa: E402
from gloam_jax.io.files import write_atomic  # noqa: E402
from gloam_jax.odometry import Odometry  # noqa: E402

FIRST = 3  # frames 0-2: the anchor and the start-up redo


def costs(path: str, frames: int, policy: str) -> np.ndarray:
    """GICP's cost per inlier of frames FIRST.. of ``path`` with deskew ``policy``."""
    root, _, sequence = path.partition(":")
    dataset = open_dataset(root, sequence or None)
    base = load_config("gicp")
    config = build_dataclass(type(base), {"preprocess": {"deskew": policy}}, policy, base=base)
    odometry = Odometry(config)
    for i in range(min(frames, len(dataset))):
        scan, _ = dataset.frame(i)  # per-point times left out: raw KITTI has none
        odometry.register_frame(scan, None, 0.1)
    return np.array([s.residual for s in odometry.status[FIRST:]])


def distortion(path: str) -> str:
    root, _, sequence = path.partition(":")
    world = Path(root) / "sequences" / sequence / "world.json"
    if sequence and world.is_file():
        return "distorted" if json.loads(world.read_text())["motion_distortion"] else "undistorted"
    return "not recorded"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="+", help="ROOT:SEQUENCE or a folder of scans")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.json and OUT.md")
    args = parser.parse_args()
    script = "experiments/undistorted_scans/probe_deskew_fit.py"
    command = f"python {script} {' '.join(args.data)} --frames {args.frames}"
    meta = {"command": f"{command} --out {args.out}", "commit": commit()}
    json_path = args.out.with_suffix(".json")
    results = json.loads(json_path.read_text())["results"] if json_path.exists() else {}
    for path in args.data:
        if path in results:  # resume
            continue
        azimuth, off = costs(path, args.frames, "azimuth"), costs(path, args.frames, "off")
        results[path] = {
            "scans": distortion(path),
            "cost_azimuth": float(azimuth.mean()),
            "cost_off": float(off.mean()),
            "ratio": float(azimuth.mean() / off.mean()),
            "azimuth_better": int(np.sum(azimuth < off)),
            "frames_compared": len(off),
        }
        print(path, json.dumps(results[path]), flush=True)
        write_atomic(json_path, json.dumps({**meta, "results": results}, indent=1))
    lines = [f"`{meta['command']}` at `{meta['commit']}`. Cost: GICP's per inlier, frames "
             f"{FIRST} on.", "", "| data | scans | cost, azimuth deskew | cost, off | ratio | "
             "frames azimuth fits better |", "|---|---|---|---|---|---|"]  # fmt: skip
    lines += [
        f"| {k} | {r['scans']} | {r['cost_azimuth']:.4f} | {r['cost_off']:.4f} | "
        f"{r['ratio']:.3f} | {r['azimuth_better']} / {r['frames_compared']} |"
        for k, r in results.items()
    ]
    write_atomic(args.out.with_suffix(".md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
