"""Odometry accuracy and speed: this project's GICP against small_gicp and KISS-ICP.

    python scripts/bench_odometry.py DATA --sequences 07 05 01 --threads 2 --out bench.json

DATA is a KITTI-layout root (real or from ``gloam simulate``). Every method gets the same raw
scans, in order, with the same number of threads:

* ``gicp``, ``gicp_da``, ``gicp_ce``, ``gloam``: this project's frame-to-model odometry with
  ``configs/<method>.yaml``, deskewed with the scans' per-point times (azimuth-derived where
  absent); the learned methods take ``--weights`` and the model's backbone features, whose
  extraction is timed apart from registration (``median_ms_features``);
* ``small_gicp``: its documented scan-to-model odometry (VGICP on a GaussianVoxelMap of 1 m
  voxels with an LRU horizon, 0.25 m downsampling, constant-velocity guess), no deskew;
* ``kiss-icp``: KISS-ICP with its default configuration, deskew on (times in [0, 1]).

Prints t_err (%), r_err (deg/100 m) with the KITTI devkit metric in the camera-0 frame, and the
median milliseconds per frame of registration; for this project's methods also the wall time
per frame of the whole loop (reading, features and registration, the next scan read and its
features computed while a frame registers, as in ``gloam run``); counts JAX compilations after
the first 20 frames. For this
project's methods, a second table breaks a frame down by stage (``gloam_jax.timing``: load,
features, preprocess, neighbours, covariances, solve, map, other), each stage's median and 95th
percentile in ms over the frames after the first two (``stage_ms`` in the ``--out`` file).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
from make_tables import window_rte

from gloam_jax import io, metrics, timing


class _CompileCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if "Compiling" in record.getMessage():
            self.count += 1


def run_ours(seq: io.KittiSequence, n: int, config, weights: Path | None, counter):
    """This project's odometry with ``config`` (an OdometryConfig), frame by frame."""
    import dataclasses

    from gloam_jax.odometry import Odometry
    from gloam_jax.pipeline import prefetched, timed_input

    if weights is not None:
        config = dataclasses.replace(config, model=str(weights))
    odometry = Odometry(config)
    backbone = None
    if odometry.needs_features:
        backbone = odometry.model.backbone()
    times, ms, feature_ms, late_compiles = seq.times, [], [], 0

    def fetch(i: int):
        return timed_input(lambda: (seq.scan(i), seq.point_times(i)), backbone, seq.scan_path(i), i)

    # as gloam run does: the next scan and its features on a worker thread (pipeline.prefetched)
    loop_start = time.perf_counter()
    for i, fetched in enumerate(prefetched(fetch, range(n))):
        scan, point_times, features, stage_ms = fetched.result()
        for stage, stage_time in stage_ms.items():
            odometry.timer.add(stage, stage_time)
        if "features" in stage_ms:
            feature_ms.append(stage_ms["features"])
        dt = float(times[i] - times[i - 1]) if i else 0.1
        if i == 20:
            late_compiles = counter.count
        t0 = time.perf_counter()
        odometry.register_frame(scan, point_times, dt, features=features)
        ms.append(1e3 * (time.perf_counter() - t0))
    wall_ms = 1e3 * (time.perf_counter() - loop_start) / n
    extra = {
        "compiles_after_frame_20": counter.count - late_compiles if n > 20 else None,
        "rounds_per_frame": float(np.mean([s.iterations for s in odometry.status[1:]])),
        "degenerate_frames": int(sum(s.degenerate for s in odometry.status)),
        "thinned_points": int(sum(s.num_thinned for s in odometry.status)),
        # frames 0 and 1 left out: the first compilations, and frame 1 redoes both
        "stage_ms": timing.summarise(s.stage_ms for s in odometry.status[2 if n > 3 else 0 :]),
        # everything a frame needs, overlapped: what must stay under the sensor's period
        "wall_ms_per_frame": wall_ms,
    }
    if feature_ms:
        extra["median_ms_features"] = float(np.median(feature_ms))
    return np.stack(odometry.poses), ms, extra


def run_small_gicp(seq: io.KittiSequence, n: int, threads: int):
    import small_gicp

    voxelmap = small_gicp.GaussianVoxelMap(1.0)
    voxelmap.set_lru(horizon=100, clear_cycle=10)
    T_world_lidar, T_last_current = np.eye(4), np.eye(4)
    poses, ms = [], []
    for i in range(n):
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
        poses.append(T_world_lidar.copy())
    return np.stack(poses), ms, {}


def run_kiss(seq: io.KittiSequence, n: int, threads: int):
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)
    config.data.deskew = True
    config.registration.max_num_threads = threads
    odometry = KissICP(config)
    poses, ms = [], []
    for i in range(n):
        scan = seq.scan(i)[:, :3].astype(np.float64)
        point_times = seq.point_times(i)
        if point_times is None:
            u = 0.5 * (1.0 - np.arctan2(scan[:, 1], scan[:, 0]) / np.pi)
        else:
            u = 0.5 + point_times.astype(np.float64) / 0.1
        t0 = time.perf_counter()
        odometry.register_frame(scan, u)
        ms.append(1e3 * (time.perf_counter() - t0))
        poses.append(odometry.last_pose.copy())
    return np.stack(poses), ms, {}


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
    parser.add_argument("--configs", type=Path, default=Path("configs"), help="<method>.yaml")
    parser.add_argument("--weights", type=Path, default=None, help="model for learned methods")
    parser.add_argument("--methods", default="gicp,small_gicp,kiss-icp")
    parser.add_argument("--out", type=Path, default=Path("bench_odometry.json"))
    args = parser.parse_args()

    import jax

    counter = _CompileCounter()
    logging.getLogger("jax").addHandler(counter)
    jax.config.update("jax_log_compiles", True)
    logging.getLogger("jax").setLevel(logging.WARNING)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))

    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    for name in args.sequences:
        seq = io.KittiSequence(args.data, name)
        n = len(seq) if args.frames is None else min(args.frames, len(seq))
        gt = seq.gt_poses_cam[:n]
        for method in args.methods.split(","):
            key = f"{name}/{method}"
            if key in results:  # resume: keep what an earlier run measured
                continue
            if method == "small_gicp":
                poses, ms, extra = run_small_gicp(seq, n, args.threads)
            elif method == "kiss-icp":
                poses, ms, extra = run_kiss(seq, n, args.threads)
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
            }
            print(key, json.dumps(results[key]), flush=True)
            io.write_atomic(args.out, json.dumps(results, indent=2))

    print(
        "\n| sequence | method | t_err (%) | r_err (deg/100 m) | median ms/frame | vs small_gicp "
        "| wall ms/frame |"
    )
    print("|---|---|---|---|---|---|---|")
    for key, r in results.items():
        name, method = key.split("/")
        peer = results.get(f"{name}/small_gicp")
        ratio = f"{r['median_ms_per_frame'] / peer['median_ms_per_frame']:.1f}x" if peer else "-"
        wall = f"{r['wall_ms_per_frame']:.1f}" if "wall_ms_per_frame" in r else "-"
        print(
            f"| {name} | {method} | {r['t_err_percent']:.2f} | {r['r_err_deg_per_100m']:.2f} | "
            f"{r['median_ms_per_frame']:.1f} | {ratio} | {wall} |"
        )
    if any(r.get("stage_ms") for r in results.values()):
        print("\n" + stage_table(results))


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
        name, method = key.split("/")
        cells = [f"{stages[s]['median']:.1f} / {stages[s]['p95']:.1f}" for s in timing.STAGES]
        total = sum(stages[s]["median"] for s in timing.STAGES)
        lines.append(f"| {name} | {method} | " + " | ".join(cells) + f" | {total:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
