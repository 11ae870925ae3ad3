"""ROS bags and MCAP files: recordings written here (by rosbags' own writers) from a simulated
drive run exactly as the same scans in a folder; two drivers' per-point time fields are found
and deskew as well as the simulator's own times; every bad recording is one line."""

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from gloam_jax import io
from gloam_jax.cli import app
from gloam_jax.datasets import open_dataset
from gloam_jax.datasets.rosbag import decode_cloud
from gloam_jax.errors import InputError
from gloam_jax.odometry import OdometryConfig
from gloam_jax.pipeline import run_dataset, select_frames
from gloam_jax.preprocess import normalise_times
from gloam_jax.simulate import simulate

rosbags = pytest.importorskip("rosbags")  # the `ros` extra (in `test` too)
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

pytestmark = pytest.mark.xdist_group("rosbag")  # one worker builds the module's drive once

runner = CliRunner()
FRAMES = 10
CLOUD = "sensor_msgs/msg/PointCloud2"
FLOAT32, FLOAT64, UINT16, UINT32 = 7, 8, 4, 6  # sensor_msgs/PointField datatypes
# Two drivers' layouts (name, PointField type, byte offset), padding included, and their
# per-point times as a function of the simulator's (s from mid-sweep, one 0.1 s sweep).
DRIVERS = {
    # ouster_ros: t is uint32 ns from the sweep's start; 48-byte points
    "ouster": {
        "fields": [("x", FLOAT32, 0), ("y", FLOAT32, 4), ("z", FLOAT32, 8),
                   ("intensity", FLOAT32, 16), ("t", UINT32, 20), ("ring", UINT16, 26)],
        "step": 48,
        "time": "t",
        "times": lambda mid: np.round((mid.astype(np.float64) + 0.05) * 1e9).astype(np.uint32),
        "convention": "ns from start",
    },
    # velodyne_pointcloud: time is float32 s relative to the stamp (the sweep's last packet),
    # listed first here: the order of the fields is not the order of the bytes
    "velodyne": {
        "fields": [("time", FLOAT32, 24), ("ring", UINT16, 20), ("intensity", FLOAT32, 16),
                   ("x", FLOAT32, 0), ("y", FLOAT32, 4), ("z", FLOAT32, 8)],
        "step": 32,
        "time": "time",
        "times": lambda mid: (mid - 0.05).astype(np.float32),
        "convention": "s before end",
    },
}  # fmt: skip
STAMP0 = 1_700_000_000  # s since the epoch: header stamps as a robot's clock writes them
ROS1, ROS2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_HUMBLE)
_NUMPY = {FLOAT32: "f4", FLOAT64: "f8", UINT16: "u2", UINT32: "u4"}


def cloud_bytes(scan, times, driver: str) -> bytes:
    """A scan ``(N, 4)`` and its driver times as that driver's PointCloud2 data bytes."""
    layout = DRIVERS[driver]
    dtype = np.dtype({
        "names": [name for name, _, _ in layout["fields"]],
        "formats": ["<" + _NUMPY[kind] for _, kind, _ in layout["fields"]],
        "offsets": [offset for _, _, offset in layout["fields"]],
        "itemsize": layout["step"],
    })  # fmt: skip
    record = np.zeros(len(scan), dtype)
    for k, name in enumerate("xyz"):
        record[name] = scan[:, k]
    record["intensity"] = scan[:, 3]
    record[layout["time"]] = times
    record["ring"] = np.arange(len(scan)) % 16
    return record.tobytes()


def point_cloud(typestore, k: int, data: bytes, fields, step: int, n: int):
    types = typestore.types
    field = types["sensor_msgs/msg/PointField"]
    stamp = types["builtin_interfaces/msg/Time"](sec=STAMP0 + k // 10, nanosec=k % 10 * 10**8)
    header = {"stamp": stamp, "frame_id": "lidar"}
    if "seq" in types["std_msgs/msg/Header"].__dataclass_fields__:  # ROS 1 headers count
        header["seq"] = k
    return types[CLOUD](
        header=types["std_msgs/msg/Header"](**header), height=1, width=n,
        fields=[field(name=name, offset=offset, datatype=kind, count=1)
                for name, kind, offset in fields],
        is_bigendian=False, point_step=step, row_step=step * n,
        data=np.frombuffer(data, np.uint8), is_dense=True,
    )  # fmt: skip


def write_recording(path, storage: str, messages: dict[str, list]):
    """``messages`` {topic: [(msgtype, ROS 1 message, ROS 2 message), ...]} as a ROS 1 bag
    (``ros1``), a ROS 2 bag folder (``sqlite3``) or a bare ``.mcap`` file (``mcap``);
    returns the path ``gloam run`` takes."""
    if storage == "ros1":
        with Writer1(path) as writer:
            for topic, items in messages.items():
                connection = writer.add_connection(topic, items[0][0], typestore=ROS1)
                for k, (msgtype, msg, _) in enumerate(items):
                    writer.write(
                        connection, (STAMP0 + k) * 10**9, ROS1.serialize_ros1(msg, msgtype)
                    )
        return path
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    folder = path.with_suffix("") if storage == "mcap" else path
    with Writer2(folder, version=9, storage_plugin=plugin) as writer:
        for topic, items in messages.items():
            connection = writer.add_connection(topic, items[0][0], typestore=ROS2)
            for k, (msgtype, _, msg) in enumerate(items):
                writer.write(connection, (STAMP0 + k) * 10**9, ROS2.serialize_cdr(msg, msgtype))
    if storage != "mcap":
        return folder
    shutil.move(next(folder.glob("*.mcap")), path)  # the storage file alone, no metadata.yaml
    shutil.rmtree(folder)
    return path


def driver_messages(drive, driver: str) -> list:
    """The drive's scans as ``driver``'s PointCloud2 messages, for both ROS versions."""
    layout = DRIVERS[driver]
    items = []
    for k, (scan, mid) in enumerate(drive.frames):
        data = cloud_bytes(scan, layout["times"](mid), driver)
        args = (k, data, layout["fields"], layout["step"], len(scan))
        items.append((CLOUD, point_cloud(ROS1, *args), point_cloud(ROS2, *args)))
    return items


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A short simulated drive (16 beams, motion-distorted, times in s from mid-sweep)."""
    import types

    root = tmp_path_factory.mktemp("drive")
    simulate(root, frames=FRAMES, num_beams=16, num_columns=500, seed=7, style="urban")
    kitti = open_dataset(root, "00")
    frames = [kitti.frame(i) for i in range(FRAMES)]
    stamps = np.array([STAMP0 + k // 10 + 1e-9 * (k % 10 * 10**8) for k in range(FRAMES)])
    return types.SimpleNamespace(root=root, kitti=kitti, frames=frames, stamps=stamps)


def folder_of(drive, driver: str, folder):
    """The same scans as a folder: .bin files, the driver's times as stored (decoded to
    int64 / float64, as from the message), the header stamps as times.txt."""
    (folder / "timestamps").mkdir(parents=True)
    for k, (scan, mid) in enumerate(drive.frames):
        io.write_scan_bin(folder / f"{k:06d}.bin", scan)
        times = DRIVERS[driver]["times"](mid)
        np.save(folder / "timestamps" / f"{k:06d}.npy",
                times.astype(np.int64 if times.dtype.kind == "u" else np.float64))  # fmt: skip
    (folder / "times.txt").write_text("".join(f"{float(t)!r}\n" for t in drive.stamps))
    return folder


def lidar_poses(run, name: str) -> np.ndarray:
    return io.read_kitti_poses(run / f"{name}_poses_lidar_kitti.txt")


@pytest.mark.parametrize(
    ("storage", "driver", "name", "start", "count", "stride"),
    [("ros1", "ouster", "drive.bag", 1, 8, 1), ("sqlite3", "velodyne", "drive", 1, 8, 1),
     ("mcap", "ouster", "drive.mcap", 2, 4, 2)],
)  # fmt: skip
def test_a_recording_runs_exactly_as_its_scans_in_a_folder(drive, tmp_path, storage, driver,
                                                           name, start, count, stride):  # fmt: skip
    path = write_recording(tmp_path / name, storage, {"/points": driver_messages(drive, driver)})
    out = tmp_path / "results"
    selection = ["--start", str(start), "--frames", str(count), "--stride", str(stride)]
    args = [*selection, "--no-compilation-cache"]
    result = runner.invoke(app, ["run", str(path), *args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    assert metrics["dataset"] == "rosbag"
    details = metrics["dataset_details"]
    recording = {"ros1": "ROS 1 bag", "sqlite3": "ROS 2 bag (sqlite3)", "mcap": "MCAP file"}
    assert details["recording"] == recording[storage]
    assert details["topic"] == "/points" and details["messages"] == FRAMES
    time_field = DRIVERS[driver]["time"]
    assert details["per-point time field"] == time_field
    assert (
        f"{time_field}:{'uint32' if driver == 'ouster' else 'float32'}@" in details["point fields"]
    )
    assert metrics["deskew"]["used"] == "timestamps"
    assert metrics["deskew"]["time_convention"] == DRIVERS[driver]["convention"]
    assert metrics["frames"] == {"start": start, "stride": stride, "count": count}
    for said in ("topic: /points", f"messages: {FRAMES}", DRIVERS[driver]["convention"]):
        assert result.output.count(said) == 1, result.output  # each said once
    # The same scans, times and stamps as a folder: the same poses.
    folder = folder_of(drive, driver, tmp_path / "folder")
    chosen = select_frames(FRAMES, start, count, stride)
    run_dataset(open_dataset(folder), OdometryConfig(), tmp_path / "ref", chosen)
    np.testing.assert_allclose(
        lidar_poses(out / "latest", path.stem), lidar_poses(tmp_path / "ref", "folder"), atol=1e-6
    )
    stamps, _ = io.read_tum_poses(out / "latest" / f"{path.stem}_poses_tum.txt")
    np.testing.assert_allclose(stamps, drive.stamps[list(chosen)], rtol=0, atol=1e-6)


def test_each_drivers_time_field_deskews_as_the_simulators_own_times(drive, tmp_path):
    # What the deskew reads of a scan is its times made seconds from mid-sweep: for each
    # driver's field they must be the simulator's own, frame by frame (a field ignored, or the
    # wrong one read, is off by up to a whole sweep, 0.1 s).
    frames = select_frames(FRAMES)
    own = [normalise_times(t, 0.1)[0] for _, t in drive.frames]
    reference = run_dataset(drive.kitti, OdometryConfig(), tmp_path / "ref", frames)
    assert reference["deskew"]["used"] == "timestamps"
    assert reference["deskew"]["time_convention"] == "s from mid-sweep"
    poses = lidar_poses(tmp_path / "ref", "00")
    for driver in DRIVERS:
        bag = write_recording(tmp_path / f"{driver}.bag", "ros1",
                              {"/points": driver_messages(drive, driver)})  # fmt: skip
        recording = open_dataset(bag)
        for k in range(FRAMES):
            times, convention = normalise_times(recording.frame(k)[1], 0.1)
            assert convention == DRIVERS[driver]["convention"]
            np.testing.assert_allclose(times, own[k], rtol=0, atol=1e-6)
        result = run_dataset(recording, OdometryConfig(), tmp_path / driver, frames)
        assert result["deskew"]["used"] == "timestamps"
        assert result["deskew"]["time_convention"] == DRIVERS[driver]["convention"]
        # The same run, up to where times a few ns apart tip a round's discrete choices
        # (requery, convergence) the other way: millimetres, on this 16-beam drive.
        np.testing.assert_allclose(lidar_poses(tmp_path / driver, driver), poses, atol=0.02)


def test_any_field_order_type_byte_order_and_padding_decodes():
    """x y z as big-endian float64 after the intensity, points padded, rows padded."""
    rng = np.random.default_rng(0)
    height, width, step, row_step = 3, 5, 40, 40 * 5 + 8
    dtype = np.dtype({"names": ["intensity", "x", "y", "z", "timestamp"],
                      "formats": [">f4", ">f8", ">f8", ">f8", ">f8"],
                      "offsets": [0, 8, 16, 24, 32], "itemsize": step})  # fmt: skip
    record = np.zeros((height, width), dtype)
    for name in dtype.names:
        record[name] = rng.normal(size=(height, width))
    record["timestamp"] = STAMP0 + rng.uniform(0, 0.1, size=(height, width))
    rows = np.zeros((height, row_step), np.uint8)
    rows[:, : width * step] = np.frombuffer(record.tobytes(), np.uint8).reshape(height, -1)
    fields = [("z", FLOAT64, 24), ("timestamp", FLOAT64, 32), ("x", FLOAT64, 8),
              ("intensity", FLOAT32, 0), ("y", FLOAT64, 16)]  # fmt: skip
    msg = point_cloud(ROS2, 0, rows.tobytes(), fields, step, width)
    msg.height, msg.row_step, msg.is_bigendian = height, row_step, True
    scan, times = decode_cloud(msg, "cloud")
    flat = record.reshape(-1)
    expected = np.c_[flat["x"], flat["y"], flat["z"], flat["intensity"]].astype(np.float32)
    np.testing.assert_array_equal(scan, expected)
    np.testing.assert_array_equal(times, flat["timestamp"])
    msg.fields[0].datatype = 9
    with pytest.raises(InputError, match="cloud: field 'z' has unknown datatype 9"):
        decode_cloud(msg, "cloud")
    msg.fields[0].datatype, msg.fields[0].offset = FLOAT64, 36
    with pytest.raises(InputError, match=r"field 'z' \(offset 36, 1 x >f8\) runs past the point"):
        decode_cloud(msg, "cloud")


def test_the_topic_is_chosen_by_itself_or_by_name(drive, tmp_path):
    clouds = driver_messages(drive, "ouster")[:3]
    bag = write_recording(tmp_path / "two.bag", "ros1", {"/front": clouds, "/rear": clouds})
    with pytest.raises(InputError, match=r"two\.bag: 2 PointCloud2 topics \(/front, /rear\): "
                       "choose one with --topic"):  # fmt: skip
        open_dataset(bag)
    assert open_dataset(bag, topic="/rear").topic == "/rear"
    with pytest.raises(InputError, match=r"no PointCloud2 topic '/top' \(.*: /front, /rear\)"):
        open_dataset(bag, topic="/top")
    with pytest.raises(InputError, match="--topic does not apply to kitti data"):
        open_dataset(drive.root, "00", topic="/points")
    # gloam segment takes recordings as gloam run does: message 1 of /rear labelled.
    out = tmp_path / "segment"
    args = ["segment", str(bag), "--topic", "/rear", "--start", "1", "--frames", "1"]
    result = runner.invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    labels = io.read_labels(out / "labels" / "000001.label")
    assert labels.shape == (len(drive.frames[1][0]),)


def run_one_line(path, *args) -> str:
    """``gloam run`` on bad input: exit status 2 and one line, no traceback (nor anything else
    printed: the recording is refused when it is opened)."""
    result = runner.invoke(app, ["run", str(path), *args, "--out", str(path.parent / "r")])
    assert result.exit_code == 2, result.output
    assert len(result.output.strip().splitlines()) == 1 and "Traceback" not in result.output
    return result.output


def blank_messages(count: int, fields=None, size=None, stamp=None) -> list:
    """``count`` messages of 4 zero points (32 bytes each) in Velodyne's layout, for both ROS
    versions; ``fields``, ``size`` (data bytes) and ``stamp`` (stamp index) of message ``k``
    as given."""
    fields = fields or (lambda k: DRIVERS["velodyne"]["fields"])
    size, stamp = size or (lambda k: 32 * 4), stamp or (lambda k: k)
    return [
        (CLOUD, *(point_cloud(store, stamp(k), bytes(size(k)), fields(k), 32, 4)
                  for store in (ROS1, ROS2)))
        for k in range(count)
    ]  # fmt: skip


def test_bad_recordings_are_one_line(drive, tmp_path):
    types = ROS2.types
    text = [("std_msgs/msg/String", types["std_msgs/msg/String"](data="hello"),
             types["std_msgs/msg/String"](data="hello"))] * 2  # fmt: skip
    no_cloud = write_recording(tmp_path / "chatter.mcap", "mcap", {"/chatter": text})
    line = run_one_line(no_cloud)
    assert "chatter.mcap: no sensor_msgs/PointCloud2 topic (topics: /chatter (std_msgs" in line
    clouds = driver_messages(drive, "velodyne")[:3]
    two = write_recording(tmp_path / "two", "sqlite3", {"/a": clouds, "/b": clouds})
    assert "2 PointCloud2 topics (/a, /b): choose one with --topic" in run_one_line(two)
    # No x/y/z: the fields renamed, as an unknown driver might write them.
    renamed = blank_messages(3, lambda k: [("u", FLOAT32, 0), ("v", FLOAT32, 4), ("w", FLOAT32, 8)])
    layout = write_recording(tmp_path / "layout.bag", "ros1", {"/points": renamed})
    assert "layout.bag/000000: no x, y, z field (fields: u, v, w)" in run_one_line(layout)
    full = write_recording(tmp_path / "full.bag", "ros1", {"/points": clouds})
    cut = tmp_path / "cut.bag"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size * 2 // 3])
    assert "cut.bag: unreadable recording: " in run_one_line(cut)
    mcap = write_recording(tmp_path / "full.mcap", "mcap", {"/points": clouds})
    cut_mcap = tmp_path / "cut.mcap"
    cut_mcap.write_bytes(mcap.read_bytes()[:-100])
    assert "cut.mcap: unreadable recording: " in run_one_line(cut_mcap)
    # A later message's data shorter than its rows say: found before the first frame is run,
    # named by its index; a selection without it runs.
    short = blank_messages(4, size=lambda k: 32 * (3 if k == 2 else 4))
    bag = write_recording(tmp_path / "short.bag", "ros1", {"/points": short})
    result = runner.invoke(app, ["run", str(bag), "--out", str(tmp_path / "r")])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert result.output.strip().splitlines()[-1] == (
        f"error: {bag}/000002: truncated: 1 rows of 128 bytes need 128 bytes of data, found 96"
    )
    assert "frame 1/" not in result.output  # nothing was run
    with pytest.raises(InputError, match="000002: truncated"):
        open_dataset(bag).check(range(1, 4))
    open_dataset(bag).check(range(2))
    # Header stamps that do not increase; a later message without the time field.
    same = blank_messages(3, stamp=lambda k: 0)
    line = run_one_line(write_recording(tmp_path / "same.bag", "ros1", {"/points": same}))
    assert "same.bag/000001: header stamp 1700000000.000000000 s is not after" in line
    fields = DRIVERS["velodyne"]["fields"]  # "time" first
    untimed = blank_messages(3, lambda k: fields[1:] if k == 1 else fields)
    bag = write_recording(tmp_path / "untimed.bag", "ros1", {"/points": untimed})
    with pytest.raises(InputError, match="untimed.bag/000001: per-point time field none, unlike"):
        open_dataset(bag).check(range(3))
