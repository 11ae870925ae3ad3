"""Dataset -> odometry -> metrics -> result files, for one KITTI-layout sequence.

A run folder holds (``NN`` the sequence id)::

    NN_poses_kitti.txt        estimate, camera-0 convention (compare with poses/NN.txt)
    NN_poses_lidar_kitti.txt  estimate, LiDAR frame (T_world_lidar, first pose identity)
    NN_poses_tum.txt          estimate, camera-0 convention, with the frame times
    metrics.json              KITTI RTE and ATE (when ground truth exists), timing, frame flags
    trajectory.png            estimate against ground truth, and error per segment length
    config.yaml               the settings used
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from gloam_jax import io, metrics
from gloam_jax.config import dump_config
from gloam_jax.errors import InputError
from gloam_jax.features import Backbone, get_backbone
from gloam_jax.odometry import Odometry, OdometryConfig


def run_sequence(
    root: str | Path,
    sequence: str | int,
    config: OdometryConfig,
    out_dir: str | Path,
    *,
    frames: int | None = None,
    progress: Callable[[int, float], None] | None = None,
    features_dir: str | Path | None = None,
) -> dict:
    """Run odometry over a sequence and write the run folder; returns the metrics dict.

    Learned methods get per-point features from the model's backbone, or from one file per
    scan in ``features_dir`` (the ``precomputed`` backbone). The time per frame counts
    registration only; feature extraction is timed separately (``median_ms_features``).
    """
    seq = io.KittiSequence(root, sequence)
    n = len(seq) if frames is None else min(frames, len(seq))
    if n < 2:
        raise InputError(seq.sequence_dir, f"need at least 2 scans, have {n}")
    odometry = Odometry(config)
    backbone = _backbone(odometry, features_dir)
    times = seq.times
    frame_ms, feature_ms = [], []
    for i in range(n):
        scan = seq.scan(i)
        point_times = seq.point_times(i)
        frame_dt = float(times[i] - times[i - 1]) if i > 0 else config.preprocess.sweep_duration
        path = seq.scan_path(i)
        features = None
        if backbone is not None:
            t0 = time.perf_counter()
            features = backbone(scan, path=path, frame=i)
            feature_ms.append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        odometry.register_frame(scan, point_times, frame_dt, source=str(path), features=features)
        frame_ms.append(1e3 * (time.perf_counter() - t0))
        if progress is not None:
            progress(i, frame_ms[-1])
    result = write_run(seq, odometry, config, out_dir, n, frame_ms)
    if feature_ms:
        result["median_ms_features"] = float(np.median(feature_ms))
        io.write_atomic(Path(out_dir) / "metrics.json", json.dumps(result, indent=2))
    return result


def _backbone(odometry: Odometry, features_dir: str | Path | None) -> Backbone | None:
    """The feature source of a learned method: the model's backbone or a folder of files."""
    if not odometry.needs_features:
        return None
    if features_dir is not None:
        return get_backbone("precomputed", folder=features_dir)
    return odometry.model.backbone()


def write_run(seq: io.KittiSequence, odometry: Odometry, config: OdometryConfig,
              out_dir: str | Path, n: int, frame_ms: list[float]) -> dict:  # fmt: skip
    out = Path(out_dir)
    name = seq.sequence
    T_lidar = np.stack(odometry.poses)
    T_cam = io.lidar_to_cam_poses(T_lidar, seq.Tr_cam_velo)
    io.write_kitti_poses(out / f"{name}_poses_kitti.txt", T_cam)
    io.write_kitti_poses(out / f"{name}_poses_lidar_kitti.txt", T_lidar)
    io.write_tum_poses(out / f"{name}_poses_tum.txt", seq.times[:n], T_cam)
    dump_config(config, out / "config.yaml")
    flags = [asdict(s) for s in odometry.status]
    result: dict = {
        "sequence": name,
        "num_frames": n,
        "median_ms_per_frame": float(np.median(frame_ms[1:] if n > 2 else frame_ms)),
        "mean_ms_per_frame": float(np.mean(frame_ms)),
        "degenerate_frames": [i for i, s in enumerate(flags) if s["degenerate"]],
        "bad_input_frames": {i: s["error"] for i, s in enumerate(flags) if s["error"]},
        "dropped_invalid_points": int(sum(s["num_dropped"] for s in flags)),
        "thinned_points": int(sum(s["num_thinned"] for s in flags)),
    }
    gt = seq.gt_poses_cam
    if gt is not None:
        gt = gt[:n]
        try:
            result.update(metrics.evaluate(gt, T_cam))
            metrics.plot_evaluation(
                gt, T_cam, None, out / "trajectory.png", title=f"sequence {name}"
            )
        except InputError as err:  # too short for the devkit's segments: ATE only
            result["rte_unavailable"] = err.problem
            result["ate"] = metrics.ate(gt, T_cam).to_dict()
    io.write_atomic(out / "frames.json", json.dumps(flags))
    io.write_atomic(out / "metrics.json", json.dumps(result, indent=2))
    return result
