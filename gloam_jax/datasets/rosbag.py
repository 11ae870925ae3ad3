"""Recordings as robots make them: ROS 1 bags, ROS 2 bags (sqlite3 or MCAP) and MCAP files of
``sensor_msgs/PointCloud2`` scans, read by the pure-Python ``rosbags`` library (the optional
``ros`` extra), as KISS-ICP reads them.

A recording is a ``.bag`` file, a ROS 2 bag folder (``metadata.yaml`` beside its ``.db3`` or
``.mcap`` files) or a ``.mcap`` file. Its one PointCloud2 topic is taken; with several, the
``topic`` option names one. Frame times are the messages' header stamps (s since the epoch,
float64). Per-point times are the driver's own field, as stored (Ouster ``t``: uint32 ns from
the sweep's start; Velodyne ``time``: float32 s relative; Hesai and Robosense ``timestamp``:
absolute s; Livox ``offset_time``: ns), whatever their unit and origin:
:mod:`gloam_jax.preprocess` finds the convention. ``x y z intensity`` may come in any order and
offset, as any PointField type, in either byte order, with padding inside points and rows.

A recording has no calibration or ground truth: poses stay in the LiDAR frame and nothing is
scored (both said once as defaults). Its scans are not assumed motion-distorted (a Livox
sweep is not a spinning one): the ``auto`` deskew policy deskews with per-point times only.
Message ``i`` of the topic goes by ``PATH/NNNNNN`` (``scan_path``) in messages, and a
precomputed feature file for it is named ``NNNNNN``.
"""

from __future__ import annotations

import contextlib
import weakref
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gloam_jax.datasets.base import Dataset, register
from gloam_jax.errors import InputError
from gloam_jax.io.scans import TIME_NAMES, scan_from_columns

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"  # rosbags names ROS 1 types the ROS 2 way too
# sensor_msgs/PointField datatype codes -> NumPy types (byte order added per message).
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def is_recording(path: Path) -> bool:
    """A ``.bag`` or ``.mcap`` file, or a ROS 2 bag folder (one with ``metadata.yaml``)."""
    if path.is_file():
        return path.suffix.lower() in (".bag", ".mcap")
    return (path / "metadata.yaml").is_file()


def point_dtype(msg, source: Path | str) -> np.dtype:
    """A PointCloud2 message's fields -> one point's structured dtype (lower-case names, the
    first of a repeated name; ``itemsize`` is ``point_step``, so gaps are padding). Checks the
    layout: known types, fields inside the point, x/y/z present, data as long as the rows."""
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for field in msg.fields:
        name = field.name.lower()
        if name in names:
            continue
        if field.datatype not in _DATATYPES:
            raise InputError(source, f"field '{field.name}' has unknown datatype {field.datatype}")
        base = np.dtype(order + _DATATYPES[field.datatype])
        count = max(int(field.count), 1)
        if field.offset + count * base.itemsize > msg.point_step:
            raise InputError(
                source,
                f"field '{field.name}' (offset {field.offset}, {count} x {base}) runs past the "
                f"point step of {msg.point_step} bytes",
            )
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(field.offset)
    listed = ", ".join(f.name for f in msg.fields) or "none"
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise InputError(source, f"no {', '.join(missing)} field (fields: {listed})")
    if msg.row_step < msg.width * msg.point_step:
        raise InputError(
            source, f"row step {msg.row_step} is below width {msg.width} x point step "
            f"{msg.point_step}"
        )  # fmt: skip
    if len(msg.data) < msg.height * msg.row_step:
        raise InputError(
            source, f"truncated: {msg.height} rows of {msg.row_step} bytes need "
            f"{msg.height * msg.row_step} bytes of data, found {len(msg.data)}"
        )  # fmt: skip
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step}
    )


def decode_cloud(msg, source: Path | str) -> tuple[np.ndarray, np.ndarray | None]:
    """A PointCloud2 message -> the scan ``(N, 4)`` float32 ``[x, y, z, intensity]`` (zero
    intensity without one) and its per-point times ``(N,)`` as stored, or None."""
    dtype = point_dtype(msg, source)
    data = np.asarray(msg.data, np.uint8)[: msg.height * msg.row_step]
    # Each row may end in padding (row_step beyond width x point_step): cut it off first.
    rows = data.reshape(msg.height, msg.row_step)[:, : msg.width * msg.point_step]
    points = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    columns = {
        name: points[name] if points[name].ndim == 1 else points[name][:, 0] for name in dtype.names
    }
    return scan_from_columns(columns, source)


def time_field(msg) -> str | None:
    """The field a message's per-point times are taken from, or None."""
    names = [f.name.lower() for f in msg.fields]
    return next((name for name in TIME_NAMES if name in names), None)


def describe_fields(msg) -> str:
    """``x:float32@0 y:float32@4 ...``: each field's name, type and offset (count if not 1)."""
    order = ">" if msg.is_bigendian else "<"
    words = []
    for f in msg.fields:
        kind = np.dtype(order + _DATATYPES[f.datatype]).name if f.datatype in _DATATYPES else "?"
        words.append(f"{f.name}:{kind}{'' if f.count <= 1 else f'x{f.count}'}@{f.offset}")
    return " ".join(words)


@contextlib.contextmanager
def open_recording(path: Path) -> Iterator:
    """An open ``rosbags`` reader of the recording at ``path``; its errors (a damaged index, a
    truncated file, an unreadable message) become one-line InputErrors naming the file."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError(
            path, "reading ROS bags and MCAP files needs rosbags: pip install 'gloam-jax[ros]'"
        ) from None
    try:
        # Bags written without message definitions (old ROS 2 sqlite3 ones) decode with these.
        with AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as reader:
            yield reader
    except AnyReaderError as err:
        # rosbags' messages may span lines (YAML errors): one line, as the CLI prints it.
        raise InputError(path, f"unreadable recording: {' '.join(str(err).split())}") from None


def choose_topic(reader, topic: str | None, path: Path) -> str:
    """The PointCloud2 topic: ``topic`` if it is one, else the only one (an InputError listing
    them when there are several or none)."""
    clouds = sorted(t for t, info in reader.topics.items() if info.msgtype == POINTCLOUD2)
    if topic is not None:
        if topic not in clouds:
            found = ", ".join(clouds) or "none"
            raise InputError(path, f"no PointCloud2 topic '{topic}' (PointCloud2 topics: {found})")
        return topic
    if not clouds:
        listed = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(reader.topics.items()))
        raise InputError(path, f"no sensor_msgs/PointCloud2 topic (topics: {listed or 'none'})")
    if len(clouds) > 1:
        raise InputError(
            path, f"{len(clouds)} PointCloud2 topics ({', '.join(clouds)}): choose one with --topic"
        )
    return clouds[0]


def read_messages(path: Path, topic: str, start: int) -> Iterator[tuple[int, object]]:
    """:func:`topic_messages` of the recording at ``path``, which stays open until the last
    message is read or the generator is closed."""
    with open_recording(path) as reader:
        yield from topic_messages(reader, topic, start)


def topic_messages(reader, topic: str, start: int = 0) -> Iterator[tuple[int, object]]:
    """Messages ``start, start + 1, ...`` of ``topic``, decoded, with their index (the ones
    before ``start`` are read but not decoded)."""
    connections = [c for c in reader.connections if c.topic == topic]
    for i, (connection, _, raw) in enumerate(reader.messages(connections)):
        if i >= start:
            yield i, reader.deserialize(raw, connection.msgtype)


@register("rosbag", is_recording, options=("topic",))
class RosbagDataset(Dataset):
    kind = "rosbag"
    distorted = False

    def __init__(self, path: Path, sequence: str | None = None, topic: str | None = None):
        path = Path(path)
        if not path.exists():
            raise InputError(path, "not found")
        self.path = path
        self.name = sequence or (path.name if path.is_dir() else path.stem)
        self.defaults = [
            "a recording has no calibration: poses in the LiDAR frame",
            "a recording has no ground truth: not scored",
        ]
        stamps, problems = [], {}
        with open_recording(path) as reader:
            self.topic = choose_topic(reader, topic, path)
            for i, msg in topic_messages(reader, self.topic):
                stamps.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
                field = time_field(msg)
                if i == 0:
                    first, self._time_field = msg, field
                try:
                    point_dtype(msg, self.scan_path(i))
                    if field != self._time_field:  # deskewing needs every scan's
                        raise InputError(
                            self.scan_path(i),
                            f"per-point time field {field or 'none'}, unlike the "
                            f"first message's {self._time_field or 'none'}",
                        )
                except InputError as err:
                    problems[i] = err  # raised by check() only when the scan is run
        if not stamps:
            raise InputError(path, f"topic '{self.topic}' has no messages")
        self._times = np.asarray(stamps, np.float64)
        steps = np.diff(self._times)
        if np.any(steps <= 0):
            k = int(np.argmax(steps <= 0)) + 1
            raise InputError(
                self.scan_path(k),
                f"header stamp {self._times[k]:.9f} s is not after the previous message's "
                f"{self._times[k - 1]:.9f} s",
            )
        if 0 in problems:  # the first message's layout is the recording's: unusable
            raise problems[0]
        self._problems = problems
        if path.is_dir():
            storage = "MCAP" if any(path.glob("*.mcap")) else "sqlite3"
            recording = f"ROS 2 bag ({storage})"
        else:
            recording = "ROS 1 bag" if path.suffix.lower() == ".bag" else "MCAP file"
        self.details = {
            "recording": recording,
            "topic": self.topic,
            "messages": len(stamps),
            "point fields": describe_fields(first),
            "per-point time field": self._time_field or "none",
        }
        self._stream: Iterator = iter(())
        self._closer: weakref.finalize | None = None
        self._next = 0

    def _message(self, i: int):
        """Message ``i``: read on from the last one asked for, or again from the start (the
        pipeline reads a few first scans, then all in order)."""
        if self._next > i or self._closer is None:
            if self._closer is not None:
                self._closer()  # closes the last reader now, not when collected
            stream = read_messages(self.path, self.topic, i)
            # The open reader closes with the dataset, or at exit while Python still can.
            self._stream, self._next = stream, i
            self._closer = weakref.finalize(self, stream.close)
        for k, msg in self._stream:
            self._next = k + 1
            if k == i:
                return msg
        raise InputError(self.scan_path(i), "message missing (the recording changed?)")

    def __len__(self) -> int:
        return len(self._times)

    def __repr__(self) -> str:
        return f"RosbagDataset({str(self.path)!r}, topic={self.topic!r}, frames={len(self)})"

    def scan_path(self, i: int) -> Path:
        return self.path / f"{i:06d}"

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        return decode_cloud(self._message(i), self.scan_path(i))

    @property
    def has_point_times(self) -> bool:
        return self._time_field is not None

    @property
    def times(self) -> np.ndarray:
        return self._times

    @property
    def Tr_cam_velo(self) -> np.ndarray:
        return np.eye(4)

    @property
    def gt_poses_cam(self) -> np.ndarray | None:
        return None

    def check(self, frames: range) -> None:
        for i in frames:
            if i in self._problems:
                raise self._problems[i]
