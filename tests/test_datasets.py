"""Loaders: a KITTI root or any folder of scans runs the same way; optional files say their
defaults; bad scans are found before the first frame; real KITTI scans run out of the box."""

import json
import shutil

import numpy as np
import pytest
from repo_scripts import import_script
from shared_data import shared_path
from typer.testing import CliRunner

from gloam_jax import io
from gloam_jax.cli import app
from gloam_jax.datasets import LOADERS, open_dataset
from gloam_jax.errors import InputError
from gloam_jax.io.scans import write_scan_pcd
from gloam_jax.odometry import OdometryConfig
from gloam_jax.pipeline import run_dataset, select_frames

runner = CliRunner()


def test_the_registry_picks_the_loader_by_the_layout(sim_sequence, tmp_path):
    assert {"kitti", "folder"} <= set(LOADERS)
    kitti = open_dataset(sim_sequence, "00")
    assert kitti.kind == "kitti" and kitti.distorted and kitti.has_point_times
    assert open_dataset(sim_sequence / "sequences" / "00").name == "00"  # the sequence folder
    folder = tmp_path / "scans"
    folder.mkdir()
    for name in ("10.bin", "2.bin", "1.bin"):
        shutil.copy(sim_sequence / "sequences" / "00" / "velodyne" / "000000.bin", folder / name)
    dataset = open_dataset(folder)
    assert dataset.kind == "folder" and not dataset.distorted and dataset.gt_poses_cam is None
    assert [dataset.scan_path(i).name for i in range(3)] == ["1.bin", "2.bin", "10.bin"]
    assert [d.split(":")[0] for d in dataset.defaults] == [
        "no calib.txt",
        "no times.txt",
        "no poses.txt",
    ]
    np.testing.assert_allclose(dataset.times, [0.0, 0.1, 0.2])
    np.save(folder / "3.npy", np.zeros((5, 4), np.float32))
    with pytest.raises(InputError, match=r"scans of several formats \(.bin: 3, .npy: 1\)"):
        open_dataset(folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty: neither a KITTI root"):
        open_dataset(tmp_path / "empty")
    with pytest.raises(InputError, match="nowhere: not found"):
        open_dataset(tmp_path / "nowhere")


def test_frame_selection():
    assert list(select_frames(10, 2, 3, 2)) == [2, 4, 6]
    assert list(select_frames(10, 7, None, 1)) == [7, 8, 9]
    with pytest.raises(InputError, match="--start 10 is past the last of the 10 scans"):
        select_frames(10, 10)


@pytest.mark.parametrize("data", ["binary", "binary_compressed"])
def test_a_folder_of_pcd_scans_runs_like_the_kitti_layout(sim_sequence, tmp_path, data):
    kitti = open_dataset(sim_sequence, "00")
    folder = tmp_path / "pcd"
    folder.mkdir()
    frames = range(5)
    for i in frames:
        scan, times = kitti.frame(i)
        write_scan_pcd(folder / f"{i:04d}.pcd", scan, data, times=times)
    # The ground truth and frame times beside the scans, as a user would put them.
    io.write_calib(folder / "calib.txt", {"Tr": kitti.Tr_cam_velo})
    (folder / "times.txt").write_text("".join(f"{t}\n" for t in kitti.times[:5]))
    io.write_kitti_poses(folder / "poses.txt", kitti.gt_poses_cam[:5])
    dataset = open_dataset(folder)
    assert dataset.has_point_times and dataset.defaults == []
    result = run_dataset(dataset, OdometryConfig(), tmp_path / "pcd_run", select_frames(5))
    assert result["deskew"]["used"] == "timestamps"
    assert result["deskew"]["time_convention"] == "s from mid-sweep"
    reference = run_dataset(kitti, OdometryConfig(), tmp_path / "bin_run", frames)
    np.testing.assert_allclose(
        io.read_kitti_poses(tmp_path / "pcd_run" / "pcd_poses_kitti.txt"),
        io.read_kitti_poses(tmp_path / "bin_run" / "00_poses_kitti.txt"),
        # Float32 rounding of the times through another file format, which can move the
        # solver's stop (updates below gicp.translation_eps, 1 mm) by an iteration.
        atol=1e-3,
    )
    assert result["ate"]["rmse"] == pytest.approx(reference["ate"]["rmse"], abs=1e-3)


def test_a_bad_scan_is_found_before_the_first_frame(sim_sequence, tmp_path):
    folder = tmp_path / "scans"
    shutil.copytree(sim_sequence / "sequences" / "00" / "velodyne", folder)
    bad = folder / "000003.bin"
    bad.write_bytes(bad.read_bytes()[:-4])
    calls = []
    with pytest.raises(InputError, match=r"000003\.bin: file size .* not a multiple of 16"):
        run_dataset(open_dataset(folder), OdometryConfig(), tmp_path / "run", select_frames(6),
                    progress=lambda k, ms: calls.append(k))  # fmt: skip
    assert calls == []  # nothing was computed
    # A selection that leaves the bad scan out runs.
    result = run_dataset(open_dataset(folder), OdometryConfig(), tmp_path / "run2",
                         select_frames(len(list(folder.iterdir())), 4, 3))  # fmt: skip
    assert result["frames"] == {"start": 4, "stride": 1, "count": 3}


def test_start_and_stride_score_against_the_matching_ground_truth(sim_sequence, tmp_path):
    out = tmp_path / "results"
    args = ["--start", "10", "--frames", "6", "--stride", "2", "--no-compilation-cache"]
    result = runner.invoke(app, ["run", str(sim_sequence), *args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    run = out / "latest"
    gt = io.read_kitti_poses(run / "00_gt_kitti.txt")
    full = io.KittiSequence(sim_sequence, "00").gt_poses_cam
    np.testing.assert_allclose(gt, np.linalg.inv(full[10]) @ full[10:22:2], atol=1e-9)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["frames"] == {"start": 10, "stride": 2, "count": 6}
    assert metrics["ate"]["rmse"] < 0.2
    times, _ = io.read_tum_poses(run / "00_poses_tum.txt")
    np.testing.assert_allclose(np.diff(times), 0.2, atol=1e-6)


def test_a_run_says_how_map_resolution_auto_was_resolved(tmp_path):
    config = tmp_path / "auto.yaml"
    config.write_text("base: gicp\nmap_resolution: auto\n")
    out = tmp_path / "results"
    result = runner.invoke(app, ["run", str(shared_path("real_kitti16")), "--frames", "3",
                                 "--config", str(config), "--out", str(out),
                                 "--no-compilation-cache"])  # fmt: skip
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())  # the console wraps long lines
    assert "local map: auto: 6" in said and "rings measured (at least 40)" in said
    assert "one keyframe's points per 0.5 m voxel" in said
    written = json.loads((out / "latest" / "metrics.json").read_text())["map"]
    assert written["setting"] == "auto" and written["resolution"] == 0.5


def test_real_kitti_scans_run_out_of_the_box_and_agree_with_small_gicp(tmp_path):
    data = shared_path("real_kitti16")
    out = tmp_path / "results"
    result = runner.invoke(app, ["run", str(data), "--frames", "6", "--out", str(out),
                                 "--no-compilation-cache"])  # fmt: skip
    assert result.exit_code == 0, result.output
    for note in ("no calib.txt", "no times.txt", "no poses.txt", "deskew: auto -> off"):
        assert result.output.count(note) == 1, note  # each default said once
    run = out / "latest"
    assert (run / "trajectory.png").stat().st_size > 10_000
    assert not (run / "real_kitti16_gt_kitti.txt").exists()
    ours = io.read_kitti_poses(run / "real_kitti16_poses_lidar_kitti.txt")
    dataset = open_dataset(data)
    compare_real = import_script("compare_real")
    theirs = compare_real.small_gicp_odometry([dataset.frame(i)[0] for i in range(6)])
    step_theirs = np.linalg.inv(theirs[:-1]) @ theirs[1:]
    motion = np.linalg.norm(step_theirs[:, :3, 3], axis=1)
    assert np.all((motion > 0.5) & (motion < 1.0))  # the data's ~0.7-0.9 m per frame
    agreement = compare_real.step_differences(ours, theirs)
    assert agreement["trans_cm_mean"] < 3  # measured on all 16 frames: 0.58 cm (docs/real_data.md)
    assert agreement["path_m"] == pytest.approx(motion.sum(), rel=0.02)
