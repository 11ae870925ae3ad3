"""Odometry accuracy and speed: this project's methods against small_gicp, KISS-ICP, GenZ-ICP.

    python scripts/bench_odometry.py DATA --sequences 07 05 01 --threads 2 --out bench.json
    python scripts/bench_odometry.py DATA --sequences 403 --isolate \
        --methods gicp,gicp_da,gicp_ce,gloam,gloam_net,small_gicp,kiss-icp,genz-icp

DATA is a KITTI-layout root (real or from ``gloam simulate``). A method that cannot run (a
peer not installed, or no ``<method>.yaml`` in ``--configs``) stops it before the first run.
Every method gets the same raw scans, in order, with the same number of threads:

* ``gicp``, ``gicp_da``, ``gicp_ce``, ``gloam``: this project's frame-to-model odometry with
  ``configs/<method>.yaml``, deskewed with the scans' per-point times (azimuth-derived where
  absent); the learned methods take ``--weights`` and the model's backbone features, whose
  extraction is timed apart from registration (``median_ms_features``);
* ``small_gicp``: its documented scan-to-model odometry (VGICP on a GaussianVoxelMap of 1 m
  voxels with an LRU horizon, 0.25 m downsampling, constant-velocity guess), no deskew;
* ``kiss-icp``: KISS-ICP with its default configuration, deskew on (times in [0, 1]);
* ``genz-icp``: GenZ-ICP with its default configuration, deskew on (azimuth times in [0, 1]),
  ``genz-icp-kitti`` with the KITTI preset it ships.

Every method's frame time (``frame_ms``: median and p95) is the loop's wall time per frame,
the scan's reading included (and, for the learned methods, the features); ``--isolate`` runs
each method in processes of its own and adds the whole process's wall time, CPU time (user
and system, all threads) and peak memory (``process_s``, ``cpu_s``, ``peak_mib``): first with
an empty JAX compilation cache, then with the cache that run filled (the peers compile
nothing: one run). CPU time over wall time is the cores a method keeps busy: on two cores,
one near 2 cannot go faster by moving work between its threads. ``--rounds N`` runs the
methods in turn N times (round r > 1 under ``name/method@r``): this machine's speed drifts by
tens of percent within an hour, so a ratio is only as good as the time between its two runs,
and the ratio table compares each run with the same round's ``gicp`` and small_gicp.

Prints t_err (%), r_err (deg/100 m) with the KITTI devkit metric in the camera-0 frame, and the
median milliseconds per frame of registration; for this project's methods also the wall time
per frame of the whole loop (reading, features and registration, the next scan read, its
features and voxel grid computed while a frame registers, as in ``gloam run``); counts JAX
compilations after the first 20 frames. For this project's methods, a second table breaks a
frame down by stage (``gloam_jax.timing``: load, features, voxels, deskew, neighbours,
covariances, solve, map, other), each stage's median and 95th percentile in ms over the
frames after the first two (``stage_ms`` in the ``--out`` file).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np
from make_tables import commit, machine, window_rte

from gloam_jax import io, metrics, timing


class _CompileCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if "Compiling" in record.getMessage():
            self.count += 1


def run_ours(seq: io.KittiSequence, n: int, config, weights: Path | None, counter):
    """This project's odometry with ``config`` (an OdometryConfig), frame by frame, with the
    model (or the guard's variant) that ``gloam run`` picks from the first scans."""
    import dataclasses

    from gloam_jax.datasets import open_dataset
    from gloam_jax.pipeline import VoxelPlacement, open_odometry, prefetched, timed_input

    if weights is not None:
        config = dataclasses.replace(config, model=str(weights))
    setup = open_odometry(open_dataset(seq.root, seq.sequence), config, range(n), None)
    odometry = setup.odometry
    times, ms, feature_ms, late_compiles = seq.times, [], [], 0

    def fetch(i: int):
        def read():
            return seq.scan(i), seq.point_times(i)

        return timed_input(
            read, setup.per_point, seq.scan_path(i), i, odometry if placement.ahead else None
        )

    placement = VoxelPlacement()

    # as gloam run does: the next scan, its features and, while that thread is the less busy,
    # its voxel centres on a worker thread (pipeline.prefetched, pipeline.VoxelPlacement)
    last = time.perf_counter()
    frame_ms = []
    for i, fetched in enumerate(prefetched(fetch, range(n))):
        scan, point_times, features, centres, stage_ms = fetched.result()
        odometry.timer.add(stage_ms)
        if "features" in stage_ms:
            feature_ms.append(stage_ms["features"])
        dt = float(times[i] - times[i - 1]) if i else 0.1
        if i == 20:
            late_compiles = counter.count
        t0 = time.perf_counter()
        prepared = scan if centres is None else centres  # centres: built ahead
        odometry.register_frame(prepared, point_times, dt, features=features)
        ms.append(1e3 * (time.perf_counter() - t0))
        placement.update(odometry.status[-1].stage_ms)
        frame_ms.append(1e3 * (time.perf_counter() - last))
        last = time.perf_counter()
    extra = {
        "compiles_after_frame_20": counter.count - late_compiles if n > 20 else None,
        "rounds_per_frame": float(np.mean([s.iterations for s in odometry.status[1:]])),
        "degenerate_frames": int(sum(s.degenerate for s in odometry.status)),
        "thinned_points": int(sum(s.num_thinned for s in odometry.status)),
        # frames 0 and 1 left out: the first compilations, and frame 1 redoes both
        "stage_ms": timing.summarise(s.stage_ms for s in odometry.status[2 if n > 3 else 0 :]),
        # everything a frame needs, overlapped: what must stay under the sensor's period
        "wall_ms_per_frame": float(np.mean(frame_ms)),
        "frame_ms": frame_summary(frame_ms),
        "queries_per_frame": float(np.mean([s.queries for s in odometry.status[1:]])),
        "model_choice": setup.choice.record,
        "map": setup.map,
    }
    if feature_ms:
        extra["median_ms_features"] = float(np.median(feature_ms))
    return np.stack(odometry.poses), ms, extra


def run_small_gicp(seq: io.KittiSequence, n: int, threads: int):
    import small_gicp

    voxelmap = small_gicp.GaussianVoxelMap(1.0)
    voxelmap.set_lru(horizon=100, clear_cycle=10)
    T_world_lidar, T_last_current = np.eye(4), np.eye(4)
    poses, ms, frame_ms = [], [], []
    for i in range(n):
        start = time.perf_counter()
        raw = seq.scan(i)[:, :3].astype(np.float64)
        t0 = time.perf_counter()
        raw = raw[np.all(np.isfinite(raw), axis=1)]
        down, _ = small_gicp.preprocess_points(raw, 0.25, num_threads=threads)
        if voxelmap.size() > 0:
            result = small_gicp.align(
                voxelmap, down, T_world_lidar @ T_last_current, num_threads=threads
            )
            T_last_current = np.linalg.inv(T_world_lidar) @ result.T_target_source
            T_world_lidar = result.T_target_source
        voxelmap.insert(down, T_world_lidar)
        ms.append(1e3 * (time.perf_counter() - t0))
        frame_ms.append(1e3 * (time.perf_counter() - start))
        poses.append(T_world_lidar.copy())
    return np.stack(poses), ms, {"frame_ms": frame_summary(frame_ms)}


def run_kiss(seq: io.KittiSequence, n: int, threads: int):
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)
    config.data.deskew = True
    config.registration.max_num_threads = threads
    return _kiss_family(KissICP(config), seq, n, deskew=True, own_times=True)


def run_genz(seq: io.KittiSequence, n: int, threads: int, preset: str | None = None):
    """GenZ-ICP: its default configuration with deskew on (azimuth times in [0, 1]), or one
    of the presets it ships (``kitti``: deskew off, 0.6 m voxels, 5 m minimum range)."""
    from genz_icp.config import GenZConfig, load_config
    from genz_icp.genz_icp import GenZICP

    if preset is None:
        config = GenZConfig()
        config.data.deskew = True
    else:
        config = load_config(Path(preset))
    config.registration.max_num_threads = threads
    return _kiss_family(GenZICP(config), seq, n, deskew=config.data.deskew, own_times=False)


def _kiss_family(odometry, seq: io.KittiSequence, n: int, deskew: bool, own_times: bool):
    """The frame loop of KISS-ICP and GenZ-ICP (one API): each scan with its points' times in
    [0, 1], the scan's own where ``own_times`` and it has them, else from the azimuth."""
    poses, ms, frame_ms = [], [], []
    for i in range(n):
        start = time.perf_counter()
        scan = seq.scan(i)[:, :3].astype(np.float64)
        point_times = seq.point_times(i) if own_times else None
        if point_times is None:
            u = 0.5 * (1.0 - np.arctan2(scan[:, 1], scan[:, 0]) / np.pi)
        else:
            u = 0.5 + point_times.astype(np.float64) / 0.1
        t0 = time.perf_counter()
        odometry.register_frame(scan, u if deskew else None)
        ms.append(1e3 * (time.perf_counter() - t0))
        frame_ms.append(1e3 * (time.perf_counter() - start))
        poses.append(odometry.last_pose.copy())
    return np.stack(poses), ms, {"frame_ms": frame_summary(frame_ms)}


class Peer(NamedTuple):
    """A peer odometry: the module its package installs, and its runner (seq, frames,
    threads) -> (poses, ms, extra)."""

    module: str
    run: Callable


PEERS = {
    "small_gicp": Peer("small_gicp", run_small_gicp),
    "kiss-icp": Peer("kiss_icp", run_kiss),
    "genz-icp": Peer("genz_icp", run_genz),
    "genz-icp-kitti": Peer("genz_icp", partial(run_genz, preset="kitti")),
}


def peer_modules(methods: list[str]) -> tuple[str, ...]:
    """The modules the peers among ``methods`` run (their versions go into the records)."""
    return tuple(PEERS[m].module for m in methods if m in PEERS)


def missing_peer(methods: list[str]) -> str | None:
    """Why one of the peers among ``methods`` cannot run: its package is not installed."""
    from importlib.util import find_spec

    for method in methods:
        if method in PEERS and find_spec(PEERS[method].module) is None:
            return f"{method}: its package is not installed (pip install -e '.[peers]')"
    return None


def unrunnable(methods: list[str], configs: Path) -> str | None:
    """Why one of ``methods`` cannot run, checked before any runs (a sitting takes half an
    hour): a peer whose package is not installed, or one of ours without a config."""
    for method in methods:
        if method not in PEERS and not (config := configs / f"{method}.yaml").is_file():
            return f"{method}: neither a peer nor a config of ours ({config} is missing)"
    return missing_peer(methods)


def frame_summary(frame_ms: list[float]) -> dict:
    """Median and p95 of a run's frame times (ms), frames 0 and 1 left out (the first
    compilations, and frame 1 redoes both in this project's odometry)."""
    kept = np.asarray(frame_ms[2:] if len(frame_ms) > 3 else frame_ms)
    return {"median": float(np.median(kept)), "p95": float(np.percentile(kept, 95))}


def isolated(args: argparse.Namespace, name: str, method: str) -> dict:
    """``method`` on sequence ``name`` in processes of its own (this script, one method): first
    with an empty compilation cache, then (this project's methods) with the cache it filled.
    The cached run's entry, with each run's whole-process wall time (s), CPU time (s) and peak
    memory (MiB)."""
    runs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label in ("first", "cached"):
            out = Path(tmp) / f"{label}.json"
            cmd = [sys.executable, __file__, str(args.data), "--sequences", name,
                   "--methods", method, "--threads", str(args.threads),
                   "--configs", str(args.configs), "--out", str(out)]  # fmt: skip
            cmd += [] if args.frames is None else ["--frames", str(args.frames)]
            cmd += [] if args.weights is None else ["--weights", str(args.weights)]
            start = time.perf_counter()
            # the cache under XDG_CACHE_HOME (gloam_jax.cli.common.cache_dir): empty, then filled
            child = subprocess.Popen(cmd, env={**os.environ, "XDG_CACHE_HOME": tmp},
                                     stdout=subprocess.DEVNULL)  # fmt: skip
            _, status, usage = os.wait4(child.pid, 0)
            seconds = time.perf_counter() - start
            if os.waitstatus_to_exitcode(status) != 0:
                raise SystemExit(f"{method} on {name}: its process failed ({' '.join(cmd)})")
            entry = json.loads(out.read_text())[f"{name}/{method}"]
            cpu = usage.ru_utime + usage.ru_stime
            runs[label] = {"entry": entry, "s": seconds, "cpu": cpu, "mib": usage.ru_maxrss / 1024}
            if method in PEERS:
                break  # no compilation cache to fill
    entry = runs.get("cached", runs["first"])["entry"]
    entry["process_s"] = {label: r["s"] for label, r in runs.items()}
    entry["cpu_s"] = {label: r["cpu"] for label, r in runs.items()}
    entry["peak_mib"] = {label: r["mib"] for label, r in runs.items()}
    return entry


def score(gt: np.ndarray, est: np.ndarray) -> dict:
    """Devkit t_err and r_err; on a drive shorter than the devkit's shortest segment (100 m),
    over segments scaled to the drive (``make_tables.window_rte``), whose lengths it records."""
    if metrics.path_lengths(gt)[-1] > min(metrics.DEFAULT_LENGTHS):
        rte = metrics.kitti_rte(gt, est)
        return {"t_err_percent": rte.t_err_percent, "r_err_deg_per_100m": rte.r_err_deg_per_100m}
    w = window_rte(gt, est)
    return {
        "t_err_percent": w["t_err"],
        "r_err_deg_per_100m": w["r_err"],
        "lengths_m": w["lengths_m"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--sequences", nargs="+", required=True)
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--configs", type=Path, default=Path("configs"),
        help="folder of <method>.yaml; a base: that names a config (base: gicp) still reads the "
        "shipped one, a path (base: ./gicp.yaml) this folder's",
    )  # fmt: skip
    parser.add_argument("--weights", type=Path, default=None, help="model for learned methods")
    parser.add_argument("--methods", default="gicp,small_gicp,kiss-icp")
    parser.add_argument("--out", type=Path, default=Path("bench_odometry.json"))
    parser.add_argument(
        "--isolate",
        action="store_true",
        help="each method in processes of its own: process time, peak memory",
    )
    parser.add_argument(
        "--rounds", type=int, default=1,
        help="run the methods in turn this many times; ratios within each round",
    )  # fmt: skip
    args = parser.parse_args()
    if (problem := unrunnable(args.methods.split(","), args.configs)) is not None:
        parser.error(problem)

    import jax

    counter = _CompileCounter()
    logging.getLogger("jax").addHandler(counter)
    jax.config.update("jax_log_compiles", True)
    logging.getLogger("jax").setLevel(logging.WARNING)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    from gloam_jax.cli.common import use_compilation_cache

    use_compilation_cache()  # as gloam run does

    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    here = commit()  # the code this process loaded; each method's machine record, once
    machines = {m: machine(peer_modules([m])) for m in args.methods.split(",")}
    for name in args.sequences:
        seq = io.KittiSequence(args.data, name)
        n = len(seq) if args.frames is None else min(args.frames, len(seq))
        gt = seq.gt_poses_cam[:n]
        for round_, method in ((r, m) for r in range(1, args.rounds + 1)
                               for m in args.methods.split(",")):  # fmt: skip
            key = f"{name}/{method}" + (f"@{round_}" if round_ > 1 else "")
            if key in results:  # resume: keep what an earlier run measured
                continue
            where = {"commit": here, "machine": machines[method]}
            if args.isolate:
                results[key] = isolated(args, name, method) | where
                print(key, json.dumps(results[key]), flush=True)
                io.write_atomic(args.out, json.dumps(results, indent=2))
                continue
            if method in PEERS:
                poses, ms, extra = PEERS[method].run(seq, n, args.threads)
            else:
                from gloam_jax.config import load_config

                config = load_config(args.configs / f"{method}.yaml")
                poses, ms, extra = run_ours(seq, n, config, args.weights, counter)
            est = io.lidar_to_cam_poses(np.linalg.inv(poses[0]) @ poses, seq.Tr_cam_velo)
            results[key] = {
                **score(gt, est),
                "median_ms_per_frame": float(np.median(ms)),
                "frames": n,
                **extra,
                **where,
            }
            print(key, json.dumps(results[key]), flush=True)
            io.write_atomic(args.out, json.dumps(results, indent=2))

    print("\n" + speed_table(results))
    if any(r.get("stage_ms") for r in results.values()):
        print("\n" + stage_table(results))
    if any("@" in key for key in results):
        print("\n" + ratio_table(results))


def _split(key: str) -> tuple[str, str, str]:
    """(sequence, method, round suffix: "" or "@r") of a results key."""
    name, rest = key.split("/")
    method, _, round_ = rest.partition("@")
    return name, method, f"@{round_}" if round_ else ""


def ratio_table(results: dict) -> str:
    """Each method's median frame time over ``gicp``'s and over small_gicp's of the same
    sequence and round, per round and their median over the rounds."""
    ratios: dict[tuple[str, str, str], list[float]] = {}
    for key, r in results.items():
        name, method, round_ = _split(key)
        if method == "small_gicp":  # the reference, not a row
            continue
        for peer in ("gicp", "small_gicp"):
            other = results.get(f"{name}/{peer}{round_}")
            if other and method != peer and r.get("frame_ms") and other.get("frame_ms"):
                ratio = r["frame_ms"]["median"] / other["frame_ms"]["median"]
                ratios.setdefault((name, method, peer), []).append(ratio)
    lines = ["| sequence | method | over | per round | median |", "|---|---|---|---|---|"]
    for (name, method, peer), values in ratios.items():
        rounds = ", ".join(f"{v:.2f}" for v in values)
        lines.append(f"| {name} | {method} | {peer} | {rounds} | {np.median(values):.2f}x |")
    return "\n".join(lines)


def speed_table(results: dict) -> str:
    """Accuracy and speed per entry: frame time (median / p95 ms, reading and features
    included) and its ratio to small_gicp's median on the same sequence, registration alone
    (median ms), and with ``--isolate`` the whole process (s) and its peak memory (MiB), first
    run / cached run, and the cores the last run kept busy (its CPU time over its wall time)."""
    lines = [
        "| sequence | method | t_err (%) | r_err (deg/100 m) | frame ms, median / p95 "
        "| vs small_gicp | registration ms | process s, first / cached | cores | peak MiB |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def pair(values: dict | None, fmt: str) -> str:
        return " / ".join(format(v, fmt) for v in values.values()) if values else "-"

    for key, r in results.items():
        name, method, round_ = _split(key)
        frame = r.get("frame_ms")
        peer = results.get(f"{name}/small_gicp{round_}", {}).get("frame_ms")
        ratio = f"{frame['median'] / peer['median']:.2f}x" if frame and peer else "-"
        process, cpu = r.get("process_s"), r.get("cpu_s")
        cores = f"{list(cpu.values())[-1] / list(process.values())[-1]:.2f}" if cpu else "-"
        lines.append(
            f"| {name} | {method}{round_} | {r['t_err_percent']:.3f} | "
            f"{r['r_err_deg_per_100m']:.3f} | "
            f"{pair(frame, '.1f')} | {ratio} | {r['median_ms_per_frame']:.1f} | "
            f"{pair(process, '.0f')} | {cores} | {pair(r.get('peak_mib'), '.0f')} |"
        )
    return "\n".join(lines)


def stage_table(results: dict) -> str:
    """The per-stage breakdown of the entries with one (this project's methods): median / p95
    ms of each stage, and the sum of the medians (the stages do not overlap: about a typical
    frame's time, loading and features included)."""
    lines = [
        "| sequence | method | " + " | ".join(timing.STAGES) + " | sum of medians |",
        "|---|---|" + "---|" * (len(timing.STAGES) + 1),
    ]
    for key, r in results.items():
        stages = r.get("stage_ms")
        if not stages:
            continue
        name, method = key.split("/")  # with its round, if any
        cells = [f"{stages[s]['median']:.1f} / {stages[s]['p95']:.1f}" for s in timing.STAGES]
        total = sum(stages[s]["median"] for s in timing.STAGES)
        lines.append(f"| {name} | {method} | " + " | ".join(cells) + f" | {total:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
