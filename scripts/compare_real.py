"""Real scans without ground truth: each method's frame-to-frame motion against small_gicp's.

    python scripts/compare_real.py ../shared/data/real_kitti16 --methods gicp,gloam,gloam_net \
        --out experiments/real_agreement/real_agreement.json

Every method runs ``gloam run``'s pipeline with ``configs/<method>.yaml`` on the same scans
(any dataset ``gloam run`` reads); the reference is small_gicp's GICP frame to frame (0.25 m
voxels, 10 neighbours, 1 m correspondences, constant-velocity guess). Agreement is not
accuracy: with no ground truth, it says only that a method tracks the motion as a mature
peer does. Writes JSON and a markdown table (``--out`` with ``.md``) with the command and
commit.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from make_tables import commit

from gloam_jax import io, metrics
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset
from gloam_jax.pipeline import run_dataset, select_frames


def small_gicp_odometry(scans: list[np.ndarray]) -> np.ndarray:
    """small_gicp's GICP frame to frame (0.25 m voxels, constant-velocity guess): (N, 4, 4)."""
    import small_gicp

    poses, velocity, previous = [np.eye(4)], np.eye(4), None
    for scan in scans:
        points = scan[:, :3].astype(np.float64)
        r = np.linalg.norm(points, axis=1)
        cloud, tree = small_gicp.preprocess_points(
            points[(r > 3) & (r < 100)], downsampling_resolution=0.25, num_neighbors=10
        )
        if previous is not None:
            result = small_gicp.align(
                previous[0], cloud, previous[1], init_T_target_source=velocity,
                registration_type="GICP", max_correspondence_distance=1.0,
            )  # fmt: skip
            velocity = result.T_target_source
            poses.append(poses[-1] @ velocity)
        previous = (cloud, tree)
    return np.stack(poses)


def step_differences(ours: np.ndarray, theirs: np.ndarray) -> dict[str, float]:
    """Frame-to-frame translation (cm) and rotation (deg) differences of two (N, 4, 4) runs."""
    a, b = io.frame_motions(ours), io.frame_motions(theirs)
    dt = 100 * np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return {"trans_cm_mean": float(dt.mean()), "trans_cm_max": float(dt.max()),
            "rot_deg_mean": float(np.degrees(np.arccos(cos)).mean()),
            "path_m": float(metrics.path_lengths(ours)[-1])}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--sequence", default=None)
    parser.add_argument("--methods", default="gicp,gloam,gloam_net")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    dataset = open_dataset(args.data, args.sequence)
    frames = select_frames(len(dataset))
    theirs = small_gicp_odometry([dataset.frame(i)[0] for i in frames])
    rows = {"small_gicp": {"path_m": float(metrics.path_lengths(theirs)[-1])}}
    for method in args.methods.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            result = run_dataset(dataset, load_config(method), tmp, frames)
            ours = io.read_kitti_poses(Path(tmp) / f"{dataset.name}_poses_lidar_kitti.txt")
        rows[method] = {**step_differences(ours, theirs),
                        "median_ms_per_frame": result["median_ms_per_frame"],
                        "warnings": result["warnings"]}  # fmt: skip
        print(method, json.dumps(rows[method]), flush=True)

    record = {"command": "python " + " ".join(sys.argv), "commit": commit(),
              "data": str(args.data), "frames": len(frames), "rows": rows}  # fmt: skip
    io.write_atomic(args.out, json.dumps(record, indent=1))
    lines = [f"`{record['command']}` at `{record['commit']}`", "",
             "| method | translation difference per frame, mean / max (cm) | rotation "
             "difference per frame, mean (deg) | path (m) |", "|---|---|---|---|"]  # fmt: skip
    for method, r in rows.items():
        if method == "small_gicp":
            lines.append(f"| small_gicp (reference) | - | - | {r['path_m']:.2f} |")
            continue
        lines.append(f"| {method} | {r['trans_cm_mean']:.2f} / {r['trans_cm_max']:.2f} | "
                     f"{r['rot_deg_mean']:.3f} | {r['path_m']:.2f} |")  # fmt: skip
    io.write_atomic(args.out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
