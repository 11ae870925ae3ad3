"""The odometry's poses on the first frames of a drive, as bench_odometry runs it (prefetch
thread included), saved for a bit-for-bit comparison between commits.

    PYTHONPATH=. python experiments/layered_map/poses.py data/long 403 300 gicp OUT.npy
    python experiments/layered_map/poses.py --compare A.npy B.npy
"""

import sys
from pathlib import Path

import numpy as np

if sys.argv[1] == "--compare":
    a, b = np.load(sys.argv[2]), np.load(sys.argv[3])
    diff = np.abs(a - b).max(axis=(1, 2))
    first = int(np.argmax(diff > 0)) if (diff > 0).any() else None
    print(
        f"{len(a)} poses, identical: {bool((diff == 0).all())}, largest difference "
        f"{diff.max():.3g}, first differing frame {first}"
    )
    sys.exit(0)

sys.path.insert(0, str(Path.cwd() / "scripts"))
import bench_odometry as bench  # noqa: E402

from gloam_jax import io  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402

data, sequence, frames, method, out = sys.argv[1:6]
seq = io.KittiSequence(data, sequence)
config = load_config(Path("gloam_jax/configs") / f"{method}.yaml")
poses, ms, extra = bench.run_ours(seq, int(frames), config, None, bench._CompileCounter())
np.save(out, np.asarray(poses))
print(method, f"{len(poses)} poses, median frame {np.median(ms):.1f} ms")
