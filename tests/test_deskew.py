"""Deskew policy and per-point time conventions: the same drive gives the same poses whatever
the convention of its times; undistorted scans in a plain folder are not deskewed; settings
that would silently change the result are errors."""

import json
import shutil

import numpy as np
import pytest

from gloam_jax import io
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset
from gloam_jax.errors import InputError
from gloam_jax.odometry import OdometryConfig
from gloam_jax.pipeline import run_dataset, run_sequence, select_frames
from gloam_jax.preprocess import (
    PreprocessConfig,
    centre_rows,
    detect_time_convention,
    normalise_times,
    resolve_deskew,
    voxel_centres,
)
from gloam_jax.simulate import ErrorSwitches, simulate

# One worker runs this module (pytest-xdist --dist loadgroup): its module fixture is built once.
pytestmark = pytest.mark.xdist_group("deskew")


MID = np.linspace(-0.05, 0.05, 2001)  # seconds from mid-sweep, one 0.1 s sweep

# The conventions drivers write, each as a function of seconds from mid-sweep.
CONVENTIONS = {
    "s from mid-sweep": lambda t: t,
    "s from start": lambda t: t + 0.05,
    "s before end": lambda t: t - 0.05,
    "fraction [0, 1]": lambda t: (t + 0.05) / 0.1,
    "absolute s": lambda t: 1.7e9 + t.astype(np.float64),
    "ns from start": lambda t: np.round((t.astype(np.float64) + 0.05) * 1e9).astype(np.int64),
    "absolute ns": lambda t: (
        1_700_000_000_000_000_000 + np.round((t.astype(np.float64) + 0.05) * 1e9).astype(np.int64)
    ),
}


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_each_convention_is_detected_and_normalised_onto_the_sweep(convention):
    times = CONVENTIONS[convention](MID)
    assert detect_time_convention(times, 0.1) == convention
    normalised, found = normalise_times(times, 0.1)
    assert found == convention
    np.testing.assert_allclose(normalised, MID, atol=1e-6)  # absolute s: float64 resolution


def test_a_span_that_fits_no_convention_is_an_error():
    with pytest.raises(InputError, match=r"scan.bin: per-point times span 10 .* no convention"):
        normalise_times(np.linspace(0, 10, 100), 0.1, "scan.bin")
    with pytest.raises(InputError, match="NaN"):
        normalise_times(np.array([0.0, np.nan, 0.1]), 0.1, "scan.bin")


def test_the_policy_follows_the_data():
    assert resolve_deskew("auto", True, False)[0] == "timestamps"
    used, why = resolve_deskew("auto", False, True)  # KITTI layout: distorted
    assert used == "azimuth" and "deskew: off" in why  # says how to turn it off
    used, why = resolve_deskew("auto", False, False)
    assert used == "off" and "azimuth" in why  # says how to turn it on
    assert resolve_deskew("azimuth", True, False)[0] == "azimuth"
    with pytest.raises(InputError, match="'timestamps' but the scans have no per-point times"):
        resolve_deskew("timestamps", False, True)


def _with_times(root, tmp_path, name, convert):
    """A copy of the simulated sequence whose per-point times are rewritten by ``convert``."""
    copy = tmp_path / name
    seq_dir = copy / "sequences" / "00"
    seq_dir.mkdir(parents=True)
    (copy / "poses").symlink_to(root / "poses")
    for item in ("velodyne", "calib.txt", "times.txt"):
        (seq_dir / item).symlink_to(root / "sequences" / "00" / item)
    (seq_dir / "timestamps").mkdir()
    for path in sorted((root / "sequences" / "00" / "timestamps").glob("*.npy")):
        np.save(seq_dir / "timestamps" / path.name, convert(np.load(path)))
    return copy


def test_the_same_drive_gives_the_same_poses_in_every_convention(sim_sequence, tmp_path):
    poses = {}
    for k, (convention, convert) in enumerate(CONVENTIONS.items()):
        root = _with_times(sim_sequence, tmp_path, f"c{k}", convert)
        result = run_sequence(root, "00", OdometryConfig(), tmp_path / f"run{k}", frames=8)
        assert result["deskew"]["used"] == "timestamps"
        assert result["deskew"]["time_convention"] == convention
        poses[convention] = io.read_kitti_poses(tmp_path / f"run{k}" / "00_poses_kitti.txt")
    reference = poses["s from mid-sweep"]
    for convention, estimate in poses.items():
        np.testing.assert_allclose(estimate, reference, atol=2e-4, err_msg=convention)


def test_deskew_undoes_a_known_distortion_whatever_the_convention():
    """A sensor moving 1 m and turning 2 deg per 0.1 s sweep sees points on a 20 m circle, each
    at its own time; deskewing with that velocity must put them back where they are at
    mid-sweep, from the times in any convention (or from the azimuth, nearly)."""
    from gloam_jax import geometry as geo
    from gloam_jax.preprocess import preprocess_scan

    n = 4001
    azimuth = np.linspace(np.pi, -np.pi, n)  # clockwise from behind, as KITTI's HDL-64E
    mid = -azimuth / (2 * np.pi) * 0.1  # s from mid-sweep, -0.05 .. 0.05
    world = np.c_[20 * np.cos(azimuth), 20 * np.sin(azimuth), np.linspace(-1, 1, n)]
    xi = np.array([1.0, 0.0, 0.0, 0.0, 0.0, np.deg2rad(2.0)])  # per frame (0.1 s)
    T = np.asarray(geo.se3_exp(mid[:, None] / 0.1 * xi[None, :]), np.float64)
    seen = np.einsum("nji,nj->ni", T[:, :3, :3], world - T[:, :3, 3])  # inv(T(t)) @ p
    scan = np.c_[seen, np.zeros(n)].astype(np.float32)

    def error(policy, times):
        config = PreprocessConfig(deskew=policy, downsampling_resolution=0.0, min_range=0.0)
        points = preprocess_scan(scan, times, config, velocity=xi, frame_dt=0.1)[0]
        # The voxel grid is off, so the rows stay in order.
        return np.linalg.norm(points - world, axis=1)

    assert error("off", None).max() > 0.4  # half a metre at the seam
    # The azimuth seen is near the true one, except at the seam behind, where a point may
    # land on the other side (the first instead of the last moment of the sweep).
    inner = np.abs(mid) < 0.045
    assert error("azimuth", None)[inner].max() < 0.02
    for convention, convert in CONVENTIONS.items():
        assert error("timestamps", convert(mid)).max() < 2e-3, convention  # float32 scan


@pytest.fixture(scope="module")
def undistorted(tmp_path_factory):
    root = tmp_path_factory.mktemp("undistorted")
    simulate(root, frames=6, num_beams=16, num_columns=600, seed=2,
             switches=ErrorSwitches(motion_distortion=False))  # fmt: skip
    return root


def test_undistorted_scans_in_a_folder_are_not_deskewed(undistorted, tmp_path):
    folder = tmp_path / "scans"
    shutil.copytree(undistorted / "sequences" / "00" / "velodyne", folder)
    dataset = open_dataset(folder)
    assert dataset.kind == "folder" and not dataset.has_point_times
    frames = select_frames(len(dataset))
    auto = run_dataset(dataset, OdometryConfig(), tmp_path / "auto", frames)
    assert auto["deskew"]["used"] == "off" and "no per-point times" in auto["deskew"]["reason"]
    off = OdometryConfig(preprocess=PreprocessConfig(deskew="off"))
    azimuth = OdometryConfig(preprocess=PreprocessConfig(deskew="azimuth"))
    run_dataset(dataset, off, tmp_path / "off", frames)
    run_dataset(dataset, azimuth, tmp_path / "azimuth", frames)
    name = dataset.name
    read = {k: io.read_kitti_poses(tmp_path / k / f"{name}_poses_kitti.txt") for k in
            ("auto", "off", "azimuth")}  # fmt: skip
    np.testing.assert_allclose(read["auto"], read["off"], atol=1e-9)
    assert np.abs(read["azimuth"] - read["off"]).max() > 1e-4  # deskewing would change them
    # The same scans in the KITTI layout without timestamps: known distorted, so azimuth.
    kitti = tmp_path / "kitti"
    shutil.copytree(undistorted, kitti)
    shutil.rmtree(kitti / "sequences" / "00" / "timestamps")
    result = run_sequence(kitti, "00", OdometryConfig(), tmp_path / "kitti_run", frames=3)
    assert result["deskew"]["used"] == "azimuth"
    saved = json.loads((tmp_path / "kitti_run" / "metrics.json").read_text())
    assert saved["deskew"] == result["deskew"]


def test_times_that_are_all_equal_are_one_instant_and_deskew_nothing(undistorted, tmp_path):
    """Per-point times with no span (a simulator without motion distortion writes zeros; a
    driver may write one stamp for a deskewed scan) mean the sweep is one instant: auto keeps
    the times, says so, and the poses are those of deskew off, not an error."""
    for stamps in (np.zeros(7), np.full(7, 1_700_000_000_000_000_000, dtype=np.int64)):
        assert detect_time_convention(stamps, 0.1) == "one instant"
        normalised, found = normalise_times(stamps, 0.1)
        assert found == "one instant" and np.array_equal(normalised, np.zeros(7))
    times = np.load(sorted((undistorted / "sequences" / "00" / "timestamps").glob("*.npy"))[0])
    assert times.size and np.ptp(times) == 0  # the simulator's undistorted scans
    auto = run_sequence(undistorted, "00", OdometryConfig(), tmp_path / "auto", frames=4)
    assert auto["deskew"]["used"] == "timestamps"
    assert auto["deskew"]["time_convention"] == "one instant"
    assert "deskew: azimuth" in auto["deskew"]["reason"]  # how to deskew raw sweeps instead
    off = OdometryConfig(preprocess=PreprocessConfig(deskew="off"))
    run_sequence(undistorted, "00", off, tmp_path / "off", frames=4)
    read = [io.read_kitti_poses(tmp_path / k / "00_poses_kitti.txt") for k in ("auto", "off")]
    np.testing.assert_allclose(read[0], read[1], atol=1e-9)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"min_range": 50.0, "max_range": 5.0}, r"min_range \(50.0\) must be below .*max_range"),
        ({"downsampling_resolution": -0.5}, "downsampling_resolution must be a voxel size"),
        ({"num_neighbors": 2}, "num_neighbors must be an integer >= 3"),
        ({"num_neighbors": 10.5}, "num_neighbors must be an integer >= 3"),
        ({"sweep_duration": 0.0}, "sweep_duration must be positive"),
        ({"max_range": -1.0}, "max_range must be positive"),
        ({"min_range": float("nan")}, "min_range must be a number >= 0"),
        ({"deskew": "sometimes"}, "deskew must be one of"),
    ],
)
def test_preprocess_settings_check_themselves(values, message):
    with pytest.raises(InputError, match=message):
        PreprocessConfig(**values)


def test_zero_downsampling_is_off_and_old_boolean_deskew_still_loads(tmp_path):
    assert PreprocessConfig(downsampling_resolution=0.0).downsampling_resolution == 0.0
    path = tmp_path / "old.yaml"
    path.write_text("preprocess:\n  deskew: true\n")
    assert load_config(path).preprocess.deskew == "auto"
    path.write_text("preprocess:\n  deskew: false\n")
    assert load_config(path).preprocess.deskew == "off"
    path.write_text("preprocess:\n  min_range: 50\n  max_range: 5\n")
    with pytest.raises(InputError, match="min_range"):
        load_config(path)


@pytest.mark.parametrize("resolution", [0.5, 0.0])
def test_centre_rows_average_raw_points_onto_the_voxel_centres(resolution):
    """The map from raw points to the centres that fine-tuning averages its features with."""
    rng = np.random.default_rng(3)
    scan = np.c_[rng.uniform(-40, 40, (5000, 3)), rng.uniform(0, 1, 5000)]
    scan[:20, :3] = 0.5  # inside min_range: dropped
    scan[20:25, 0] = np.nan  # invalid: dropped
    config = PreprocessConfig(downsampling_resolution=resolution, deskew="off")
    rows = centre_rows(scan, config)
    centres = voxel_centres(scan, None, config).points
    assert np.all(rows[:25] == -1) and rows.max() == len(centres) - 1
    kept = rows >= 0
    counts = np.bincount(rows[kept])
    means = np.stack([np.bincount(rows[kept], scan[kept, i]) / counts for i in range(3)], axis=1)
    np.testing.assert_allclose(means, centres, atol=1e-9)
