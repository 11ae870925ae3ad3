"""Long recordings through `gloam run`: kills and resumes, bad scans, gaps, time and units."""

import dataclasses
import json
import random
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from gloam_jax import io
from gloam_jax.cli import app
from gloam_jax.datasets import open_dataset
from gloam_jax.errors import InputError
from gloam_jax.odometry import FrameStatus, OdometryConfig
from gloam_jax.pipeline import VoxelPlacement, run_dataset, select_frames, unfinished_runs
from gloam_jax.timing import STAGES

# One worker runs this module (pytest-xdist --dist loadgroup): its reference run is made once.
pytestmark = pytest.mark.xdist_group("pipeline")

runner = CliRunner()
FLUSH = ["--flush-every", "4"]


def _lidar_poses(run) -> np.ndarray:
    (path,) = run.glob("*_poses_lidar_kitti.txt")
    return io.read_kitti_poses(path)


@pytest.fixture(scope="module")
def reference(sim_sequence, tmp_path_factory):
    """The uninterrupted run of the 40-frame drive."""
    out = tmp_path_factory.mktemp("reference")
    result = runner.invoke(app, ["run", str(sim_sequence), *FLUSH, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert not (out / "latest" / "checkpoint.npz").exists()  # a finished run needs none
    return _lidar_poses(out / "latest")


def _scans_folder(sim_sequence, folder, keep=None):
    """The drive's scans, point times and ground truth as a folder of scans (``keep``: only
    those frame indices, their file numbers kept)."""
    seq = io.KittiSequence(sim_sequence, "00")
    keep = range(len(seq)) if keep is None else keep
    (folder / "timestamps").mkdir(parents=True)
    for i in keep:
        shutil.copy(seq.scan_path(i), folder)
        np.save(folder / "timestamps" / f"{i:06d}.npy", seq.point_times(i))
    io.write_kitti_poses(folder / "poses.txt", seq.gt_poses_lidar[list(keep)])
    return seq


@pytest.mark.parametrize(
    "stop", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT], ids=["SIGKILL", "SIGTERM", "SIGINT"]
)
def test_a_killed_run_resumes_with_the_same_poses(sim_sequence, reference, tmp_path, stop):
    target = random.randint(5, 30)  # frames written before the kill
    out = tmp_path / "out"
    command = [sys.executable, "-m", "gloam_jax", "run", str(sim_sequence), *FLUSH,
               "--out", str(out)]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    metrics = None
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None:
        runs = [p for p in out.glob("20*") if (p / "metrics.json").exists()]
        if runs:
            metrics = json.loads((runs[0] / "metrics.json").read_text())
            if metrics["frames_done"] >= target:
                break
        time.sleep(0.05)
    process.send_signal(stop)
    _, err = process.communicate(timeout=120)
    codes = {signal.SIGKILL: -9, signal.SIGTERM: 143, signal.SIGINT: 130}
    assert process.returncode == codes[stop], err.decode()
    (run,) = out.glob("20*")
    metrics = json.loads((run / "metrics.json").read_text())
    done = metrics["frames_done"]
    written = _lidar_poses(run)
    assert target <= done == len(written) < 40, f"killed at frame {target}"
    # Every pose written is the uninterrupted run's.
    np.testing.assert_allclose(written, reference[:done], atol=1e-9)
    assert metrics["status"] == ("running" if stop == signal.SIGKILL else "interrupted")
    how = "killed after" if stop == signal.SIGKILL else f"interrupted ({stop.name}) after"
    # The next `gloam run` into the same folder says so.
    ((found, ended),) = unfinished_runs(out).items()
    assert found == run and ended.startswith(f"{how} {done} frames")
    result = runner.invoke(app, ["run", str(sim_sequence), "--resume", str(run), *FLUSH])
    assert result.exit_code == 0, result.output
    assert f"resuming {run}: {how} {done} frames" in result.output.replace("\n", "")
    resumed = _lidar_poses(run)
    assert len(resumed) == 40
    # The frames after the resume point, as the uninterrupted run has them (1e-6 m).
    np.testing.assert_allclose(resumed[:, :3, 3], reference[:, :3, 3], atol=1e-6,
                               err_msg=f"resumed after {done} frames")  # fmt: skip
    final = json.loads((run / "metrics.json").read_text())
    assert final["status"] == "finished" and final["num_frames"] == 40
    assert not (run / "checkpoint.npz").exists() and (out / "latest").resolve() == run.resolve()
    again = runner.invoke(app, ["run", str(sim_sequence), "--resume", str(run)])
    assert again.exit_code == 2 and "this run finished: nothing to resume" in again.output


def test_resume_takes_the_runs_own_settings(sim_sequence, tmp_path):
    result = runner.invoke(
        app, ["run", str(sim_sequence), "--resume", str(tmp_path), "--method", "gloam"]
    )
    assert result.exit_code == 2 and "leave out --method" in result.output
    result = runner.invoke(app, ["run", str(sim_sequence), "--resume", str(tmp_path)])
    assert result.exit_code == 2 and "holds no checkpoint.npz" in result.output


def test_a_bad_scan_stops_the_run_or_is_skipped(sim_sequence, reference, tmp_path):
    folder = tmp_path / "scans"
    seq = _scans_folder(sim_sequence, folder)
    # A damaged scan that passes the up-front checks (its size is right): garbage contents.
    bad = folder / "000017.bin"
    bad.write_bytes(np.random.default_rng(0).bytes(bad.stat().st_size))
    out = tmp_path / "stop"
    stopped = runner.invoke(app, ["run", str(folder), *FLUSH, "--out", str(out)])
    assert stopped.exit_code == 2
    assert "000017.bin: bad scan at frame 17" in stopped.output
    assert "Traceback" not in stopped.output
    (run,) = out.glob("20*")
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["status"] == "stopped" and metrics["frames_done"] == 17
    np.testing.assert_allclose(_lidar_poses(run)[:, :3, 3], reference[:17, :3, 3], atol=1e-6)
    # Going on past it: its pose is the motion prior, flagged; the rest stays on track.
    resumed = runner.invoke(
        app, ["run", str(folder), "--resume", str(run), "--on-bad-scan", "skip", *FLUSH]
    )
    assert resumed.exit_code == 0, resumed.output
    assert "skipped (bad scans, motion prior kept): frame(s) 17" in resumed.output.replace("\n", "")
    flags = json.loads((run / "frames.json").read_text())
    assert flags[17]["error"].startswith("skipped: ") and "000017.bin" in flags[17]["error"]
    assert [k for k, f in enumerate(flags) if f["error"]] == [17]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["skipped_frames"] == [17]
    poses = _lidar_poses(run)
    predicted = poses[16] @ np.linalg.inv(poses[15]) @ poses[16]  # constant velocity
    np.testing.assert_allclose(poses[17], predicted, atol=1e-6)
    error = np.linalg.norm(poses[:, :3, 3] - seq.gt_poses_lidar[:, :3, 3], axis=1)
    assert error.max() < 0.3, error
    # A run with skip from the start gives the same poses.
    skipped = run_dataset(open_dataset(folder), OdometryConfig(), tmp_path / "skip",
                          select_frames(40), on_bad_scan="skip")  # fmt: skip
    assert skipped["skipped_frames"] == [17]
    np.testing.assert_allclose(_lidar_poses(tmp_path / "skip")[:, :3, 3], poses[:, :3, 3],
                               atol=1e-6)  # fmt: skip


def test_a_gap_in_the_scans_is_predicted_over_its_time(sim_sequence, tmp_path):
    folder = tmp_path / "gap"
    keep = [*range(12), *range(15, 24)]  # scans 12-14 dropped: 0.4 s between 11 and 15
    seq = _scans_folder(sim_sequence, folder, keep)
    dataset = open_dataset(folder)
    np.testing.assert_allclose(np.diff(dataset.times)[11], 0.4)
    assert "3 numbers missing" in dataset.defaults[-1]
    result = run_dataset(dataset, OdometryConfig(), tmp_path / "run", select_frames(len(keep)))
    assert result["frames_after_a_gap"] == [12]
    error = np.linalg.norm(
        _lidar_poses(tmp_path / "run")[:, :3, 3] - seq.gt_poses_lidar[keep, :3, 3], axis=1
    )
    assert error.max() < 0.3, error
    # Taken as 10 Hz (the step of one frame), the prediction falls 3 frames short.
    (folder / "times.txt").write_text("".join(f"{0.1 * k}\n" for k in range(len(keep))))
    run_dataset(open_dataset(folder), OdometryConfig(), tmp_path / "10hz",
                select_frames(len(keep)))  # fmt: skip
    flat = np.linalg.norm(
        _lidar_poses(tmp_path / "10hz")[:, :3, 3] - seq.gt_poses_lidar[keep, :3, 3], axis=1
    )
    assert flat[12:].max() > 3 * error[12:].max(), (flat, error)


def test_times_that_go_back_or_repeat_are_one_line_naming_the_frame(sim_sequence, tmp_path):
    folder = tmp_path / "scans"
    _scans_folder(sim_sequence, folder, range(10))
    for times, how in (([0, 0.1, 0.2, 0.3, 0.3], "repeats"), ([0, 0.1, 0.2, 0.3, 0.25],
                                                                "goes back before")):  # fmt: skip
        stamps = [*times, *(0.1 * np.arange(5, 10))]
        (folder / "times.txt").write_text("".join(f"{t}\n" for t in stamps))
        result = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "out")])
        assert result.exit_code == 2
        line = result.output.strip().splitlines()[-1]
        assert f"000004.bin: frame 4: its time {times[4]:.6f} s {how} frame 3's" in line
        assert "Traceback" not in result.output and not (tmp_path / "out").exists()


def test_a_scan_in_millimetres_is_one_line(sim_sequence, tmp_path):
    folder = tmp_path / "mm"
    _scans_folder(sim_sequence, folder, range(4))
    for path in folder.glob("*.bin"):
        scan = io.read_scan(path)
        scan[:, :3] *= 1000
        io.write_scan_bin(path, scan)
    result = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2 and "Traceback" not in result.output
    line = result.output.strip().splitlines()[-1]
    assert "000000.bin: median range" in line and "looks like millimetres" in line


def test_check_units():
    from gloam_jax.preprocess import PreprocessConfig, check_units

    rng = np.random.default_rng(0)
    metres = rng.normal(0, 20, (1000, 4)).astype(np.float32)
    check_units(metres, PreprocessConfig())
    far = metres.copy()
    far[:, :3] *= 60  # median about 1.6 km
    with pytest.raises(InputError, match="x.bin: median range .* looks like millimetres"):
        check_units(far, PreprocessConfig(), "x.bin")
    beyond = metres.copy()
    beyond[:995, :3] += 500  # 99.5 % beyond 100 m, median well under 1 km
    with pytest.raises(InputError, match=r"99\.5 % of points beyond"):
        check_units(beyond, PreprocessConfig(), "x.bin")
    beyond[:985, :3] = metres[:985, :3]
    check_units(beyond, PreprocessConfig())  # 1 % far returns: a normal scan


def test_a_two_million_point_scan_runs_within_4_gb(tmp_path):
    rng = np.random.default_rng(0)
    n = 2_000_000  # a 128-beam sensor's sweep: a street of ground, facades and poles
    kind = rng.integers(0, 4, n)
    x = np.where(kind == 3, rng.integers(-6, 6, n) * 10 + rng.normal(0, 0.1, n),
                 rng.uniform(-60, 60, n))  # fmt: skip
    y = np.select([kind == 0, kind == 1, kind == 2], [rng.uniform(-10, 10, n), -10.0, 10.0],
                  rng.choice([-6.0, 6.0], n) + rng.normal(0, 0.1, n))  # fmt: skip
    z = np.where(kind == 0, -1.8, rng.uniform(-1.8, 8, n))
    scan = np.column_stack([x, y, z, rng.uniform(0, 1, n)]).astype(np.float32)
    for k in range(3):
        io.write_scan_bin(tmp_path / "scans" / f"{k:06d}.bin", scan - [0.5 * k, 0, 0, 0])
    run = [sys.executable, "-m", "gloam_jax", "run", str(tmp_path / "scans"), "--out",
           str(tmp_path / "out"), "--no-compilation-cache"]  # fmt: skip
    # The peak of the run alone: a parent that only waits for it.
    measure = (
        "import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
        "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)"
    )
    result = subprocess.run([sys.executable, "-c", measure, *run], capture_output=True,
                            text=True, timeout=600)  # fmt: skip
    code, peak_kib = map(int, result.stdout.split()[-2:])
    assert code == 0, result.stdout + result.stderr
    assert peak_kib * 1024 < 4 * 2**30, f"peak RSS {peak_kib / 2**20:.2f} GiB"
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["num_frames"] == 3 and not metrics["bad_input_frames"]


def test_the_voxel_grid_goes_to_the_thread_with_less_to_do():
    placement = VoxelPlacement()
    assert placement.ahead  # the first frame's grid: the prefetch thread has read nothing yet
    gicp = dict.fromkeys(STAGES, 0.0) | {"load": 3.0, "voxels": 28.0, "neighbours": 35.0}
    placement.update(gicp)
    assert placement.ahead
    # a backbone longer than the registration without the grid: the grid joins the registration
    placement.update(gicp | {"features": 136.0, "neighbours": 65.0, "solve": 19.0})
    assert not placement.ahead
    placement.update(gicp | {"features": 20.0})
    assert placement.ahead


def test_a_run_records_each_frames_stages_and_their_median_and_p95(sim_sequence, tmp_path):
    """frames.json: each frame's stage_ms, loading and the voxel grid (both on the prefetch
    thread) included; metrics.json: each stage's median
    and p95 over the frames after the first two. Older frames.json entries without times
    still load."""
    result = run_dataset(open_dataset(sim_sequence, "00"), OdometryConfig(), tmp_path,
                         select_frames(40, 0, 6), flush_every=4)  # fmt: skip
    flags = json.loads((tmp_path / "frames.json").read_text())
    stage_ms = [f["stage_ms"] for f in flags]
    assert len(stage_ms) == 6 and all(tuple(ms) == STAGES for ms in stage_ms)
    assert all(ms["load"] > 0 and ms["voxels"] > 0 and min(ms.values()) >= 0 for ms in stage_ms)
    assert all(ms["solve"] > 0 and ms["neighbours"] > 0 for ms in stage_ms[1:])
    # the stages inside registration add up to its time (frames 0, 1 redone within frame 1's),
    # and its voxel grid where the registration built it (the prefetch thread was the busier
    # when the grid was due: pipeline.VoxelPlacement, decided while the frames run)
    registration = [sum(v for k, v in ms.items() if k not in ("load", "features", "voxels"))
                    for ms in stage_ms]  # fmt: skip
    first = zip(result["first_frames_ms"], registration[:3], stage_ms[:3], strict=True)
    for frame_ms, inside, ms in first:
        assert inside - 0.5 <= frame_ms <= inside + ms["voxels"] + 0.5
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["stage_ms"] == result["stage_ms"]
    for stage in STAGES:
        later = [ms[stage] for ms in stage_ms[2:]]
        summary = metrics["stage_ms"][stage]
        assert summary["median"] == pytest.approx(np.median(later), abs=0.01)
        assert summary["p95"] == pytest.approx(np.percentile(later, 95), abs=0.01)
    old = {k: v for k, v in flags[3].items() if k != "stage_ms"}
    assert FrameStatus(**old).stage_ms == {}


def test_prefetched_scans_and_features_give_the_poses_of_a_frame_by_frame_loop(
    sim_sequence, tmp_path
):
    """The run reads scan k+1 and computes its features on a worker thread while scan k
    registers; the poses are those of the plain loop, and the worker's load and features
    times land in each frame's stages."""
    from gloam_jax.config import load_config
    from gloam_jax.models import load_model, shipped_model_path
    from gloam_jax.odometry import Odometry

    model_path = shipped_model_path("hdl64")
    config = dataclasses.replace(load_config("gloam"), model=str(model_path))
    dataset = open_dataset(sim_sequence, "00")
    result = run_dataset(dataset, config, tmp_path / "run", select_frames(40, 0, 6))
    model = load_model(model_path)
    odometry, backbone = Odometry(config, model), model.backbone()
    for i in range(6):
        scan, point_times = dataset.frame(i)
        frame_dt = float(dataset.times[i] - dataset.times[i - 1]) if i else 0.1
        # a backbone on the odometry's voxel grid makes the features itself
        features = None if odometry.grid_backbone is not None else backbone(scan)
        odometry.register_frame(scan, point_times, frame_dt, features=features)
    np.testing.assert_array_equal(_lidar_poses(tmp_path / "run"), np.stack(odometry.poses))
    flags = json.loads((tmp_path / "run" / "frames.json").read_text())
    assert all(f["stage_ms"]["features"] > 0 and f["stage_ms"]["load"] > 0 for f in flags)
    assert result["median_ms_features"] > 0 and result["wall_ms_per_frame"] > 0
