"""Where gloam_net's voxel grid + features run (VoxelPlacement) and what forcing it does."""
import sys, json, time
sys.path.insert(0, "scripts")
import numpy as np
import bench_odometry as B
from gloam_jax import io, pipeline
from gloam_jax.config import load_config
from gloam_jax.cli.common import use_compilation_cache
use_compilation_cache()
mode, method, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
orig = pipeline.VoxelPlacement.update
log = []
def update(self, stage_ms):
    orig(self, stage_ms)
    if mode == "ahead": self.ahead = True
    if mode == "main": self.ahead = False
    log.append(self.ahead)
pipeline.VoxelPlacement.update = update
_open = pipeline.open_odometry
box = {}
def open_odometry(*a, **k):
    box["setup"] = r = _open(*a, **k); return r
pipeline.open_odometry = open_odometry
class C: count = 0
seq = io.KittiSequence("data/long", "403")
import gloam_jax.timing as tm
poses, ms, extra = B.run_ours(seq, n, load_config(f"gloam_jax/configs/{method}.yaml"), None, C())
print({k: v["median"] for k, v in extra["stage_ms"].items()}); print(mode, method, "ahead share", np.mean(log[20:]), "reg median", round(np.median(ms[20:]),1),
      "frame", extra["frame_ms"], "wall", round(extra["wall_ms_per_frame"],1), "feat", round(extra.get("median_ms_features", 0),1))
import numpy as np
st = B  # noqa
fm = np.array(extra.get("_frame_ms", []))

sts = box["setup"].odometry.status
keys = ["load","features","voxels","deskew","neighbours","covariances","solve","map","other"]
stage = np.array([[s.stage_ms.get(k, 0.0) for k in keys] for s in sts])
npts = np.array([s.num_points for s in sts])
np.savez("/tmp/place_%s_%s.npz" % (mode, method), ms=np.array(ms), ahead=np.array(log), stage=stage, npts=npts)
ms = np.array(ms); top = np.argsort(ms)[-50:]
print("top-5% frames: mean ms", ms[top].mean(), "ahead share", np.mean(np.array([True]+log)[top]))
print("stage means top:", dict(zip(keys, stage[top].mean(0).round(1))))
print("stage means all:", dict(zip(keys, stage[20:].mean(0).round(1))))
print("points top/all", npts[top].mean(), npts[20:].mean())
