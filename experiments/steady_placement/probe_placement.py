"""Where a method's voxel grid (and grid features) is built, frame by frame, and what each
placement costs (issue 42). Run from the repository root:

python experiments/steady_placement/probe_placement.py MODE METHOD FRAMES [OUT.npz]

MODE: ``policy`` (pipeline.VoxelPlacement as it is), ``ahead`` (always on the prefetch
thread) or ``main`` (always in the registration). val 403 d0 (data/long), run as
scripts/bench_odometry.py runs it. Prints the share of frames built ahead, the switches,
and the registration's ms (median / p95) split by where frame f's grid and f+1's were
built (the decision after frame j sets frame j+2's grid: the prefetch thread starts frame
j+1's fetch before frame j registers)."""

import sys

import numpy as np

sys.path.insert(0, "scripts")
import bench_odometry  # noqa: E402

from gloam_jax import io, pipeline  # noqa: E402
from gloam_jax.cli.common import use_compilation_cache  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402

STAGES = ("load", "features", "voxels", "deskew", "neighbours", "covariances", "solve", "map",
          "other")  # fmt: skip


def main() -> None:
    mode, method, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    use_compilation_cache()
    decide, decisions = pipeline.VoxelPlacement.update, []

    def update(self, stage_ms):
        decide(self, stage_ms)
        self.ahead = {"ahead": True, "main": False}.get(mode, self.ahead)
        decisions.append(self.ahead)

    pipeline.VoxelPlacement.update = update
    pipeline_open, setup_result = pipeline.open_odometry, {}

    def opened(*args, **kwargs):
        setup_result["value"] = pipeline_open(*args, **kwargs)
        return setup_result["value"]

    pipeline.open_odometry = opened

    class Counter:
        count = 0

    config = load_config(f"gloam_jax/configs/{method}.yaml")
    _, ms, extra = bench_odometry.run_ours(io.KittiSequence("data/long", "403"), n, config,
                                           None, Counter())  # fmt: skip
    status = setup_result["value"].odometry.status
    ms, ahead = np.asarray(ms), np.asarray(decisions)
    stage = np.array([[s.stage_ms.get(k, 0.0) for k in STAGES] for s in status])
    print(f"{mode} {method}: ahead {ahead[20:].mean():.2f} of frames, "
          f"{int(np.sum(ahead[1:] != ahead[:-1]))} switches; frame (loop) median / p95 "
          f"{extra['frame_ms']['median']:.1f} / {extra['frame_ms']['p95']:.1f} ms")  # fmt: skip
    for own in (True, False):
        for beside in (True, False):
            pair = (ahead[:-2] == own) & (ahead[1:-1] == beside)  # frame k at k - 2
            f = np.flatnonzero(pair[20:]) + 22  # after 22 frames of compilations
            if len(f):
                print(
                    f"  f's grid {'ahead' if own else 'in registration'}, f+1's "
                    f"{'ahead' if beside else 'in its registration'}: {len(f)} frames, "
                    f"registration {np.median(ms[f]):.1f} / {np.percentile(ms[f], 95):.1f} ms; "
                    f"stage means {dict(zip(STAGES, stage[f].mean(0).round(1), strict=True))}"
                )
    if len(sys.argv) > 4:
        np.savez(sys.argv[4], ms=ms, ahead=ahead, stage=stage)


if __name__ == "__main__":
    main()
