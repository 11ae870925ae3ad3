"""Tests for gloam_jax.io: pose/calib/scan/label files and the KITTI odometry layout."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shared_data import shared_path

from gloam_jax import io as gio
from gloam_jax.errors import InputError
from gloam_jax.io.scans import check_scan, read_scan_with_times, write_scan_pcd


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=100.0, size=(n, 3))
    poses[:, 3, 3] = 1.0
    return poses


def random_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(scale=20.0, size=(n, 4)).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Poses


def test_kitti_round_trip_creates_parents(tmp_path):
    poses = random_poses(50)
    path = tmp_path / "a" / "b" / "poses.txt"
    gio.write_kitti_poses(path, poses)
    lines = path.read_text().splitlines()
    assert len(lines) == 50 and all(len(line.split()) == 12 for line in lines)
    back = gio.read_kitti_poses(path)
    assert back.dtype == np.float64 and back.shape == (50, 4, 4)
    assert np.max(np.abs(back - poses)) < 1e-9


def test_kitti_reads_open_text_file():
    text = "1 0 0 1 0 1 0 2 0 0 1 3\n\n1 0 0 4 0 1 0 5 0 0 1 6\n"
    poses = gio.read_kitti_poses(io.StringIO(text))
    assert poses.shape == (2, 4, 4)
    np.testing.assert_array_equal(poses[1, :3, 3], [4, 5, 6])
    np.testing.assert_array_equal(poses[:, 3], [[0, 0, 0, 1]] * 2)


def test_tum_round_trip(tmp_path):
    poses = random_poses(40, seed=1)
    times = 1.3e9 + np.cumsum(np.full(40, 0.1))
    path = tmp_path / "traj.tum"
    gio.write_tum_poses(path, times, poses)
    t, back = gio.read_tum_poses(path)
    assert np.max(np.abs(t - times)) < 1e-6
    assert np.max(np.abs(back - poses)) < 1e-6


def test_tum_skips_comments_and_normalises_quaternions():
    text = "# t x y z qx qy qz qw\n0.5 1 2 3 0 0 0 2\n"
    times, poses = gio.read_tum_poses(io.StringIO(text))
    np.testing.assert_array_equal(times, [0.5])
    np.testing.assert_allclose(poses[0], [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])


def test_writer_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "poses.txt"
    gio.write_kitti_poses(path, random_poses(3))
    before = path.read_bytes()

    def fail(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(InputError, match="poses.txt: cannot write"):
        gio.write_kitti_poses(path, random_poses(5, seed=3))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.txt"]


def test_evo_reads_our_files(tmp_path):
    from evo.tools import file_interface

    poses = random_poses(20, seed=2)
    times = np.arange(20) * 0.1
    gio.write_kitti_poses(tmp_path / "k.txt", poses)
    gio.write_tum_poses(tmp_path / "t.txt", times, poses)
    kitti = file_interface.read_kitti_poses_file(str(tmp_path / "k.txt"))
    tum = file_interface.read_tum_trajectory_file(str(tmp_path / "t.txt"))
    assert np.max(np.abs(np.array(kitti.poses_se3) - poses)) < 1e-9
    assert np.max(np.abs(np.array(tum.poses_se3) - poses)) < 1e-6
    assert np.max(np.abs(tum.timestamps - times)) < 1e-9


def test_shared_kitti_gt_poses():
    poses = gio.read_kitti_poses(shared_path("kitti_gt_poses/00.txt"))
    assert poses.shape == (4541, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)
    times = gio.read_times(shared_path("kitti_gt_poses/00_times.txt"))
    assert times.shape == (4541,) and times[0] == 0.0


def test_cam_lidar_conversions(tmp_path):
    P = random_poses(10, seed=4)
    Tr = random_poses(1, seed=5)[0]
    T = gio.cam_to_lidar_poses(P, Tr)
    np.testing.assert_allclose(T[3], np.linalg.inv(Tr) @ P[3] @ Tr, atol=1e-9)
    np.testing.assert_allclose(gio.lidar_to_cam_poses(T, Tr), P, atol=1e-9)


# --------------------------------------------------------------------------------------------
# Calibration and times


def test_calib_round_trip(tmp_path):
    P0 = np.arange(12, dtype=float).reshape(3, 4)
    Tr = random_poses(1, seed=6)[0]
    path = tmp_path / "calib.txt"
    gio.write_calib(path, {"P0": P0, "Tr": Tr})
    assert len(path.read_text().splitlines()[1].split()) == 13  # "Tr:" + 12 numbers, as KITTI
    calib = gio.read_calib(path)
    assert calib["P0"].shape == (3, 4) and calib["Tr"].shape == (4, 4)
    np.testing.assert_allclose(calib["P0"], P0)
    np.testing.assert_allclose(calib["Tr"], Tr, atol=1e-11)


def test_shared_calib_file():
    calib = gio.read_calib(shared_path("kitti_gt_poses/calib_Tr_velo_to_cam0.txt"))
    Tr = calib["Tr_00_02"]
    assert Tr.shape == (4, 4)
    np.testing.assert_array_equal(Tr[3], [0, 0, 0, 1])
    np.testing.assert_allclose(Tr[:3, :3] @ Tr[:3, :3].T, np.eye(3), atol=1e-6)


def test_read_times(tmp_path):
    path = tmp_path / "times.txt"
    path.write_text("0.0\n1.036e-01\n0.2\n")
    np.testing.assert_allclose(gio.read_times(path), [0.0, 0.1036, 0.2])


# --------------------------------------------------------------------------------------------
# Scans


def test_bin_round_trip_keeps_nan_points(tmp_path):
    points = random_points(100)
    points[7, :3] = np.nan
    path = tmp_path / "000000.bin"
    gio.write_scan_bin(path, points)
    assert path.stat().st_size == 100 * 16
    back = gio.read_scan(path)
    assert back.dtype == np.float32 and back.shape == (100, 4)
    np.testing.assert_array_equal(back, points)


def test_shared_pcd():
    points = gio.read_scan(shared_path("real_pair/251370668.pcd"))
    assert points.shape == (69088, 4) and points.dtype == np.float32
    assert np.all(np.isfinite(points))


def write_pcd_ascii(path: Path, fields: dict[str, np.ndarray], types: dict[str, str]) -> None:
    """PCD ascii file; a 2-D column is written as one field with COUNT = its width."""
    cols = [v.reshape(len(v), -1) for v in fields.values()]
    n = len(cols[0])
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(types[k][1:] for k in fields),
        "TYPE " + " ".join(types[k][0] for k in fields),
        "COUNT " + " ".join(str(c.shape[1]) for c in cols),
        f"WIDTH {n}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {n}",
        "DATA ascii",
    ]
    rows = [" ".join(f"{v:.9g}" for c in cols for v in c[i]) for i in range(n)]
    path.write_text("\n".join(header + rows) + "\n")


def test_pcd_ascii_any_field_order_and_types(tmp_path):
    points = random_points(30, seed=1)
    points[:, 3] = np.round(np.abs(points[:, 3]))
    ring = np.arange(30) % 16
    normals = np.ones((30, 3))
    path = tmp_path / "cloud.pcd"
    write_pcd_ascii(
        path,
        {"ring": ring, "intensity": points[:, 3], "z": points[:, 2], "normal": normals,
         "x": points[:, 0], "y": points[:, 1]},
        {"ring": "U2", "intensity": "U1", "z": "F4", "normal": "F8", "x": "F4", "y": "F4"},
    )  # fmt: skip
    np.testing.assert_allclose(gio.read_scan(path), points, rtol=1e-6)


def test_pcd_without_intensity_gets_zeros(tmp_path):
    points = random_points(5, seed=2)
    path = tmp_path / "xyz.pcd"
    write_pcd_ascii(
        path,
        {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]},
        {"x": "F4", "y": "F4", "z": "F4"},
    )
    back = gio.read_scan(path)
    np.testing.assert_allclose(back[:, :3], points[:, :3], rtol=1e-6)
    np.testing.assert_array_equal(back[:, 3], 0)


def test_pcd_binary_mixed_types(tmp_path):
    n = 20
    rng = np.random.default_rng(3)
    record = np.zeros(
        n, dtype=[("t", "<f8"), ("x", "<f4"), ("y", "<f4"), ("z", "<f8"), ("intensity", "<u2")]
    )
    for name in ("t", "x", "y", "z"):
        record[name] = rng.normal(size=n)
    record["intensity"] = rng.integers(0, 255, size=n)
    header = (
        "VERSION 0.7\nFIELDS t x y z intensity\nSIZE 8 4 4 8 2\nTYPE F F F F U\n"
        f"COUNT 1 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    path = tmp_path / "mixed.pcd"
    path.write_bytes(header.encode() + record.tobytes())
    back = gio.read_scan(path)
    for k, name in enumerate(("x", "y", "z", "intensity")):
        np.testing.assert_allclose(back[:, k], record[name], rtol=1e-6)


def write_ply(path: Path, points: np.ndarray, fmt: str) -> None:
    """PLY with a double-precision vertex element (x y z intensity) followed by a face element."""
    header = (
        f"ply\nformat {fmt} 1.0\ncomment written by test_io\nelement vertex {len(points)}\n"
        "property double x\nproperty double y\nproperty double z\nproperty float intensity\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    if fmt == "ascii":
        body = "".join(" ".join(f"{v:.9g}" for v in p) + "\n" for p in points) + "3 0 1 2\n"
        path.write_bytes(header + body.encode())
    else:
        record = np.zeros(
            len(points), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("i", "<f4")]
        )
        for k, name in enumerate(("x", "y", "z", "i")):
            record[name] = points[:, k]
        face = np.array([3], np.uint8).tobytes() + np.array([0, 1, 2], "<i4").tobytes()
        path.write_bytes(header + record.tobytes() + face)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_round_trip(tmp_path, fmt):
    points = random_points(25, seed=4)
    path = tmp_path / "cloud.ply"
    write_ply(path, points, fmt)
    back = gio.read_scan(path)
    assert back.dtype == np.float32 and back.shape == (25, 4)
    np.testing.assert_allclose(back, points, rtol=1e-6)


def test_ply_big_endian_with_faces_before_the_vertices_and_a_time_field(tmp_path):
    """plyfile reads what the hand parser refused: list properties before the vertices."""
    from plyfile import PlyData, PlyElement

    points = random_points(12, seed=6)
    vertex = np.zeros(12, [("z", ">f8"), ("x", ">f4"), ("y", ">f4"), ("time", ">f8"),
                           ("intensity", ">u2")])  # fmt: skip
    for k, name in enumerate("xyz"):
        vertex[name] = points[:, k]
    vertex["intensity"] = np.arange(12)
    vertex["time"] = np.linspace(0, 0.1, 12)
    face = np.array([([0, 1, 2],)], [("vertex_indices", "O")])
    elements = [PlyElement.describe(face, "face"), PlyElement.describe(vertex, "vertex")]
    path = tmp_path / "big.ply"
    PlyData(elements, byte_order=">").write(str(path))
    scan, times = read_scan_with_times(path)
    np.testing.assert_allclose(scan[:, :3], points[:, :3], rtol=1e-6)
    np.testing.assert_array_equal(scan[:, 3], np.arange(12))
    np.testing.assert_array_equal(times, vertex["time"])
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(InputError, match=r"big\.ply: not a readable PLY file \(.*end-of-file"):
        gio.read_scan(path)


def test_npy_scans(tmp_path):
    points = random_points(10, seed=5)
    np.save(tmp_path / "a.npy", points[:, :3].astype(np.float64))
    np.save(tmp_path / "b.npy", np.column_stack([points, np.ones(10)]))
    a = gio.read_scan(tmp_path / "a.npy")
    np.testing.assert_array_equal(a[:, :3], points[:, :3])
    np.testing.assert_array_equal(a[:, 3], 0)
    np.testing.assert_array_equal(gio.read_scan(tmp_path / "b.npy"), points)


def test_labels_round_trip(tmp_path):
    classes = np.array([0, 10, 40, 252, 65535], dtype=np.uint16)
    instances = np.array([0, 3, 0, 7, 65535])
    path = tmp_path / "000000.label"
    gio.write_labels(path, classes, instances)
    raw = np.fromfile(path, dtype="<u4")
    np.testing.assert_array_equal(raw >> 16, instances)
    back = gio.read_labels(path, expected_count=5)
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, classes)


# --------------------------------------------------------------------------------------------
# KITTI layout


def make_sequence(root: Path, seq: str = "03", n: int = 4, poses: bool = True) -> dict:
    """Tiny KITTI odometry layout under root; returns what was written."""
    seq_dir = root / "sequences" / seq
    scans = [random_points(10 + i, seed=i) for i in range(n)]
    for i, s in enumerate(scans):
        gio.write_scan_bin(seq_dir / "velodyne" / f"{i:06d}.bin", s)
    Tr = random_poses(1, seed=9)[0]
    gio.write_calib(seq_dir / "calib.txt", {"P0": np.eye(3, 4), "Tr": Tr})
    times = np.arange(n) * 0.1
    (seq_dir / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    P = random_poses(n, seed=10)
    if poses:
        gio.write_kitti_poses(root / "poses" / f"{seq}.txt", P)
    return {"scans": scans, "Tr": Tr, "times": times, "P": P, "dir": seq_dir}


def test_kitti_sequence(tmp_path):
    made = make_sequence(tmp_path)
    seq = gio.KittiSequence(tmp_path, 3)
    assert len(seq) == 4
    assert seq.scan_path(2).name == "000002.bin"
    np.testing.assert_array_equal(seq.scan(1), made["scans"][1])
    np.testing.assert_allclose(seq.times, made["times"])
    np.testing.assert_allclose(seq.Tr_cam_velo, made["Tr"], atol=1e-11)
    np.testing.assert_allclose(seq.gt_poses_cam, made["P"], atol=1e-9)
    Tr = seq.Tr_cam_velo
    expected = np.linalg.inv(Tr) @ seq.gt_poses_cam @ Tr
    np.testing.assert_allclose(seq.gt_poses_lidar, expected, atol=1e-12)
    assert seq.labels(0) is None and seq.point_times(0) is None
    with pytest.raises(ValueError):
        seq.times[0] = 5.0  # shared arrays are read-only

    gio.write_labels(made["dir"] / "labels" / "000001.label", np.arange(11))
    (made["dir"] / "timestamps").mkdir()
    np.save(made["dir"] / "timestamps" / "000001.npy", np.linspace(0, 0.1, 11, dtype=np.float32))
    np.testing.assert_array_equal(seq.labels(1), np.arange(11))
    point_times = seq.point_times(1)
    assert point_times.dtype == np.float32 and point_times.shape == (11,)


def test_kitti_sequence_string_id_and_no_poses(tmp_path):
    make_sequence(tmp_path, seq="07", poses=False)
    seq = gio.KittiSequence(str(tmp_path), "07")
    assert len(seq) == 4
    assert seq.gt_poses_cam is None and seq.gt_poses_lidar is None


# --------------------------------------------------------------------------------------------
# Bad input: InputError naming the file and the problem


def test_missing_pose_file(tmp_path):
    with pytest.raises(InputError, match=r"nope\.txt: file not found"):
        gio.read_kitti_poses(tmp_path / "nope.txt")


def test_pose_wrong_column_count(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"poses\.txt: line 2 has 11 columns, expected 12"):
        gio.read_kitti_poses(path)


def test_tum_wrong_column_count(tmp_path):
    path = tmp_path / "traj.tum"
    path.write_text("# header\n0 1 2 3 0 0 0 1 9\n")
    with pytest.raises(InputError, match=r"traj\.tum: line 2 has 9 columns, expected 8"):
        gio.read_tum_poses(path)


@pytest.mark.parametrize("bad", ["nan", "inf", "-Infinity"])
def test_pose_non_finite(tmp_path, bad):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2 + f"1 0 0 {bad} 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"poses\.txt: line 3 has a NaN or infinite value"):
        gio.read_kitti_poses(path)


def test_pose_non_numeric(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 x 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"poses\.txt: line 1 has a non-numeric value"):
        gio.read_kitti_poses(path)


def test_empty_pose_file(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("\n")
    with pytest.raises(InputError, match=r"poses\.txt: file is empty"):
        gio.read_kitti_poses(path)


def test_empty_scan(tmp_path):
    path = tmp_path / "000000.bin"
    path.write_bytes(b"")
    with pytest.raises(InputError, match=r"000000\.bin: empty scan"):
        gio.read_scan(path)


def test_bin_size_not_multiple_of_16(tmp_path):
    path = tmp_path / "000000.bin"
    path.write_bytes(np.zeros(5, np.float32).tobytes())
    with pytest.raises(InputError, match=r"000000\.bin: file size 20 bytes is not a multiple"):
        gio.read_scan(path)


def test_missing_scan(tmp_path):
    with pytest.raises(InputError, match=r"gone\.pcd: file not found"):
        gio.read_scan(tmp_path / "gone.pcd")


def test_unsupported_scan_extension(tmp_path):
    path = tmp_path / "cloud.las"
    path.write_bytes(b"LASF")
    with pytest.raises(InputError, match=r"cloud\.las: unsupported scan format"):
        gio.read_scan(path)


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_pcd_round_trip_with_times(tmp_path, data):
    rng = np.random.default_rng(4)
    points = rng.normal(size=(300, 4)).astype(np.float32)
    points[100:200] = points[100]  # repeats: LZF back references
    times = np.linspace(0.0, 0.1, 300)
    path = tmp_path / f"{data}.pcd"
    write_scan_pcd(path, points, data, times=times)
    check_scan(path)
    read, read_times = read_scan_with_times(path)
    np.testing.assert_array_equal(read, points)
    np.testing.assert_allclose(read_times, times, rtol=1e-12)


def test_pcd_binary_compressed_from_a_known_lzf_stream(tmp_path):
    """A hand-made LZF stream, as PCL's liblzf writes one: a literal 'a', then an 11-byte copy
    from 1 back (long form: length 7 + extra byte 2, + 2): x, y, z of one point, all 'aaaa'."""
    header = (
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
        b"POINTS 1\nDATA binary_compressed\n"
    )
    stream = b"\x00a\xe0\x02\x00"
    path = tmp_path / "known.pcd"
    path.write_bytes(header + np.array([len(stream), 12], "<u4").tobytes() + stream)
    check_scan(path)
    expected = np.frombuffer(b"a" * 12, "<f4")
    np.testing.assert_array_equal(gio.read_scan(path), [[*expected, 0.0]])


def test_pcd_binary_compressed_corrupt(tmp_path):
    header = (
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
        b"POINTS 1\nDATA binary_compressed\n"
    )
    path = tmp_path / "packed.pcd"
    path.write_bytes(header + b"\x00\x00\x00\x00")
    with pytest.raises(InputError, match=r"packed\.pcd: truncated: binary_compressed"):
        gio.read_scan(path)
    # A back reference before the start of the output.
    path.write_bytes(header + np.array([3, 12], "<u4").tobytes() + b"\xe0\x00\x05")
    with pytest.raises(InputError, match=r"packed\.pcd: corrupt LZF data"):
        gio.read_scan(path)


def test_cheap_checks_find_bad_files_without_reading_them(tmp_path):
    (tmp_path / "odd.bin").write_bytes(b"\x00" * 17)
    with pytest.raises(InputError, match=r"odd\.bin: file size 17 bytes is not a multiple of 16"):
        check_scan(tmp_path / "odd.bin")
    with pytest.raises(InputError, match=r"gone\.pcd: file not found"):
        check_scan(tmp_path / "gone.pcd")
    write_scan_pcd(tmp_path / "cut.pcd", np.zeros((10, 4), np.float32), "binary")
    raw = (tmp_path / "cut.pcd").read_bytes()
    (tmp_path / "cut.pcd").write_bytes(raw[:-20])
    with pytest.raises(InputError, match=r"cut\.pcd: truncated: 10 points need 160 bytes"):
        check_scan(tmp_path / "cut.pcd")
    np.save(tmp_path / "flat.npy", np.zeros(12, np.float32))
    with pytest.raises(InputError, match=r"flat\.npy: expected a numeric \(N, 3\)"):
        check_scan(tmp_path / "flat.npy")
    (tmp_path / "bad.ply").write_bytes(b"PLY?")
    with pytest.raises(InputError, match=r"bad\.ply: not a PLY file"):
        check_scan(tmp_path / "bad.ply")


def test_pcd_truncated(tmp_path):
    path = tmp_path / "short.pcd"
    path.write_bytes(
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n"
        b"POINTS 3\nDATA binary\n" + np.zeros(6, np.float32).tobytes()
    )
    with pytest.raises(InputError, match=r"short\.pcd: truncated"):
        gio.read_scan(path)


def test_pcd_ascii_bad_row(tmp_path):
    points = random_points(3)
    path = tmp_path / "rows.pcd"
    write_pcd_ascii(
        path,
        {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]},
        {"x": "F4", "y": "F4", "z": "F4"},
    )
    lines = path.read_text().splitlines()
    lines[12] += " 7"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"rows\.pcd: line 13 has 4 columns, expected 3"):
        gio.read_scan(path)


def test_ply_without_xyz(tmp_path):
    path = tmp_path / "noxyz.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n")
    with pytest.raises(InputError, match=r"noxyz\.ply: no x, y, z field"):
        gio.read_scan(path)


def test_npy_wrong_shape(tmp_path):
    np.save(tmp_path / "flat.npy", np.zeros(12))
    with pytest.raises(InputError, match=r"flat\.npy: expected a numeric \(N, 3\)"):
        gio.read_scan(tmp_path / "flat.npy")


def test_label_count_mismatch(tmp_path):
    path = tmp_path / "000000.label"
    gio.write_labels(path, np.arange(5))
    with pytest.raises(InputError, match=r"000000\.label: label count 5 does not match .* 6"):
        gio.read_labels(path, expected_count=6)


def test_label_size_not_multiple_of_4(tmp_path):
    path = tmp_path / "000000.label"
    path.write_bytes(b"\x00" * 6)
    with pytest.raises(InputError, match=r"000000\.label: file size 6 bytes is not a multiple"):
        gio.read_labels(path)


def test_sequence_labels_wrong_count(tmp_path):
    made = make_sequence(tmp_path)
    gio.write_labels(made["dir"] / "labels" / "000000.label", np.arange(3))
    seq = gio.KittiSequence(tmp_path, "03")
    with pytest.raises(InputError, match=r"000000\.label: label count 3 .* 10 points"):
        seq.labels(0)


@pytest.mark.parametrize(
    ("remove", "match"),
    [
        ("", r"sequences[/\\]03: sequence 03 not found"),
        ("sequences/03/velodyne", r"velodyne: velodyne folder not found"),
    ],
)
def test_sequence_missing_parts(tmp_path, remove, match):
    import shutil

    if remove:
        make_sequence(tmp_path)
        target = tmp_path / remove
        shutil.rmtree(target) if target.is_dir() else target.unlink()
    else:
        (tmp_path / "sequences").mkdir()
    with pytest.raises(InputError, match=match):
        gio.KittiSequence(tmp_path, 3)


def test_sequence_without_calib_and_times_takes_said_defaults(tmp_path):
    made = make_sequence(tmp_path, poses=False)
    (made["dir"] / "calib.txt").unlink()
    (made["dir"] / "times.txt").unlink()
    seq = gio.KittiSequence(tmp_path, 3)
    np.testing.assert_array_equal(seq.Tr_cam_velo, np.eye(4))
    np.testing.assert_allclose(seq.times, [0.0, 0.1, 0.2, 0.3])
    assert [d.split(":")[0] for d in seq.defaults] == [
        "no calib.txt",
        "no times.txt",
        "no poses/03.txt",
    ]


def test_sequence_missing_root(tmp_path):
    with pytest.raises(InputError, match=r"nowhere: dataset root not found"):
        gio.KittiSequence(tmp_path / "nowhere", 0)


def test_sequence_times_count_mismatch(tmp_path):
    made = make_sequence(tmp_path)
    (made["dir"] / "times.txt").write_text("0\n0.1\n0.2\n")
    with pytest.raises(InputError, match=r"times\.txt: 3 timestamps but 4 scans"):
        gio.KittiSequence(tmp_path, 3)


def test_sequence_pose_count_mismatch(tmp_path):
    make_sequence(tmp_path)
    gio.write_kitti_poses(tmp_path / "poses" / "03.txt", random_poses(6))
    with pytest.raises(InputError, match=r"03\.txt: 6 poses but 4 scans"):
        gio.KittiSequence(tmp_path, 3)
