"""What the slowest frames of a 1000-frame drive have in common (experiments/net_p95): runs
METHOD on val 403 d0 as bench_odometry runs it and records, per frame, the loop's wall time
(one registered frame to the next, as ``frame_ms``), its stages (``stage_ms``), whether it
added a keyframe to the map, and which thread built its voxel grid (VoxelPlacement). Writes
OUT.json: the frames at or above the 95th percentile against the rest.

    python experiments/net_p95/probe_slow_frames.py METHOD OUT.json
"""

import json
import sys
import time

import numpy as np

sys.path.insert(0, "scripts")
import bench_odometry  # noqa: E402
from make_tables import commit, machine  # noqa: E402

from gloam_jax import io  # noqa: E402
from gloam_jax.cli.common import use_compilation_cache  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402
from gloam_jax.io import write_atomic  # noqa: E402
from gloam_jax.local_map import LocalMap  # noqa: E402
from gloam_jax.odometry import Odometry  # noqa: E402
from gloam_jax.preprocess import VoxelCentres  # noqa: E402

frames: list[dict] = []


def main() -> None:
    method, out = sys.argv[1], sys.argv[2]
    use_compilation_cache()
    register, add = Odometry.register_frame, LocalMap.add

    def registered(self, *args, **kwargs):
        # a frame whose voxel grid the prefetch thread built comes as its VoxelCentres
        frames.append({"keyframe": False, "ahead": isinstance(args[0], VoxelCentres)})
        T = register(self, *args, **kwargs)
        frames[-1] |= {"end": time.perf_counter(), "stage_ms": dict(self.status[-1].stage_ms)}
        return T

    def added(self, *args, **kwargs):
        if frames:
            frames[-1]["keyframe"] = True
        return add(self, *args, **kwargs)

    Odometry.register_frame, LocalMap.add = registered, added

    class Counter:
        count = 0

    config = load_config(f"gloam_jax/configs/{method}.yaml")
    bench_odometry.run_ours(io.KittiSequence("data/long", "403"), 1000, config, None, Counter())
    ends = np.array([f["end"] for f in frames])
    ms = 1e3 * np.diff(ends)  # frame k (k >= 1): from frame k-1's end to its own
    rows = frames[1:]
    keep = np.arange(len(ms)) >= 20  # past the first frames' compilations
    p95 = np.percentile(ms[keep], 95)
    slow = keep & (ms >= p95)
    rest = keep & ~slow

    def summary(mask: np.ndarray) -> dict:
        picked = [r for r, m in zip(rows, mask, strict=True) if m]
        stages = {s: float(np.median([r["stage_ms"].get(s, 0.0) for r in picked]))
                  for s in picked[0]["stage_ms"]}  # fmt: skip
        return {
            "frames": int(mask.sum()),
            "median_ms": float(np.median(ms[mask])),
            "keyframe_share": float(np.mean([r["keyframe"] for r in picked])),
            "grid_on_prefetch_share": float(np.mean([r["ahead"] for r in picked])),
            "median_stage_ms": stages,
        }

    result = {"command": "python " + " ".join(sys.argv), "commit": commit(),
              "machine": machine(), "method": method, "p95_ms": float(p95),
              "slow": summary(slow), "rest": summary(rest)}  # fmt: skip
    write_atomic(out, json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
