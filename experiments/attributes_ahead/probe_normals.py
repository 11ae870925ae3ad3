"""How far variant A's covariances (k-NN on the voxel centres as measured, each normal turned
by the deskew's rotation at its point) are from the deskewed scan's own, on scans of a drive
deskewed with the ground truth's motion: the normals' angle (degrees), and where the large
ones lie (the sweep's last and first 5 ms: the seam).

    python experiments/attributes_ahead/probe_normals.py data/long 403 100 400 700
"""

import argparse

import numpy as np

from gloam_jax import geometry as geo
from gloam_jax import io
from gloam_jax.config import load_config
from gloam_jax.preprocess import deskew, voxel_centres
from gloam_jax.registration import build_cloud


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("root")
    parser.add_argument("sequence")
    parser.add_argument("frames", type=int, nargs="+")
    args = parser.parse_args()
    prep = load_config("gicp").preprocess
    seq = io.KittiSequence(args.root, args.sequence)
    gt = io.cam_to_lidar_poses(seq.gt_poses_cam, seq.Tr_cam_velo)
    for i in args.frames:
        xi = np.asarray(geo.se3_log_jit(np.linalg.inv(gt[i - 1]) @ gt[i]), np.float64)
        centres = voxel_centres(seq.scan(i), None, prep)
        moved = deskew(centres.points, centres.times, xi, 0.1)
        exact = build_cloud(moved, prep.num_neighbors)
        measured = build_cloud(centres.points, prep.num_neighbors)
        T = np.asarray(geo.se3_exp_jit((centres.times / 0.1)[:, None] * xi[None]), np.float64)
        turned = np.einsum("nij,nj->ni", T[:, :3, :3], measured.normals)
        cosine = np.clip(np.abs(np.sum(turned * exact.normals, axis=1)), 0.0, 1.0)
        angle = np.degrees(np.arccos(cosine))
        large = angle > 5
        seam = np.abs(centres.times) > 0.045
        print(f"frame {i}: {10 * np.linalg.norm(xi[:3]):.1f} m/s, "
              f"{np.degrees(10 * np.linalg.norm(xi[3:])):.1f} deg/s, {len(moved)} centres; "
              f"normal change median {np.median(angle):.3f} deg, 99th pct "
              f"{np.percentile(angle, 99):.2f}, over 5 deg {100 * large.mean():.2f} % "
              f"({100 * seam[large].mean():.0f} % of them at the seam, which holds "
              f"{100 * seam.mean():.0f} % of centres)")  # fmt: skip


if __name__ == "__main__":
    main()
