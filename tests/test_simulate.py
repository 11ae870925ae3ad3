"""The LiDAR simulator: geometry of the returns, error sources, determinism, KITTI output."""

import json
import sys
from dataclasses import replace

import numpy as np
import pytest
from repo_scripts import import_script
from shared_data import shared_path

from gloam_jax import io
from gloam_jax.errors import InputError
from gloam_jax.simulate import (
    ErrorSwitches,
    SweepSimulator,
    Trajectory,
    get_sensor,
    simulate,
)
from gloam_jax.simulate.preview import deskewed_points
from gloam_jax.simulate.trajectory import default_Tr_cam_velo
from gloam_jax.simulate.world import BUILDING, ROAD, TERRAIN, Ground, PrimitiveList, Scene

# One thinned sensor for every test: small and compiled only a few times.
SENSOR = get_sensor("hdl64", num_beams=16, num_columns=400)
NO_ERRORS = ErrorSwitches(False, False, False, False)


def straight_trajectory(speed: float = 10.0, frames: int = 5) -> Trajectory:
    """Driving along +x at ``speed`` m/s, LiDAR 1.73 m above a flat road at z = 0."""
    times = 0.1 * np.arange(-40, frames + 40)
    T = np.tile(np.eye(4), (len(times), 1, 1))
    T[:, 0, 3] = speed * times
    T[:, 2, 3] = 1.73
    return Trajectory(times, T, 40, frames, default_Tr_cam_velo(), "straight")


def flat_scene(boxes=()) -> Scene:
    ground = Ground(
        origin=np.array([-200.0, -200.0]),
        base_height=np.zeros((801, 801), np.float32),
        path_distance=np.full((801, 801), 50.0, np.float32),
        road_half_width=0.0,
        sidewalk_width=0.0,
        curb_height=0.0,
    )
    prims = PrimitiveList()
    for centre, half in boxes:
        prims.add(centre, half, 0.0, BUILDING)
    empty = PrimitiveList()
    return Scene("test", ground, prims.build(0), empty.build(len(boxes)), empty.build(len(boxes)))


def world_points(scan, T_world_lidar):
    return scan.points[:, :3] @ T_world_lidar[:3, :3].T + T_world_lidar[:3, 3]


def test_flat_ground_and_wall_are_exact_without_errors():
    traj = straight_trajectory(speed=0.0)
    wall = ([20.0, 0.0, 5.0], [0.5, 30.0, 5.0])  # front face at x = 19.5
    sim = SweepSimulator(flat_scene([wall]), traj, SENSOR, seed=0, switches=NO_ERRORS)
    scan = sim.frame(0)
    p = world_points(scan, traj.frame_poses[0])
    ground, walls = scan.labels == TERRAIN, scan.labels == BUILDING
    assert ground.sum() > 1000 and walls.sum() > 300
    np.testing.assert_allclose(p[ground, 2], 0.0, atol=2e-3)
    np.testing.assert_allclose(p[walls, 0], 19.5, atol=2e-3)
    # Nothing is seen through the wall (its shadow cone), nor beyond the sensor's range.
    behind = p[:, 0] > 19.51
    assert behind.any()
    assert np.all(np.abs(p[behind, 1]) / p[behind, 0] > 29.9 / 20.5)
    assert np.linalg.norm(scan.points[:, :3], axis=1).max() <= SENSOR.max_range


def test_motion_distortion_is_undone_by_the_timestamps():
    traj = straight_trajectory(speed=15.0)
    wall = ([20.0, 0.0, 5.0], [0.5, 30.0, 5.0])
    switches = ErrorSwitches(True, False, False, False)
    sim = SweepSimulator(flat_scene([wall]), traj, SENSOR, seed=0, switches=switches)
    scan = sim.frame(0)
    walls = scan.labels == BUILDING
    assert np.all(np.abs(scan.times) <= SENSOR.sweep_s / 2)
    # Raw: every column sees the wall from where the sensor was at its own firing time.
    raw = world_points(scan, traj.frame_poses[0])[walls, 0]
    assert raw.max() - raw.min() > 0.3
    # Moving each point by the pose at its timestamp puts the wall back in place.
    T_col = traj.poses_at(traj.frame_times[0] + scan.times[walls])
    fixed = np.einsum("nij,nj->ni", T_col[:, :3, :3], scan.points[walls, :3]) + T_col[:, :3, 3]
    np.testing.assert_allclose(fixed[:, 0], 19.5, atol=2e-3)


def test_elevation_bias_bends_the_ground_down():
    traj = straight_trajectory(speed=0.0)
    switches = ErrorSwitches(False, False, False, True)
    biased = replace(SENSOR.without_errors(), elevation_bias_deg=0.22)
    scan = SweepSimulator(flat_scene(), traj, biased, seed=0, switches=switches).frame(0)
    p = world_points(scan, traj.frame_poses[0])
    r = np.linalg.norm(scan.points[:, :3], axis=1)
    # Rays leave 0.22 deg higher than reported: the reported ground sinks by ~r*sin(0.22 deg).
    expected = -r * np.sin(np.deg2rad(0.22))
    assert np.all(np.abs(p[:, 2] - expected) < 0.005 + 0.001 * r)
    assert np.mean(p[r > 20, 2]) < -0.05


def test_sensor_noise_has_the_configured_size():
    traj = straight_trajectory(speed=0.0)
    switches = ErrorSwitches(False, False, False, True)
    noisy = replace(
        SENSOR.without_errors(), range_noise=0.02, range_noise_per_m=0.0, beam_range_offset_std=0
    )
    wall = ([10.0, 0.0, 5.0], [0.5, 30.0, 5.0])
    scan = SweepSimulator(flat_scene([wall]), traj, noisy, seed=0, switches=switches).frame(0)
    p = world_points(scan, traj.frame_poses[0])
    front = (scan.labels == BUILDING) & (np.abs(p[:, 1]) < 3)  # near-normal incidence
    resid = (p[front, 0] - 9.5) * np.linalg.norm(scan.points[front, :3], axis=1) / 9.5
    assert 0.015 < np.std(resid) < 0.03


def test_simulation_is_deterministic_per_seed(tmp_path):
    kw = dict(frames=2, num_beams=16, num_columns=400, trajectory=None, style="suburban")
    a = simulate(tmp_path / "a", seed=3, **kw)
    b = simulate(tmp_path / "b", seed=3, **kw)
    c = simulate(tmp_path / "c", seed=4, **kw)
    for name in ("velodyne/000001.bin", "labels/000001.label", "timestamps/000001.npy"):
        assert (a / name).read_bytes() == (b / name).read_bytes()
    assert (a / "velodyne/000001.bin").read_bytes() != (c / "velodyne/000001.bin").read_bytes()


def test_kitti_window_reads_back_with_lidar_frame_ground_truth(tmp_path):
    KITTI_00 = shared_path("kitti_gt_poses/00.txt")
    seq_dir = simulate(
        tmp_path, trajectory=KITTI_00, start=50, frames=3, num_beams=16, num_columns=400, seed=1
    )
    seq = io.KittiSequence(tmp_path, "00")
    assert len(seq) == 3
    P = io.read_kitti_poses(KITTI_00)[50:53]
    calib = io.read_calib(KITTI_00.with_name("calib_Tr_velo_to_cam0.txt"))
    Tr = calib["Tr_00_02"]
    T_lidar = np.linalg.inv(Tr) @ P @ Tr
    expected = np.linalg.inv(T_lidar[0]) @ T_lidar  # re-based: first pose identity
    np.testing.assert_allclose(seq.gt_poses_lidar, expected, atol=1e-9)
    np.testing.assert_allclose(seq.gt_poses_cam[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(seq.Tr_cam_velo, Tr, atol=1e-12)
    times = io.read_times(KITTI_00.with_name("00_times.txt"))[50:53]
    np.testing.assert_allclose(seq.times, times - times[0], atol=1e-6)
    scan, labels, dt = seq.scan(1), seq.labels(1), seq.point_times(1)
    assert scan.shape[1] == 4 and len(labels) == len(scan) == len(dt)
    assert np.all(np.isfinite(scan)) and 0 <= scan[:, 3].min() and scan[:, 3].max() <= 1
    assert ROAD in set(np.unique(labels).tolist())
    assert (seq_dir / "simulation.json").exists()


def test_resume_regenerates_missing_frames_identically(tmp_path):
    kw = dict(frames=3, num_beams=16, num_columns=400, seed=2)
    seq_dir = simulate(tmp_path, **kw)
    original = (seq_dir / "velodyne/000001.bin").read_bytes()
    (seq_dir / "velodyne/000001.bin").unlink()
    simulate(tmp_path, **kw)
    assert (seq_dir / "velodyne/000001.bin").read_bytes() == original
    with pytest.raises(InputError, match="different simulation"):
        simulate(tmp_path, **{**kw, "seed": 5})


def test_urban_scene_has_the_expected_classes_and_previews(tmp_path):
    simulate(tmp_path, frames=4, num_beams=16, num_columns=400, seed=0, style="urban")
    seq = io.KittiSequence(tmp_path, "00")
    classes = set(np.concatenate([seq.labels(i) for i in range(4)]).tolist())
    assert {40, 48, 50, 70}.issubset(classes)  # road, sidewalk, building, vegetation
    from gloam_jax.simulate.preview import render_previews

    for png in render_previews(seq, tmp_path / "preview"):
        assert png.stat().st_size > 10_000
    # The preview map is built from deskewed points: check that helper against the raw path.
    world = deskewed_points(seq, 1, seq.gt_poses_lidar)
    assert world.shape == (len(seq.scan(1)), 3)


def test_sensor_presets():
    hdl = get_sensor("hdl64")
    assert hdl.num_beams == 64 and hdl.num_columns == 2000
    assert max(hdl.elevations_deg) == pytest.approx(2.0)
    assert min(hdl.elevations_deg) == pytest.approx(-24.8)
    assert hdl.mount_height == pytest.approx(1.73) and hdl.max_range == 120
    assert get_sensor("vlp16").num_beams == 16
    assert get_sensor("os1-64").num_beams == 64
    # Mid-sweep faces forward: the middle column's azimuth is ~0, times span one sweep.
    az = hdl.column_azimuths()
    assert abs(az[hdl.num_columns // 2]) < 2 * np.pi / hdl.num_columns
    assert hdl.column_times()[0] == pytest.approx(-0.05, abs=1e-4)
    with pytest.raises(InputError, match="unknown sensor"):
        get_sensor("hdl32e")


def test_simulate_refuses_what_it_did_not_make_and_bad_sensor_settings(tmp_path):
    from gloam_jax.errors import InputError

    kw = dict(frames=2, num_beams=8, num_columns=200, seed=3)
    seq_dir = simulate(tmp_path / "sim", **kw)
    # A user's dataset: the same layout without the simulator's record is never overwritten.
    (seq_dir / "simulation.json").unlink()
    before = (tmp_path / "sim" / "poses" / "00.txt").read_bytes()
    with pytest.raises(InputError, match="00.txt: holds data not made by the simulator"):
        simulate(tmp_path / "sim", **kw)
    assert (tmp_path / "sim" / "poses" / "00.txt").read_bytes() == before
    for bad, message in (
        (dict(num_beams=0), "num_beams must be an integer from 1 to 64"),
        (dict(num_beams=-3), "num_beams must be an integer from 1 to 64"),
        (dict(num_columns=0), "num_columns must be an integer >= 8"),
        (dict(style="rural"), "unknown scene style 'rural'"),
    ):
        with pytest.raises(InputError, match=message):
            simulate(tmp_path / "fresh", **(kw | bad))
    # A refused style leaves nothing behind that would lock the folder for a valid run.
    assert not (tmp_path / "fresh" / "sequences" / "00" / "simulation.json").exists()
    assert simulate(tmp_path / "fresh", **kw).is_dir()


def test_nearest_pair_per_sector_breaks_ties_like_argmin():
    from gloam_jax.simulate.raycast import _nearest

    rng = np.random.default_rng(0)
    sector = np.array([0, 0, 0, 2, 2, 3, 3, 3], np.int32)  # sector 1 has no pairs
    t = rng.choice([1.0, 2.0, np.inf], size=(8, 50)).astype(np.float32)  # many ties
    t_min, k = (np.asarray(a) for a in _nearest(t, sector, 4))
    for s in range(4):
        rows = np.flatnonzero(sector == s)
        if len(rows) == 0:
            assert np.all(np.isinf(t_min[s]))
            continue
        np.testing.assert_array_equal(t_min[s], t[rows].min(axis=0))
        hit = np.isfinite(t_min[s])
        np.testing.assert_array_equal(k[s][hit], rows[np.argmin(t[rows], axis=0)][hit])


def test_protocol_windows_take_another_sensor(tmp_path, monkeypatch):
    script = import_script("simulate_protocol")
    argv = ["simulate_protocol.py", "--out", str(tmp_path), "--sensor", "vlp16",
            "--sequences", "01", "--frames", "2", "--seed", "1000"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    script.main()
    config = json.loads((tmp_path / "sequences/01/simulation.json").read_text())["config"]
    assert (config["sensor"], config["num_beams"], config["seed"]) == ("vlp16", 16, 1001)
    x, y, z = io.KittiSequence(tmp_path, "01").scan(1)[:, :3].T
    elevation = np.degrees(np.arctan2(z, np.hypot(x, y)))
    assert -16.0 < elevation.min() and elevation.max() < 16.0  # the VLP-16's +-15 deg fan
    monkeypatch.setattr(sys, "argv", argv + ["--split", "val_long"])
    with pytest.raises(SystemExit):  # a split's worlds draw their own sensor
        script.main()
