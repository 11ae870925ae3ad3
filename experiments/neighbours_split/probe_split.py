"""Where the ``neighbours`` stage's time goes in the odometry (issue 42). Run from the
repository root:

python experiments/neighbours_split/probe_split.py METHOD FRAMES

val 403 d0 (data/long), run as scripts/bench_odometry.py runs it. Wraps the k-d tree's build
and queries and the degeneracy check's constraint rows, and prints, per frame after frame 20,
the median ms of each on the registration's thread (calls on other threads counted apart),
each thread's CPU time, and the stages of the frames over 100 ms.

PROBE_XLA_THREADS=1: XLA's CPU thread pool of one thread; PROBE_PLACEMENT=ahead|main: the
voxel grid (and grid features) always on the prefetch thread, or always in the registration."""

import glob
import os
import sys
import threading
import time
from collections import defaultdict

import jax
import numpy as np

sys.path.insert(0, "scripts")
import bench_odometry  # noqa: E402

from gloam_jax import io, neighbors, pipeline, registration, timing  # noqa: E402
from gloam_jax.cli.common import use_compilation_cache  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402

frames: list[dict] = [defaultdict(float)]
elsewhere: dict = defaultdict(float)
sizes: dict = defaultdict(list)


native: dict = {}  # native thread id -> Python thread name, for the threads that ran a wrapper


def timed(name, fn):
    def wrapper(*args, **kwargs):
        native[threading.get_native_id()] = threading.current_thread().name.split("_")[0]
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        ms = 1e3 * (time.perf_counter() - start)
        if threading.current_thread() is threading.main_thread():
            frames[-1][name] += ms
        else:
            elsewhere[f"{threading.current_thread().name.split('_')[0]}:{name}"] += ms
        return out

    return wrapper


def one_xla_thread() -> None:
    """XLA's CPU client sizes its thread pool by the cores the process may use when the
    client starts: start it on one core, then give every thread both cores back."""
    cores = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(cores)})
    jax.devices()
    for task in glob.glob("/proc/self/task/*"):
        os.sched_setaffinity(int(task.rsplit("/", 1)[1]), cores)


def main() -> None:
    method, n = sys.argv[1], int(sys.argv[2])
    if os.environ.get("PROBE_XLA_THREADS") == "1":
        one_xla_thread()
    if os.environ.get("PROBE_PLACEMENT") in ("ahead", "main"):
        ahead = os.environ["PROBE_PLACEMENT"] == "ahead"
        pipeline.VoxelPlacement.update = lambda self, stage_ms: setattr(self, "ahead", ahead)
    use_compilation_cache()
    init, nearest = neighbors.KdTree.__init__, neighbors.KdTree.nearest

    def init_named(self, points, source=None):
        name = "build map tree" if source == "local map" else "build scan tree"
        timed(name, init)(self, points, source)
        if threading.current_thread() is threading.main_thread():
            sizes["scan"].append(len(points))

    def nearest_named(self, queries, k, max_distance=np.inf):
        name = "scan k-NN" if self.source != "local map" else f"map query k={k}"
        return timed(name, nearest)(self, queries, k, max_distance)

    neighbors.KdTree.__init__ = init_named
    neighbors.KdTree.nearest = nearest_named
    registration.constraint_rows = timed("constraint rows", registration.constraint_rows)
    pipeline.timed_input = timed("prefetch input", pipeline.timed_input)
    begin = timing.StageTimer.begin

    def begin_row(self):  # a frame's registration starts: a new row
        frames.append(defaultdict(float))
        begin(self)

    timing.StageTimer.begin = begin_row

    class Counter:
        count = 0

    setup: dict = {}
    opened = pipeline.open_odometry

    def open_kept(*args, **kwargs):
        result = opened(*args, **kwargs)
        setup["odometry"] = result.odometry
        return result

    pipeline.open_odometry = open_kept
    config = load_config(f"gloam_jax/configs/{method}.yaml")
    _, ms, extra = bench_odometry.run_ours(io.KittiSequence("data/long", "403"), n, config,
                                           None, Counter())  # fmt: skip
    rows = frames[21:]
    names = sorted({k for r in rows for k in r})
    print(
        f"{method}, {n} frames: frame median / p95 {extra['frame_ms']['median']:.1f} / "
        f"{extra['frame_ms']['p95']:.1f} ms; neighbours stage median "
        f"{extra['stage_ms']['neighbours']['median']:.2f} ms; scan points median "
        f"{np.median(sizes['scan']):.0f}"
    )
    for name in names:
        v = np.array([r.get(name, 0.0) for r in rows])
        print(
            f"  {name:20s} median {np.median(v):6.2f}  mean {v.mean():6.2f}  p95 "
            f"{np.percentile(v, 95):6.2f} ms"
        )
    frame = np.asarray(ms)[21:]
    status = [f.stage_ms for f in setup["odometry"].status][21:]
    slow = frame > 100.0
    print(f"  frames over 100 ms: {slow.sum()} of {len(frame)}; stage medians over / under:")
    for k in status[0]:
        v = np.array([f.get(k, 0.0) for f in status])
        print(
            f"    {k:12s} {np.median(v[slow]) if slow.any() else 0:6.1f} / "
            f"{np.median(v[~slow]):6.1f}"
        )
    for name, total in sorted(elsewhere.items()):
        print(f"  elsewhere {name:24s} {total / len(rows):6.2f} ms a frame")
    # CPU time of each of the process's threads over the whole run (start-up included)
    by_name: dict = defaultdict(float)
    for task in glob.glob("/proc/self/task/*"):
        fields = open(f"{task}/stat").read().rsplit(")", 1)[1].split()
        tid = int(task.rsplit("/", 1)[1])
        name = native.get(tid, open(f"{task}/comm").read().strip())
        by_name[name] += int(fields[11]) + int(fields[12])
    ticks = os.sysconf("SC_CLK_TCK")
    for name, t in sorted(by_name.items(), key=lambda x: -x[1])[:8]:
        print(f"  threads {name:20s} {1e3 * t / ticks / n:6.2f} ms CPU a frame (run's mean)")


if __name__ == "__main__":
    main()
