"""Which jitted functions compile (or lower and load from the persistent cache) after frame 20
of val 403 d0, as bench_odometry runs a method (prefetch thread), and what those frames cost:
does a new padded shape set the p95 frame time?

    python experiments/long_speed/probe_compiles.py gicp > experiments/long_speed/probe_compiles.txt
"""

import collections
import logging
import re
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path.cwd() / "scripts"))
import bench_odometry as bench  # noqa: E402

import gloam_jax.odometry as od  # noqa: E402
from gloam_jax import io  # noqa: E402
from gloam_jax.cli.common import use_compilation_cache  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402

use_compilation_cache()  # as gloam run and bench_odometry do
events: list[str] = []


class Compiles(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        if "Compiling" in record.getMessage():
            events.append(record.getMessage()[:160])


logging.getLogger("jax").addHandler(Compiles())
logging.getLogger("jax").setLevel(logging.WARNING)
jax.config.update("jax_log_compiles", True)

method = sys.argv[1]
marks: list[int] = []  # compile events seen when each frame's registration began
register = od.Odometry.register_frame


def counted(self, *args, **kwargs):
    marks.append(len(events))
    return register(self, *args, **kwargs)


od.Odometry.register_frame = counted
seq = io.KittiSequence("data/long", "403")
config = load_config(Path(f"gloam_jax/configs/{method}.yaml"))
_, ms, _ = bench.run_ours(seq, 1000, config, None, bench._CompileCounter())
marks.append(len(events))
ms = np.asarray(ms)
compiled = np.diff(marks) > 0
late = np.arange(len(ms)) >= 20
print(f"{method}: {int((compiled & late).sum())} frames after frame 20 compile something;")
print(f"  their median {np.median(ms[compiled & late]):.1f} ms, "
      f"the others' {np.median(ms[~compiled & late]):.1f}")  # fmt: skip
print(f"  p95 of frames 2-: {np.percentile(ms[2:], 95):.1f} ms, without those frames "
      f"{np.percentile(ms[~compiled & late], 95):.1f}")  # fmt: skip
names = collections.Counter(
    re.sub(r"Compiling (\S+).*", r"\1", e) for e in events[marks[20] :]
)  # fmt: skip
print("  compiled after frame 20:", dict(names.most_common()))
