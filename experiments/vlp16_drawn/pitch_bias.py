"""Per-frame rotation error of each run on the VLP-16 long validation cells: the mean (a bias
that drifts) and the spread (noise that averages out), about each camera axis.

KITTI's scored poses are camera-0 poses (x right, y down, z forward), so the rotation vector's
x part is pitch, y yaw, z roll. Reads make_tables' runs under --out; writes pitch_bias.md.

    python experiments/vlp16_drawn/pitch_bias.py results/vlp16_model
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from gloam_jax.io import read_kitti_poses

WORLDS = ("402", "406", "407", "408")
DRAWS = ("long", "long_d1")


def frame_errors(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Rotation error (F-1, 3) of each frame's motion, millidegrees, about camera x, y, z."""
    d_est = np.linalg.inv(est[:-1]) @ est[1:]
    d_gt = np.linalg.inv(gt[:-1]) @ gt[1:]
    err = np.linalg.inv(d_gt) @ d_est
    return Rotation.from_matrix(err[:, :3, :3]).as_rotvec(degrees=True) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="make_tables' --out")
    args = parser.parse_args()
    labels = sorted(p.name for p in args.out.iterdir() if p.is_dir())
    labels = [x for x in labels if x == "GICP" or x.startswith("GLOAM")]
    lines = [
        f"Per-frame rotation error on the VLP-16 long validation cells ({args.out}): mean / "
        "sample std, millidegrees a frame; pitch is about camera x, yaw about y.",
        "",
        "| cell | run | pitch mean | yaw mean | roll mean | pitch std | t_err (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    for world in WORLDS:
        for draw in DRAWS:
            for label in labels:
                for run in sorted(glob.glob(f"{args.out}/{label}/*/{draw}-*/{world}")):
                    run = Path(run)
                    metrics = run / "metrics.json"
                    t_err = (
                        json.loads(metrics.read_text()).get("t_err_percent")
                        if metrics.is_file()
                        else None
                    )
                    if t_err is None:  # a run not finished, or not scored yet
                        continue
                    e = frame_errors(
                        read_kitti_poses(run / f"{world}_poses_kitti.txt"),
                        read_kitti_poses(run / f"{world}_gt_kitti.txt"),
                    )
                    m, s = e.mean(0), e.std(0, ddof=1)
                    model = run.parent.parent.name
                    name = label if model == "-" else f"{label} {model}"
                    lines.append(
                        f"| {world} {draw} | {name} | {m[0]:+.2f} | {m[1]:+.2f} | {m[2]:+.2f} "
                        f"| {s[0]:.1f} | {t_err:.3f} |"
                    )
    (Path(__file__).parent / "pitch_bias.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
