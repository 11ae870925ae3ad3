"""`gicp` on the first FRAMES of a drive: registration ms a frame, the map wait and the poses
(to compare the code of two worktrees, interleaved):

    PYTHONPATH=/work/wt_mv0 python experiments/map_rows/probe_ab.py data/long 409 300 runs/ab_base
    PYTHONPATH=. python experiments/map_rows/probe_ab.py data/long 409 300 runs/ab_rows
    cmp runs/ab_base/409_poses_kitti.txt runs/ab_rows/409_poses_kitti.txt
"""

import sys

from gloam_jax import pipeline
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset

root, sequence, frames, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
dataset = open_dataset(root, sequence)
m = pipeline.run_dataset(dataset, load_config("gicp"), out,
                         pipeline.select_frames(len(dataset), 0, frames))  # fmt: skip
stages = {k: v["median"] for k, v in m["stage_ms"].items()}
print(out, "registration", round(m["median_ms_per_frame"], 1), "map wait", stages["map"])
