"""The KITTI odometry layout: ``calib.txt``, ``times.txt``, SemanticKITTI labels, sequences.

* ``calib.txt`` lines are ``KEY: v1 v2 ...``; ``Tr`` is the Velodyne-to-camera-0 extrinsic as
  its top 3x4 (see :mod:`gloam_jax.io.poses` for how it relates camera and LiDAR poses).
* ``times.txt`` holds one scan timestamp a line, seconds.
* SemanticKITTI labels are uint32 per point, class id in the low 16 bits, instance id in the
  high 16 bits.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gloam_jax.errors import InputError
from gloam_jax.io.files import PathLike, load_npy, parse_rows, read_bytes, read_text, write_atomic
from gloam_jax.io.poses import cam_to_lidar_poses, read_kitti_poses, to_homogeneous
from gloam_jax.io.scans import check_scan, read_scan

__all__ = [
    "KittiSequence",
    "read_calib",
    "read_labels",
    "read_times",
    "write_calib",
    "write_labels",
]


def read_calib(path: PathLike) -> dict[str, np.ndarray]:
    """KITTI ``calib.txt`` (``KEY: v1 v2 ...`` lines) -> ``{key: float64 array}``.

    Keys starting with ``Tr`` become ``(4, 4)`` homogeneous matrices; other entries are shaped
    by their length: 12 -> ``(3, 4)`` (``P0``..``P3``), 9 -> ``(3, 3)``, 16 -> ``(4, 4)``,
    anything else stays 1-D.
    """
    text, name = read_text(path)
    entries: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep or not key:
            raise InputError(name, f"line {lineno} is not of the form 'KEY: v1 v2 ...'")
        try:
            values = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise InputError(name, f"line {lineno} ({key}) has a non-numeric value") from None
        if not np.all(np.isfinite(values)):
            raise InputError(name, f"line {lineno} ({key}) has a NaN or infinite value")
        if key.startswith("Tr"):
            if values.size == 12:
                entries[key] = to_homogeneous(values.reshape(3, 4))
            elif values.size == 16:
                entries[key] = values.reshape(4, 4)
            else:
                raise InputError(
                    name, f"line {lineno} ({key}) has {values.size} columns, expected 12"
                )
            R = entries[key][:3, :3]
            # Tr maps LiDAR points into the camera: a rigid motion, so invertible with det +1.
            if not abs(np.linalg.det(R) - 1.0) < 0.01 or not np.allclose(
                entries[key][3], [0, 0, 0, 1]
            ):
                raise InputError(
                    name,
                    f"line {lineno} ({key}) is not a rigid transform (det {np.linalg.det(R):.3g})",
                )
        else:
            shape = {9: (3, 3), 12: (3, 4), 16: (4, 4)}.get(values.size, (values.size,))
            entries[key] = values.reshape(shape)
    if not entries:
        raise InputError(name, "file is empty (no calibration entries)")
    return entries


def write_calib(path: PathLike, entries: dict[str, np.ndarray]) -> None:
    """Write ``{key: array}`` as KITTI ``calib.txt``; ``Tr*`` 4x4 matrices as their top 3x4."""
    lines = []
    for key, value in entries.items():
        value = np.asarray(value, dtype=np.float64)
        if key.startswith("Tr") and value.shape == (4, 4):
            # KITTI tools expect 12 numbers for Tr; read_calib restores the bottom row.
            value = value[:3]
        lines.append(f"{key}: " + " ".join(f"{v:.12e}" for v in value.ravel()))
    write_atomic(path, ("\n".join(lines) + "\n").encode("ascii"))


def read_times(path: PathLike) -> np.ndarray:
    """One timestamp (seconds) a line -> ``(N,)`` float64."""
    text, name = read_text(path)
    return parse_rows(text, name, 1, "timestamp")[:, 0]


def default_times(paths: list[Path], period: float = 0.1) -> tuple[np.ndarray, str]:
    """Scan times (N,) s for scans without a ``times.txt``, and the note saying so: each scan's
    file number (the digits its name ends with) times ``period``, from the first, so that a
    missing file is a gap in time; ``period`` apart in file order where the names are not
    frame numbers (not increasing, or mostly not one apart: clock times, say)."""
    numbers = [re.search(r"(\d+)$", p.stem) for p in paths]
    note = f"no times.txt: scans taken at {1 / period:g} Hz"
    if all(numbers):
        index = np.array([int(m.group(1)) for m in numbers])
        steps = np.diff(index)
        if len(steps) and np.all(steps > 0) and np.median(steps) == 1:
            missing = int(index[-1] - index[0] + 1 - len(index))
            if missing:
                note += f", by their file numbers ({missing} numbers missing: gaps in time)"
            return (index - index[0]) * period, note
    return np.arange(len(paths)) * period, note


def read_labels(path: PathLike, expected_count: int | None = None) -> np.ndarray:
    """SemanticKITTI ``.label`` -> ``(N,)`` uint16 class ids (low 16 bits of each uint32)."""
    raw = read_bytes(path)
    if len(raw) % 4:
        raise InputError(path, f"file size {len(raw)} bytes is not a multiple of 4 (uint32)")
    labels = np.frombuffer(raw, dtype="<u4")
    if expected_count is not None and len(labels) != expected_count:
        raise InputError(
            path, f"label count {len(labels)} does not match the scan's {expected_count} points"
        )
    return (labels & 0xFFFF).astype(np.uint16)


def write_labels(
    path: PathLike, class_ids: np.ndarray, instance_ids: np.ndarray | None = None
) -> None:
    """Write ``(N,)`` class ids (and optional ``(N,)`` instance ids) as a ``.label`` file."""
    cls = np.asarray(class_ids)
    inst = np.zeros_like(cls) if instance_ids is None else np.asarray(instance_ids)
    if cls.ndim != 1 or inst.shape != cls.shape:
        raise InputError(
            path, f"class and instance ids must be equal (N,) arrays, got {cls.shape}, {inst.shape}"
        )
    for what, ids in (("class", cls), ("instance", inst)):
        if ids.size and (ids.dtype.kind not in "iu" or ids.min() < 0 or ids.max() > 0xFFFF):
            raise InputError(path, f"{what} ids must be integers in [0, 65535]")
    packed = (inst.astype(np.uint32) << 16) | cls.astype(np.uint32)
    write_atomic(path, packed.astype("<u4").tobytes())


def _read_only(a: np.ndarray) -> np.ndarray:
    # Cached arrays are shared between callers; freezing them stops one caller corrupting another.
    a.setflags(write=False)
    return a


class KittiSequence:
    """One sequence of the KITTI odometry layout under ``root``.

    ``root/sequences/NN/velodyne/%06d.bin`` are required; ``sequences/NN/calib.txt`` (without
    it, ``Tr`` is the identity: poses stay in the LiDAR frame), ``sequences/NN/times.txt``
    (without it, 10 Hz), ``root/poses/NN.txt``, ``sequences/NN/labels/%06d.label`` and
    per-point timestamps ``sequences/NN/timestamps/%06d.npy`` (any convention, see
    :func:`gloam_jax.preprocess.normalise_times`) are optional; ``defaults`` says which
    defaults were taken. Frames are the sorted ``.bin`` files. Everything but the scans is
    read and checked on construction.
    """

    def __init__(self, root: PathLike, sequence: int | str) -> None:
        self.root = Path(root)
        if isinstance(sequence, int) or str(sequence).isdigit():
            sequence = f"{int(sequence):02d}"
        self.sequence: str = sequence
        self.sequence_dir = self.root / "sequences" / sequence
        velodyne = self.sequence_dir / "velodyne"
        for d, what in (
            (self.root, "dataset root"),
            (self.sequence_dir, f"sequence {sequence}"),
            (velodyne, "velodyne folder"),
        ):
            if not d.is_dir():
                raise InputError(d, f"{what} not found")
        self._scan_paths = sorted(velodyne.glob("*.bin"))
        n = len(self._scan_paths)
        if n == 0:
            raise InputError(velodyne, "no .bin scans found")

        self.defaults: list[str] = []  # what was missing, and what was assumed instead
        calib_path = self.sequence_dir / "calib.txt"
        if calib_path.exists():
            calib = read_calib(calib_path)
            if "Tr" not in calib:
                raise InputError(calib_path, "no 'Tr' (Velodyne to camera 0) entry")
            self._Tr = _read_only(calib["Tr"])
        else:
            self._Tr = _read_only(np.eye(4))
            self.defaults.append("no calib.txt: poses in the LiDAR frame (Tr = identity)")

        times_path = self.sequence_dir / "times.txt"
        if times_path.exists():
            self._times = _read_only(read_times(times_path))
            if len(self._times) != n:
                raise InputError(
                    times_path, f"{len(self._times)} timestamps but {n} scans in {velodyne}"
                )
        else:
            times, note = default_times(self._scan_paths)
            self._times = _read_only(times)
            self.defaults.append(note)

        poses_path = self.root / "poses" / f"{sequence}.txt"
        self._poses_cam: np.ndarray | None = None
        self._poses_lidar: np.ndarray | None = None
        if poses_path.exists():
            self._poses_cam = _read_only(read_kitti_poses(poses_path))
            if len(self._poses_cam) != n:
                raise InputError(
                    poses_path, f"{len(self._poses_cam)} poses but {n} scans in {velodyne}"
                )
            self._poses_lidar = _read_only(cam_to_lidar_poses(self._poses_cam, self._Tr))
        else:
            self.defaults.append(f"no poses/{sequence}.txt: no ground truth, not scored")

    def __len__(self) -> int:
        return len(self._scan_paths)

    def __repr__(self) -> str:
        return f"KittiSequence({str(self.root)!r}, {self.sequence!r}, frames={len(self)})"

    def scan_path(self, i: int) -> Path:
        """Path of frame ``i``'s ``.bin`` scan."""
        return self._scan_paths[i]

    def scan(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``(N, 4)`` float32 ``[x, y, z, intensity]`` (Velodyne frame)."""
        return read_scan(self._scan_paths[i])

    def _point_count(self, i: int) -> int:
        # From the file size, so optional per-point files can be checked without reading the scan.
        return self._scan_paths[i].stat().st_size // 16

    def labels(self, i: int) -> np.ndarray | None:
        """Frame ``i``'s ``(N,)`` uint16 class ids, or None if the sequence has no labels."""
        path = self.sequence_dir / "labels" / f"{self._scan_paths[i].stem}.label"
        if not path.exists():
            return None
        return read_labels(path, expected_count=self._point_count(i))

    def _times_path(self, i: int) -> Path:
        return self.sequence_dir / "timestamps" / f"{self._scan_paths[i].stem}.npy"

    @property
    def has_point_times(self) -> bool:
        """Whether the sequence has per-point times (its ``timestamps/`` folder)."""
        return (self.sequence_dir / "timestamps").is_dir()

    def point_times(self, i: int) -> np.ndarray | None:
        """Frame ``i``'s ``(N,)`` per-point times as stored (float32 or float64; integers as
        int64), or None. The simulator writes float32 seconds from mid-sweep; any convention
        is accepted downstream (:func:`gloam_jax.preprocess.normalise_times`)."""
        path = self._times_path(i)
        if not path.exists():
            return None
        times = load_npy(path)
        n = self._point_count(i)
        if times.shape != (n,) or times.dtype.kind not in "fiu":
            raise InputError(
                path, f"expected {n} numeric point times, got shape {times.shape} {times.dtype}"
            )
        if times.dtype.kind in "iu":
            return times.astype(np.int64)
        return times if times.dtype in (np.float32, np.float64) else times.astype(np.float64)

    def check(self, frames: range | None = None) -> None:
        """Cheap checks of each scan (and its per-point times file) before the first frame is
        computed: sizes and headers, not the data (:func:`gloam_jax.io.scans.check_scan`)."""
        for i in range(len(self)) if frames is None else frames:
            path = self._scan_paths[i]
            check_scan(path)
            times = self._times_path(i)
            if self.has_point_times and not times.exists():
                raise InputError(times, "missing: the other scans have per-point times")

    @property
    def times(self) -> np.ndarray:
        """Scan timestamps ``(N,)`` float64, seconds (read-only)."""
        return self._times

    @property
    def Tr_cam_velo(self) -> np.ndarray:
        """``(4, 4)`` Velodyne-to-camera-0 extrinsic ``Tr`` (read-only)."""
        return self._Tr

    @property
    def gt_poses_cam(self) -> np.ndarray | None:
        """Ground-truth camera-0 poses ``(N, 4, 4)`` (read-only), or None without a pose file."""
        return self._poses_cam

    @property
    def gt_poses_lidar(self) -> np.ndarray | None:
        """Ground-truth LiDAR poses ``inv(Tr) @ P @ Tr``, ``(N, 4, 4)`` (read-only), or None."""
        return self._poses_lidar
