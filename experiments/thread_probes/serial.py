"""Frame loop with no prefetch thread: wall per frame (reading included), process CPU."""

import collections
import os
import sys
import time
from pathlib import Path

import numpy as np

from gloam_jax import io
from gloam_jax.cli.common import use_compilation_cache
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset
from gloam_jax.pipeline import open_odometry

use_compilation_cache()
seq = io.KittiSequence("data/long", "403")
config = load_config(Path("gloam_jax/configs/gicp.yaml"))
n = 300
setup = open_odometry(open_dataset(seq.root, seq.sequence), config, range(n), None)
odo = setup.odometry
ms = []
cpu0 = None
for i in range(n):
    t0 = time.perf_counter()
    if i == 20:
        cpu0, w0 = time.process_time(), time.perf_counter()
        print(f"cpu at frame 20 {cpu0:.1f}")
    scan, times = seq.scan(i), seq.point_times(i)
    odo.register_frame(scan, times, 0.1)
    ms.append(1e3 * (time.perf_counter() - t0))
cpu = time.process_time() - cpu0
wall = time.perf_counter() - w0
print(
    sys.argv[1:],
    f"median frame {np.median(ms[2:]):.1f} p95 {np.percentile(ms[2:], 95):.1f}",
    "cores %.2f" % (cpu / wall),
    "cpu ms/frame %.1f" % (1e3 * cpu / (n - 20)),
)

tot = collections.Counter()
for tid in os.listdir("/proc/self/task"):
    try:
        comm = open(f"/proc/self/task/{tid}/comm").read().strip()
        f = open(f"/proc/self/task/{tid}/stat").read().rsplit(")", 1)[1].split()
        tot[comm + ("-main" if int(tid) == os.getpid() else "-" + tid)] += (
            int(f[11]) + int(f[12])
        ) / os.sysconf("SC_CLK_TCK")
    except FileNotFoundError:
        pass
for k, v in tot.most_common(30):
    print(f"  {k:20s} {v:.1f} s")
