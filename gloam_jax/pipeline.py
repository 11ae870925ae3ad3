"""Dataset -> odometry -> metrics -> result files, for one sequence of scans.

The data comes from any registered loader (:mod:`gloam_jax.datasets`: the KITTI layout, a
folder of scans, a ROS bag or MCAP recording). A run folder holds (``NN`` the dataset's name:
the KITTI sequence id, the folder's or the recording's name)::

    NN_poses_kitti.txt        estimate, ground-truth convention (camera 0 with a calibration,
                              else the LiDAR frame); compare with the ground truth
    NN_poses_lidar_kitti.txt  estimate, LiDAR frame (T_world_lidar, first pose identity)
    NN_poses_tum.txt          estimate as NN_poses_kitti.txt, with the frame times
    NN_gt_kitti.txt           ground truth of the frames run, when it exists (evo_ape kitti)
    NN_gt_tum.txt             the same with the frame times (evo_ape tum)
    metrics.json              KITTI RTE and ATE (when ground truth exists), timing, frame
                              flags, the deskew policy and time convention, the defaults taken,
                              what the loader found (dataset_details: a recording's topic,
                              message count and point fields),
                              the model run and why (model_choice: the scans' sensor, the
                              guard's decision)
    trajectory.png            the trajectory (against the ground truth, with the error per
                              segment length when the devkit's segments fit)
    config.yaml               the settings used
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from gloam_jax import io, metrics
from gloam_jax.config import dump_config
from gloam_jax.datasets import Dataset, open_dataset
from gloam_jax.errors import InputError
from gloam_jax.features import Backbone, get_backbone, intensity_warning
from gloam_jax.guard import Choice, choose
from gloam_jax.models import GLOAMModel
from gloam_jax.odometry import Odometry, OdometryConfig
from gloam_jax.preprocess import ONE_INSTANT, detect_time_convention, resolve_deskew
from gloam_jax.sensor import SENSOR_SCANS


def select_frames(n: int, start: int = 0, frames: int | None = None, stride: int = 1) -> range:
    """Frame indices ``start, start + stride, ...``: at most ``frames`` of the ``n`` scans."""
    if start < 0 or stride < 1 or (frames is not None and frames < 1):
        raise InputError(None, f"bad frame selection start={start} frames={frames} stride={stride}")
    if start >= n:
        raise InputError(None, f"--start {start} is past the last of the {n} scans")
    chosen = range(start, n, stride)
    return chosen if frames is None else chosen[:frames]


def run_sequence(
    root: str | Path,
    sequence: str | int | None,
    config: OdometryConfig,
    out_dir: str | Path,
    *,
    frames: int | None = None,
    progress: Callable[[int, float], None] | None = None,
    features_dir: str | Path | None = None,
) -> dict:
    """:func:`run_dataset` on the data at ``root`` (a KITTI root with ``sequence``, or a
    folder of scans), its first ``frames`` scans."""
    dataset = open_dataset(root, None if sequence is None else str(sequence))
    chosen = select_frames(len(dataset), 0, frames)
    return run_dataset(
        dataset, config, out_dir, chosen, progress=progress, features_dir=features_dir
    )


def plan_deskew(
    dataset: Dataset, config: OdometryConfig, first: int
) -> tuple[OdometryConfig, dict]:
    """The settings with ``preprocess.deskew`` resolved for this data (``auto`` -> one
    policy), and a record of it: the policy asked for and used, why, and the per-point time
    convention found in frame ``first`` (checked again on every frame)."""
    prep = config.preprocess
    used, why = resolve_deskew(prep.deskew, dataset.has_point_times, dataset.distorted)
    record = {"policy": prep.deskew, "used": used, "reason": why, "time_convention": None}
    if used == "timestamps":
        _, times = dataset.frame(first)
        if times is None:
            raise InputError(dataset.scan_path(first), "has no per-point times, unlike the others")
        source = dataset.scan_path(first)
        record["time_convention"] = detect_time_convention(times, prep.sweep_duration, source)
        record["reason"] += f"; per-point times in {record['time_convention']}"
        if record["time_convention"] == ONE_INSTANT:
            record["reason"] += (
                " (all equal: taken as deskewed already, so no point moves; set "
                "preprocess.deskew: azimuth if these are raw spinning-sensor sweeps)"
            )
    resolved = dataclasses.replace(config, preprocess=dataclasses.replace(prep, deskew=used))
    return resolved, record


def run_dataset(
    dataset: Dataset,
    config: OdometryConfig,
    out_dir: str | Path,
    frames: range,
    *,
    progress: Callable[[int, float], None] | None = None,
    features_dir: str | Path | None = None,
) -> dict:
    """Run odometry over ``frames`` of ``dataset`` and write the run folder; returns the
    metrics dict.

    Every scan of ``frames`` is checked (sizes, headers) before the first is registered.
    ``auto`` deskewing is resolved by the data (:func:`plan_deskew`), the model (or the
    guard's plain GICP) by the first scans' sensor (:func:`choose_model`). Learned methods get
    per-point features from the model's backbone, or from one file per scan in
    ``features_dir`` (the ``precomputed`` backbone). ``progress(k, ms)`` after the k-th frame.
    The time per frame counts registration only; feature extraction is timed separately
    (``median_ms_features``).
    """
    n = len(frames)
    if n < 2:
        raise InputError(
            dataset.scan_path(frames[0]) if n else None, f"need at least 2 scans, have {n}"
        )
    dataset.check(frames)
    resolved, deskew = plan_deskew(dataset, config, frames[0])
    choice = choose_model(dataset, resolved, frames, features_dir)
    odometry = Odometry(choice.config, choice.model)
    backbone = _backbone(odometry, features_dir)
    times = dataset.times
    frame_ms, feature_ms = [], []
    warnings = [] if choice.warning is None else [choice.warning]
    for k, i in enumerate(frames):
        scan, point_times = dataset.frame(i)
        if k == 0 and backbone is not None:
            warning = intensity_warning(backbone, odometry.model.pca, scan)
            warnings += [] if warning is None else [warning]
        if deskew["used"] != "timestamps":
            point_times = None
        prev = frames[k - 1] if k > 0 else None
        frame_dt = (
            float(times[i] - times[prev]) if prev is not None else config.preprocess.sweep_duration
        )
        path = dataset.scan_path(i)
        features = None
        if backbone is not None:
            t0 = time.perf_counter()
            features = backbone(scan, path=path, frame=i)
            feature_ms.append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        odometry.register_frame(scan, point_times, frame_dt, source=str(path), features=features)
        frame_ms.append(1e3 * (time.perf_counter() - t0))
        if progress is not None:
            progress(k, frame_ms[-1])
    extra = {"deskew": deskew, "defaults": list(dataset.defaults), "dataset": dataset.kind,
             "dataset_details": dict(dataset.details),
             "frames": {"start": frames.start, "stride": frames.step, "count": n},
             "model_choice": choice.record, "warnings": warnings}  # fmt: skip
    if feature_ms:
        extra["median_ms_features"] = float(np.median(feature_ms))
    return write_run(dataset, odometry, config, out_dir, frames, frame_ms, extra)


def choose_model(
    dataset: Dataset, config: OdometryConfig, frames: range, features_dir: str | Path | None
) -> Choice:
    """The model for a run (:func:`gloam_jax.guard.choose`), judged on its first scans."""
    first = frames[:SENSOR_SCANS]
    scans = [dataset.frame(i)[0] for i in first]

    def features(model: GLOAMModel, k: int) -> np.ndarray:
        if features_dir is not None:
            backbone = get_backbone("precomputed", folder=features_dir)
        else:
            backbone = model.backbone()
        return backbone(scans[k], path=dataset.scan_path(first[k]), frame=first[k])

    return choose(config, scans, features)


def _backbone(odometry: Odometry, features_dir: str | Path | None) -> Backbone | None:
    """The feature source of a learned method: the model's backbone or a folder of files."""
    if not odometry.needs_features:
        return None
    if features_dir is not None:
        return get_backbone("precomputed", folder=features_dir)
    return odometry.model.backbone()


def write_run(dataset: Dataset, odometry: Odometry, config: OdometryConfig, out_dir: str | Path,
              frames: range, frame_ms: list[float], extra: dict) -> dict:  # fmt: skip
    out = Path(out_dir)
    name, n = dataset.name, len(frames)
    index = np.asarray(frames)
    T_lidar = np.stack(odometry.poses)
    T_cam = io.lidar_to_cam_poses(T_lidar, dataset.Tr_cam_velo)
    stamps = dataset.times[index]
    io.write_kitti_poses(out / f"{name}_poses_kitti.txt", T_cam)
    io.write_kitti_poses(out / f"{name}_poses_lidar_kitti.txt", T_lidar)
    io.write_tum_poses(out / f"{name}_poses_tum.txt", stamps, T_cam)
    dump_config(config, out / "config.yaml")
    flags = [asdict(s) for s in odometry.status]
    result: dict = {
        "sequence": name,
        "num_frames": n,
        "median_ms_per_frame": float(np.median(frame_ms[1:] if n > 2 else frame_ms)),
        "mean_ms_per_frame": float(np.mean(frame_ms)),
        # compilation included: what JAX's persistent cache shortens on a second run
        "first_frames_ms": [float(ms) for ms in frame_ms[:3]],
        "degenerate_frames": [i for i, s in enumerate(flags) if s["degenerate"]],
        "bad_input_frames": {i: s["error"] for i, s in enumerate(flags) if s["error"]},
        "dropped_invalid_points": int(sum(s["num_dropped"] for s in flags)),
        "thinned_points": int(sum(s["num_thinned"] for s in flags)),
        **extra,
    }
    gt = dataset.gt_poses_cam
    plot = out / "trajectory.png"
    if gt is not None:
        # The ground truth of the frames run, relative to the first, as the estimate is.
        gt = np.linalg.inv(gt[index[0]]) @ gt[index]
        io.write_kitti_poses(out / f"{name}_gt_kitti.txt", gt)
        io.write_tum_poses(out / f"{name}_gt_tum.txt", stamps, gt)
        try:
            result.update(metrics.evaluate(gt, T_cam))
            metrics.plot_evaluation(gt, T_cam, None, plot, title=f"sequence {name}")
        except InputError as err:  # too short for the devkit's segments: ATE only
            result["rte_unavailable"] = err.problem
            result["ate"] = metrics.ate(gt, T_cam).to_dict()
            metrics.plot_trajectory(T_cam, gt, plot, f"{name}: RTE unavailable ({err.problem})")
    else:
        metrics.plot_trajectory(T_cam, None, plot, f"{name} (no ground truth)")
    io.write_atomic(out / "frames.json", json.dumps(flags))
    io.write_atomic(out / "metrics.json", json.dumps(result, indent=2))
    return result
