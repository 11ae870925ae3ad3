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
    metrics.json              KITTI RTE and ATE (when ground truth exists), timing (per frame,
                              and stage_ms: each stage's median and p95 ms, gloam_jax.timing,
                              over the frames after the first two), frame
                              flags, the deskew policy and time convention, the defaults taken,
                              what the loader found (dataset_details: a recording's topic,
                              message count and point fields),
                              the model run and why (model_choice: the scans' sensor, the
                              guard's decision)
    trajectory.png            the trajectory (against the ground truth, with the error per
                              segment length when the devkit's segments fit)
    config.yaml               the settings used
    frames.json               each frame's flags and stage_ms (gloam_jax.odometry.FrameStatus)
    checkpoint.npz            while the run is unfinished: the odometry's state, to resume

The poses, frames.json and the checkpoint are written every FLUSH_EVERY frames, each file
atomically, and when the run stops; metrics.json says ``status``: ``running`` (with the pid:
a run whose process is gone was killed), ``interrupted`` (SIGINT, SIGTERM), ``stopped`` (a
bad scan) or ``finished``, and how many frames are written. A run continues from its
checkpoint exactly as it would have gone on (the state is saved bit for bit).
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import closing, suppress
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from gloam_jax import io, metrics, timing
from gloam_jax.config import dump_config
from gloam_jax.datasets import Dataset, open_dataset
from gloam_jax.errors import InputError
from gloam_jax.features import Backbone, get_backbone, intensity_warning
from gloam_jax.guard import Choice, choose
from gloam_jax.interrupt import interrupt_for, stop_between
from gloam_jax.models import GLOAMModel
from gloam_jax.odometry import FrameStatus, Odometry, OdometryConfig, resolve_map_resolution
from gloam_jax.preprocess import (
    ONE_INSTANT,
    VoxelCentres,
    check_units,
    detect_time_convention,
    resolve_deskew,
)
from gloam_jax.sensor import SENSOR_SCANS, SensorSignature, try_measure

Item = TypeVar("Item")
# a frame's scan (N, 4), point times (N,) or None, features (N, D) or None, ms per stage
FrameInput = tuple[
    np.ndarray, np.ndarray | None, np.ndarray | None, VoxelCentres | None, dict[str, float]
]
FLUSH_EVERY = 100  # frames between two writes of the poses and the checkpoint
CHECKPOINT = "checkpoint.npz"
CHECKPOINT_VERSION = 1
BAD_SCAN_POLICIES = ("stop", "skip")


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
    on_bad_scan: str = "stop",
    resume: Checkpoint | None = None,
    flush_every: int = FLUSH_EVERY,
) -> dict:
    """Run odometry over ``frames`` of ``dataset`` and write the run folder; returns the
    metrics dict.

    Every scan of ``frames`` is checked (sizes, headers) and the scan times (increasing) before
    the first is registered; each scan's contents as it is read. ``auto`` deskewing is resolved
    by the data (:func:`plan_deskew`), the model (or the guard's plain GICP) by the first
    scans' sensor (:func:`open_odometry`). Learned methods get per-point features from the
    model's backbone, or from one file per scan in ``features_dir`` (the ``precomputed``
    backbone). ``progress(k, ms)`` after the k-th frame. The next scan is read, its features
    computed and its voxel grid built (:meth:`Odometry.voxel_centres`, all that needs no
    pose) on a worker thread while a frame registers. The time per frame counts registration
    only; feature extraction is timed separately (``median_ms_features``),
    the loop's wall time per frame, everything overlapped, is ``wall_ms_per_frame``, and each
    frame's time by stage (loading included) is in its ``stage_ms``.

    Poses, frame flags and a checkpoint of the odometry are written every ``flush_every``
    frames, each file atomically; on SIGINT or SIGTERM after the frame in progress, with
    ``metrics.json`` saying ``interrupted`` (then KeyboardInterrupt, or Terminated, is raised).
    A scan that cannot be read, or whose contents are wrong, stops the run (``on_bad_scan``
    ``stop``: InputError naming the file and frame, the poses before it kept) or keeps the
    motion prior for its frame (``skip``). ``resume``: continue the run of that checkpoint.
    """
    n = len(frames)
    if n < 2:
        raise InputError(
            dataset.scan_path(frames[0]) if n else None, f"need at least 2 scans, have {n}"
        )
    if on_bad_scan not in BAD_SCAN_POLICIES:
        raise InputError(None, f"--on-bad-scan must be stop or skip, not {on_bad_scan!r}")
    out = Path(out_dir)
    dataset.check(frames)
    check_times(dataset, frames)
    check_units(dataset.frame(frames[0])[0], config.preprocess, dataset.scan_path(frames[0]))
    resolved, deskew = plan_deskew(dataset, config, frames[0])
    setup = open_odometry(dataset, resolved, frames, features_dir)
    odometry, backbone, choice = setup.odometry, setup.backbone, setup.choice
    times = dataset.times
    record = {
        "version": CHECKPOINT_VERSION, "dataset": dataset.name, "num_scans": len(dataset),
        "start": frames.start, "stride": frames.step, "count": n,
        "features_dir": None if features_dir is None else str(features_dir),
        "frame_ms": [], "feature_ms": [], "skipped": [],
        "warnings": [] if choice.warning is None else [choice.warning],
    }  # fmt: skip
    if resume is not None:
        record = resume.continues(record)
        odometry.restore(resume.state, resume.status)
    files = RunFiles(dataset, out, frames)
    frame_ms, feature_ms = record["frame_ms"], record["feature_ms"]
    extra = {"deskew": deskew, "defaults": list(dataset.defaults), "dataset": dataset.kind,
             "dataset_details": dict(dataset.details),
             "frames": {"start": frames.start, "stride": frames.step, "count": n},
             "model_choice": choice.record, "warnings": record["warnings"],
             "map": setup.map,
             "skipped_frames": record["skipped"],
             "frames_after_a_gap": time_gaps(times[np.asarray(frames)])}  # fmt: skip

    def save(status: dict) -> None:
        if odometry.poses and odometry.resumable:  # else nothing final yet: frames 0 and 1
            save_progress(files, odometry, config, record, {**status, **extra})

    def fetch(k: int) -> FrameInput:
        """Frame k's input (:func:`timed_input`). Runs on the prefetch thread."""
        i, path = frames[k], dataset.scan_path(frames[k])

        def read() -> tuple[np.ndarray, np.ndarray | None]:
            scan, point_times = dataset.frame(i)
            if k:  # frame 0 was checked before the run
                check_units(scan, config.preprocess, path)
            return scan, point_times if deskew["used"] == "timestamps" else None

        return timed_input(read, setup.per_point, path, i, odometry if placement.ahead else None)

    placement = VoxelPlacement()
    start = len(odometry.poses)
    loop_start = time.perf_counter()
    with (
        stop_between(signal.SIGINT, signal.SIGTERM) as pending,
        closing(prefetched(fetch, range(start, n))) as inputs,
    ):
        for k, current in zip(range(start, n), inputs, strict=True):
            i = frames[k]
            path = dataset.scan_path(i)
            frame_dt = (
                float(times[i] - times[frames[k - 1]]) if k else config.preprocess.sweep_duration
            )
            try:  # the scan, and its features where the method needs them
                scan, point_times, features, centres, ms = current.result()
            except InputError as err:
                if on_bad_scan == "stop":
                    save({"status": "stopped", "error": str(err)})
                    raise InputError(
                        err.source, f"bad scan at frame {i}: {err.problem} (the {k} poses "
                        "before it are kept; --on-bad-scan skip goes on past it)"
                    ) from None  # fmt: skip
                record["skipped"].append(k)
                odometry.register_frame(None, None, frame_dt, source=f"skipped: {err}")
            else:
                odometry.timer.add(ms)
                if "features" in ms:
                    feature_ms.append(ms["features"])
                if k == 0 and backbone is not None:
                    warning = intensity_warning(backbone, odometry.model.pca, scan)
                    record["warnings"] += [] if warning is None else [warning]
                t0 = time.perf_counter()
                prepared = scan if centres is None else centres  # centres: built ahead
                odometry.register_frame(prepared, point_times, frame_dt, source=str(path),
                                        features=features)  # fmt: skip
                frame_ms.append(1e3 * (time.perf_counter() - t0))
                placement.update(odometry.status[-1].stage_ms)
            if progress is not None:
                progress(k, frame_ms[-1] if frame_ms else 0.0)
            if (signum := pending()) is not None:
                save({"status": "interrupted", "signal": signal.Signals(signum).name})
                raise interrupt_for(signum)
            if (k + 1) % flush_every == 0 and k + 1 < n:
                save({"status": "running", "pid": os.getpid()})
    if feature_ms:
        extra["median_ms_features"] = float(np.median(feature_ms))
    if n > start:  # this process's frames (a resumed run: those after the checkpoint)
        # what keeps up with the sensor: reading, features and registration, overlapped
        extra["wall_ms_per_frame"] = 1e3 * (time.perf_counter() - loop_start) / (n - start)
    result = write_run(files, odometry, config, frame_ms, extra)
    (out / CHECKPOINT).unlink(missing_ok=True)
    return result


def timed_input(
    read: Callable[[], tuple[np.ndarray, np.ndarray | None]],
    backbone: Backbone | None,
    path: str | os.PathLike[str],
    frame: int,
    odometry: Odometry | None = None,
) -> FrameInput:
    """A frame's scan and point times from ``read()``, its per-point features where
    ``backbone`` is given (None otherwise), its :meth:`Odometry.voxel_centres` where
    ``odometry`` is given (with the features of its ``grid_backbone``, if any; None otherwise,
    or where the scan cannot be prepared: registering the raw scan then reports why), and the
    milliseconds each took (stages ``load``, ``features``, ``voxels``)."""
    timer = timing.StageTimer()
    with timer("load"):
        scan, point_times = read()
    features = centres = None
    if backbone is not None:
        with timer("features"):
            features = backbone(scan, path=path, frame=frame)
    if odometry is not None:
        with suppress(InputError):
            centres = odometry.voxel_centres(scan, point_times, str(path), features, timer)
    return scan, point_times, features, centres, timer.ms


class VoxelPlacement:
    """Which thread builds the next frame's voxel grid (:meth:`Odometry.voxel_centres`): the
    prefetch thread while its own work (reading, features) took less than the registration
    without the grid, else the registration. On two cores a frame takes about as long as the
    busier thread; the poses are the same either way."""

    def __init__(self) -> None:
        self.ahead = True

    def update(self, stage_ms: dict[str, float]) -> None:
        """Decide from a registered frame's ``stage_ms``."""
        worker = stage_ms["load"] + stage_ms["features"]
        registration = sum(
            v for k, v in stage_ms.items() if k not in ("load", "features", "voxels")
        )
        self.ahead = worker < registration


def prefetched(fetch: Callable[[int], Item], ks: range) -> Iterator[Future[Item]]:
    """``fetch(k)`` for each k of ``ks``, in order, as futures: the next one runs on a worker
    thread while the caller handles the current one. The odometry's input (reading a scan,
    the backbone's features) is NumPy and scipy code that releases the GIL, so on two cores it
    overlaps the registration instead of adding to it. Leaving the loop early waits for the
    one fetch in flight."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="prefetch") as pool:
        ahead = pool.submit(fetch, ks[0]) if len(ks) else None
        for j in range(len(ks)):
            current = ahead
            ahead = pool.submit(fetch, ks[j + 1]) if j + 1 < len(ks) else None
            yield current


def check_times(dataset: Dataset, frames: range) -> None:
    """InputError naming the first frame of ``frames`` whose scan time is not after the one
    before it (a time going backwards or repeating)."""
    stamps = dataset.times[np.asarray(frames)]
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        how = "repeats" if stamps[k] == stamps[k - 1] else "goes back before"
        raise InputError(
            dataset.scan_path(frames[k]),
            f"frame {frames[k]}: its time {stamps[k]:.6f} s {how} frame {frames[k - 1]}'s "
            f"({stamps[k - 1]:.6f} s); scan times must increase",
        )


def time_gaps(stamps: np.ndarray) -> list[int]:
    """The frames (k, of the stamps (F,)) that come after a gap: over 1.5 times the median time
    step since the frame before (dropped scans, predicted over the whole gap)."""
    steps = np.diff(stamps)
    return (np.flatnonzero(steps > 1.5 * np.median(steps)) + 1).tolist()


@dataclass(frozen=True)
class Checkpoint:
    """What a run folder holds to continue an unfinished run: its ``record`` (the data and
    frames run, timings and skips so far), the odometry ``state`` (:meth:`Odometry.state`),
    the written frames' ``status`` (from frames.json) and how the run ``ended`` (a sentence)."""

    path: Path
    record: dict
    state: dict[str, np.ndarray]
    status: list[FrameStatus]
    ended: str

    @classmethod
    def read(cls, run_dir: str | Path) -> Checkpoint:
        """The checkpoint of ``run_dir``; InputError when there is none to continue from
        (finished, still running, stopped before its first flush)."""
        run_dir = Path(run_dir)
        path, metrics = run_dir / CHECKPOINT, _metrics(run_dir)
        status = metrics.get("status")
        if status == "finished":
            raise InputError(run_dir, "this run finished: nothing to resume")
        if status == "running" and _alive(metrics.get("pid")):
            raise InputError(run_dir, f"this run is still going (process {metrics['pid']})")
        if not path.exists():
            raise InputError(
                run_dir, f"holds no {CHECKPOINT}: the run stopped before its first "
                f"{FLUSH_EVERY} frames were written; start it again"
            )  # fmt: skip
        state = dict(np.load(path, allow_pickle=False))
        record = json.loads(str(state.pop("record")))
        done = record["frames_done"]
        # frames.json is written before the checkpoint: it has these frames, maybe more
        flags = json.loads((run_dir / "frames.json").read_text())[:done]
        ended = how_it_ended({**metrics, "frames_done": done})
        return cls(path, record, state, [FrameStatus(**f) for f in flags], ended)

    def continues(self, record: dict) -> dict:
        """This run's record, after checking that ``record`` (of the run to continue it) is
        of the same data, frames and checkpoint version."""
        for key in ("version", "dataset", "num_scans", "start", "stride", "count",
                    "features_dir"):  # fmt: skip
            if self.record[key] != record[key]:
                raise InputError(
                    self.path, f"is a run with {key} {self.record[key]!r}, not {record[key]!r}"
                )
        return dict(self.record)


def _metrics(run_dir: Path) -> dict:
    path = run_dir / "metrics.json"
    return json.loads(path.read_text()) if path.exists() else {}


def how_it_ended(metrics: dict) -> str:
    """How an unfinished run ended, from its metrics.json (a dict), as a sentence."""
    done, status = metrics.get("frames_done"), metrics.get("status")
    return {
        "interrupted": f"interrupted ({metrics.get('signal')}) after {done} frames",
        "stopped": f"stopped after {done} frames by a bad scan: {metrics.get('error')}",
    }.get(status, f"killed after {done} frames written (no clean stop: SIGKILL or a crash)")


def unfinished_runs(out: Path) -> dict[Path, str]:
    """The runs under ``out`` that stopped before their end and can resume (their process
    gone), with how each ended."""
    found = {}
    runs = out.iterdir() if out.is_dir() else []
    for run in sorted(p for p in runs if p.is_dir() and not p.is_symlink()):
        metrics = _metrics(run)
        status = metrics.get("status")
        if (run / CHECKPOINT).exists() and status in ("running", "interrupted", "stopped"):
            if not (status == "running" and _alive(metrics.get("pid"))):
                found[run] = how_it_ended(metrics)
    return found


def _alive(pid: int | None) -> bool:
    """Whether process ``pid`` (of this machine) runs, other than this one."""
    if pid is None or pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


class RunFiles:
    """The files of a run that grow frame by frame: the poses (KITTI, KITTI in the LiDAR frame,
    TUM) and ``frames.json``, each written whole and atomically at every :meth:`write`. Each
    frame is formatted once: an hour of scans (36000 frames) would otherwise take seconds a
    flush."""

    def __init__(self, dataset: Dataset, out: Path, frames: range) -> None:
        name = dataset.name
        self.dataset, self.out, self.frames, self.done = dataset, out, frames, 0
        self.paths = {
            "cam": out / f"{name}_poses_kitti.txt",
            "lidar": out / f"{name}_poses_lidar_kitti.txt",
            "tum": out / f"{name}_poses_tum.txt",
            "flags": out / "frames.json",
        }
        self.text: dict[str, list[bytes]] = {key: [] for key in self.paths}

    def write(self, odometry: Odometry) -> None:
        """The files of ``odometry``'s frames so far; those of earlier writes must be final
        (:attr:`Odometry.resumable`)."""
        new = slice(self.done, len(odometry.poses))
        if new.start < new.stop:
            T_lidar = np.stack(odometry.poses[new])
            T_cam = io.lidar_to_cam_poses(T_lidar, self.dataset.Tr_cam_velo)
            self.text["cam"].append(io.kitti_pose_text(T_cam))
            self.text["lidar"].append(io.kitti_pose_text(T_lidar))
            stamps = self.dataset.times[np.asarray(self.frames[new])]
            self.text["tum"].append(io.tum_pose_text(stamps, T_cam))
            self.text["flags"] += [json.dumps(asdict(s)).encode() for s in odometry.status[new]]
            self.done = new.stop
        for key, path in self.paths.items():
            chunks = self.text[key]
            io.write_atomic(path, b"[" + b", ".join(chunks) + b"]" if key == "flags" else
                            b"".join(chunks))  # fmt: skip


def save_progress(files: RunFiles, odometry: Odometry, config: OdometryConfig, record: dict,
                  metrics: dict) -> None:  # fmt: skip
    """Write what is computed so far, each file atomically: the poses and ``frames.json``, the
    settings, the checkpoint and, last, ``metrics.json`` (``metrics``, with ``frames_done`` and
    the dataset index of the next scan)."""
    files.write(odometry)
    out, done, frames = files.out, files.done, files.frames
    dump_config(config, out / "config.yaml")
    record = {**record, "frames_done": done}
    io.write_npz(out / CHECKPOINT, record=np.array(json.dumps(record)), **odometry.state())
    metrics = {"sequence": files.dataset.name, "frames_done": done,
               "next_scan": frames[done] if done < len(frames) else None, **metrics}  # fmt: skip
    io.write_atomic(out / "metrics.json", json.dumps(metrics, indent=2))


@dataclass(frozen=True)
class RunSetup:
    """What a run's first scans decide: the odometry (its model or the guard's variant, its map
    resolution), the learned method's feature source, the one to call per raw scan (both None
    where not needed: ``per_point`` where the odometry's ``grid_backbone`` makes them), the
    model choice (``choice.record``: metrics.json's ``model_choice``) and the map's record."""

    odometry: Odometry
    backbone: Backbone | None
    choice: Choice
    map: dict
    per_point: Backbone | None


def open_odometry(
    dataset: Dataset, config: OdometryConfig, frames: range, features_dir: str | Path | None
) -> RunSetup:
    """The odometry for a run, set up on its first scans: the model by
    :func:`gloam_jax.guard.choose`, ``map_resolution: auto`` by :func:`plan_map`."""
    first = frames[:SENSOR_SCANS]
    scans = [dataset.frame(i)[0] for i in first]

    def features(model: GLOAMModel, k: int) -> np.ndarray:
        if features_dir is not None:
            backbone = get_backbone("precomputed", folder=features_dir)
        else:
            backbone = model.backbone()
        return backbone(scans[k], path=dataset.scan_path(first[k]), frame=first[k])

    choice = choose(config, scans, features)
    settings, map_record = plan_map(choice, scans)
    odometry = Odometry(settings, choice.model)
    backbone = _backbone(odometry, features_dir)
    on_grid = features_dir is None and odometry.grid_backbone is not None
    return RunSetup(odometry, backbone, choice, map_record, None if on_grid else backbone)


def plan_map(choice: Choice, scans: list[np.ndarray]) -> tuple[OdometryConfig, dict]:
    """The chosen settings with ``map_resolution`` a number (``auto``: by the sensor of the
    first ``scans``, :func:`~gloam_jax.odometry.resolve_map_resolution`), and a record of it
    for metrics.json (``map``: the setting, the resolution, why)."""
    setting = choice.config.map_resolution
    sensor = None
    if setting == "auto":
        if "sensor" in choice.record:  # measured already (or found unmeasurable) for the model
            found = choice.record["sensor"]
            sensor = None if found is None else SensorSignature.from_dict(found)
        else:
            sensor = try_measure(scans)
    resolution, reason = resolve_map_resolution(setting, sensor)
    record = {"setting": setting, "resolution": resolution, "reason": reason}
    return dataclasses.replace(choice.config, map_resolution=resolution), record


def _backbone(odometry: Odometry, features_dir: str | Path | None) -> Backbone | None:
    """The feature source of a learned method: the model's backbone or a folder of files."""
    if not odometry.needs_features:
        return None
    if features_dir is not None:
        return get_backbone("precomputed", folder=features_dir)
    return odometry.model.backbone()


def write_run(files: RunFiles, odometry: Odometry, config: OdometryConfig,
              frame_ms: list[float], extra: dict) -> dict:  # fmt: skip
    """The finished run's files: poses and flags, ground truth, metrics, plot, settings."""
    files.write(odometry)
    dataset, out, frames = files.dataset, files.out, files.frames
    name, n = dataset.name, len(frames)
    index = np.asarray(frames)
    T_cam = io.lidar_to_cam_poses(np.stack(odometry.poses), dataset.Tr_cam_velo)
    stamps = dataset.times[index]
    dump_config(config, out / "config.yaml")
    flags = [asdict(s) for s in odometry.status]
    result: dict = {
        "status": "finished",
        "sequence": name,
        "num_frames": n,
        "median_ms_per_frame": float(np.median(frame_ms[1:] if n > 2 else frame_ms)),
        "mean_ms_per_frame": float(np.mean(frame_ms)),
        # compilation included: what JAX's persistent cache shortens on a second run
        "first_frames_ms": [float(ms) for ms in frame_ms[:3]],
        # frames 0 and 1 left out: the first compilations, and frame 1 redoes both
        "stage_ms": timing.summarise(s["stage_ms"] for s in (flags[2:] if n > 3 else flags)),
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
        except InputError as err:  # too short for the devkit's segments: no RTE
            result.update(metrics.evaluate_without_rte(gt, T_cam, err.problem))
            metrics.plot_trajectory(T_cam, gt, plot, f"{name}: RTE unavailable ({err.problem})")
    else:
        metrics.plot_trajectory(T_cam, None, plot, f"{name} (no ground truth)")
    io.write_atomic(out / "metrics.json", json.dumps(result, indent=2))
    return result
