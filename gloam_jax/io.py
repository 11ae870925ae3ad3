"""Reading and writing poses, calibration, scans and labels (NumPy, no JAX).

Conventions (shared with :mod:`gloam_jax.geometry`):

* A pose is a float64 ``(4, 4)`` homogeneous matrix ``T_world_frame`` (maps frame points into
  the world); a trajectory is ``(N, 4, 4)``. KITTI pose files store the top ``3x4`` row-major,
  12 numbers a line, in the camera-0 frame: ``P_i = T_cam0_cami``. The calibration ``Tr``
  (``Tr_cam_velo``) maps Velodyne points into camera 0, so LiDAR poses are
  ``inv(Tr) @ P_i @ Tr``.
* TUM lines are ``t x y z qx qy qz qw`` (scalar-last quaternion), ``#`` starts a comment.
* A scan is a float32 ``(N, 4)`` array ``[x, y, z, intensity]`` in the sensor frame. Points
  with NaN coordinates are returned as they are, not an error: later stages drop and count
  them.
* SemanticKITTI labels are uint32 per point, class id in the low 16 bits, instance id in the
  high 16 bits.
* Bad input raises :class:`~gloam_jax.errors.InputError` (``"<file>: <problem>"``), never a
  raw NumPy error. Writers create parent folders and replace the target atomically (temp file
  in the same folder, then ``os.replace``), so a crash never leaves half a file.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

import numpy as np
from scipy.spatial.transform import Rotation

from gloam_jax.errors import InputError

__all__ = [
    "KittiSequence",
    "cam_to_lidar_poses",
    "lidar_to_cam_poses",
    "read_calib",
    "read_kitti_poses",
    "read_labels",
    "read_scan",
    "read_times",
    "read_tum_poses",
    "write_calib",
    "write_kitti_poses",
    "write_labels",
    "write_scan_bin",
    "write_tum_poses",
]

PathLike = str | os.PathLike[str]

# 17 significant digits round-trip float64 exactly; fewer (%.9e) lose ~1e-7 m on km-scale
# KITTI translations, which would show up in trajectory-error comparisons.
_FLOAT_FMT = "%.16e"

# Field names taken as intensity, in order of preference (PCL, PLY exporters, SemanticKITTI).
_INTENSITY_NAMES = ("intensity", "i", "reflectance", "remission", "scalar_intensity")


# --------------------------------------------------------------------------------------------
# Low-level file access


def _read_bytes(path: PathLike) -> bytes:
    """Whole file as bytes; missing or unreadable files become InputError."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "file not found")
    if not p.is_file():
        raise InputError(p, "not a regular file")
    try:
        return p.read_bytes()
    except OSError as e:
        raise InputError(p, f"cannot read file ({e.strerror})") from None


def _read_text(source: PathLike | IO[str]) -> tuple[str, str]:
    """Return ``(text, name)`` of a path or an open text file."""
    if hasattr(source, "read"):
        return source.read(), str(getattr(source, "name", "<stream>"))
    raw = _read_bytes(source)
    try:
        return raw.decode("utf-8"), os.fspath(source)
    except UnicodeDecodeError:
        raise InputError(source, "not a text file (invalid UTF-8)") from None


def write_atomic(path: PathLike, data: bytes | str) -> None:
    """Write ``data`` to ``path`` via a temp file in the same folder and ``os.replace``, so
    readers (and resumed jobs) never see a half-written file. Creates parent folders."""
    p = Path(path)
    if isinstance(data, str):
        data = data.encode("utf-8")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp")
    except OSError as e:
        raise InputError(p, f"cannot write file ({e.strerror})") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        # mkstemp creates 0600 files; outputs should be as readable as any other file.
        os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise InputError(p, f"cannot write file ({e.strerror})") from None
        raise


def write_npz(path: PathLike, **arrays: np.ndarray) -> None:
    """Save arrays as one uncompressed ``.npz``, atomically (see :func:`write_atomic`)."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_atomic(path, buffer.getvalue())


def write_figure(path: PathLike, fig, dpi: int = 110, **savefig_kwargs) -> Path:
    """Save a matplotlib figure as PNG, atomically (see :func:`write_atomic`)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, **savefig_kwargs)
    write_atomic(path, buffer.getvalue())
    return Path(path)


def _parse_rows(text: str, name: str, ncols: int, what: str) -> np.ndarray:
    """Numeric table ``(N, ncols)`` float64 from whitespace-separated lines.

    Blank lines and ``#`` comments are skipped; every reported line number is 1-based in the
    file, so the user can jump straight to it.
    """
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != ncols:
            raise InputError(
                name, f"line {lineno} has {len(fields)} columns, expected {ncols} ({what})"
            )
        try:
            row = [float(v) for v in fields]
        except ValueError:
            raise InputError(name, f"line {lineno} has a non-numeric value") from None
        if not all(map(math.isfinite, row)):
            raise InputError(name, f"line {lineno} has a NaN or infinite value")
        rows.append(row)
    if not rows:
        raise InputError(name, f"file is empty (no {what} lines)")
    return np.array(rows, dtype=np.float64)


def _format_rows(rows: np.ndarray, fmt: str) -> bytes:
    buf = io.StringIO()
    np.savetxt(buf, rows, fmt=fmt, delimiter=" ")
    return buf.getvalue().encode("ascii")


def _as_poses(path: PathLike, poses: np.ndarray) -> np.ndarray:
    """Validate writer input: ``(N, 4, 4)`` or ``(N, 3, 4)``, finite -> float64 ``(N, 3, 4)``."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise InputError(path, f"poses must have shape (N, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise InputError(path, "poses contain NaN or infinite values")
    return poses[:, :3, :]


def _to_homogeneous(top: np.ndarray) -> np.ndarray:
    """(..., 3, 4) -> (..., 4, 4) with bottom row ``[0, 0, 0, 1]``."""
    out = np.zeros(top.shape[:-2] + (4, 4), dtype=np.float64)
    out[..., :3, :] = top
    out[..., 3, 3] = 1.0
    return out


# --------------------------------------------------------------------------------------------
# Pose files


def read_kitti_poses(path_or_file: PathLike | IO[str]) -> np.ndarray:
    """KITTI pose file (12 numbers a line, top 3x4 row-major) -> ``(N, 4, 4)`` float64."""
    text, name = _read_text(path_or_file)
    rows = _parse_rows(text, name, 12, "KITTI pose")
    return _to_homogeneous(rows.reshape(-1, 3, 4))


def write_kitti_poses(path: PathLike, poses: np.ndarray) -> None:
    """Write ``(N, 4, 4)`` poses as a KITTI pose file (readable by ``evo_traj kitti``)."""
    top = _as_poses(path, poses)
    write_atomic(path, _format_rows(top.reshape(-1, 12), _FLOAT_FMT))


def read_tum_poses(path_or_file: PathLike | IO[str]) -> tuple[np.ndarray, np.ndarray]:
    """TUM file (``t x y z qx qy qz qw``) -> ``(times (N,), poses (N, 4, 4))`` float64.

    Quaternions are normalised, since files often hold them rounded to a few digits.
    """
    text, name = _read_text(path_or_file)
    rows = _parse_rows(text, name, 8, "TUM t x y z qx qy qz qw")
    quats = rows[:, 4:]
    norms = np.linalg.norm(quats, axis=1)
    bad = np.flatnonzero(norms < 1e-9)
    if bad.size:
        raise InputError(name, f"pose {bad[0] + 1} has a zero quaternion")
    poses = np.zeros((len(rows), 4, 4), dtype=np.float64)
    poses[:, :3, :3] = Rotation.from_quat(quats / norms[:, None]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    poses[:, 3, 3] = 1.0
    return rows[:, 0].copy(), poses


def write_tum_poses(path: PathLike, times: np.ndarray, poses: np.ndarray) -> None:
    """Write ``times (N,)`` and ``poses (N, 4, 4)`` as a TUM trajectory file."""
    top = _as_poses(path, poses)
    times = np.asarray(times, dtype=np.float64)
    if times.shape != (len(top),):
        raise InputError(path, f"times must have shape ({len(top)},), got {times.shape}")
    if not np.all(np.isfinite(times)):
        raise InputError(path, "times contain NaN or infinite values")
    quats = Rotation.from_matrix(top[:, :, :3]).as_quat(canonical=True)
    rows = np.column_stack([times, top[:, :, 3], quats])
    write_atomic(path, _format_rows(rows, " ".join([_FLOAT_FMT] * 8)))


# --------------------------------------------------------------------------------------------
# KITTI frame conventions


def cam_to_lidar_poses(P_cam: np.ndarray, Tr_cam_velo: np.ndarray) -> np.ndarray:
    """Camera-0 poses ``(..., 4, 4)`` -> LiDAR poses ``inv(Tr) @ P @ Tr`` (float64)."""
    P = np.asarray(P_cam, dtype=np.float64)
    Tr = np.asarray(Tr_cam_velo, dtype=np.float64)
    return np.linalg.inv(Tr) @ P @ Tr


def lidar_to_cam_poses(T_lidar: np.ndarray, Tr_cam_velo: np.ndarray) -> np.ndarray:
    """LiDAR poses ``(..., 4, 4)`` -> camera-0 poses ``Tr @ T @ inv(Tr)`` (float64)."""
    T = np.asarray(T_lidar, dtype=np.float64)
    Tr = np.asarray(Tr_cam_velo, dtype=np.float64)
    return Tr @ T @ np.linalg.inv(Tr)


# --------------------------------------------------------------------------------------------
# Calibration and timestamps


def read_calib(path: PathLike) -> dict[str, np.ndarray]:
    """KITTI ``calib.txt`` (``KEY: v1 v2 ...`` lines) -> ``{key: float64 array}``.

    Keys starting with ``Tr`` become ``(4, 4)`` homogeneous matrices; other entries are shaped
    by their length: 12 -> ``(3, 4)`` (``P0``..``P3``), 9 -> ``(3, 3)``, 16 -> ``(4, 4)``,
    anything else stays 1-D.
    """
    text, name = _read_text(path)
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
                entries[key] = _to_homogeneous(values.reshape(3, 4))
            elif values.size == 16:
                entries[key] = values.reshape(4, 4)
            else:
                raise InputError(
                    name, f"line {lineno} ({key}) has {values.size} columns, expected 12"
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
    text, name = _read_text(path)
    return _parse_rows(text, name, 1, "timestamp")[:, 0]


# --------------------------------------------------------------------------------------------
# Scans


def read_scan(path: PathLike) -> np.ndarray:
    """Point cloud file -> ``(N, 4)`` float32 ``[x, y, z, intensity]``; format by extension.

    ``.bin`` (KITTI float32 x y z i), ``.pcd`` (ascii / binary, any field order and numeric
    type; ``binary_compressed`` is not supported), ``.ply`` (ascii / binary vertex element),
    ``.npy`` (``(N, 3)`` or ``(N, 4+)``). Intensity is zero when the file has none. NaN points
    are kept.
    """
    suffix = Path(path).suffix.lower()
    readers: dict[str, Callable[[PathLike], np.ndarray]] = {
        ".bin": _read_bin,
        ".pcd": _read_pcd,
        ".ply": _read_ply,
        ".npy": _read_npy,
    }
    if suffix not in readers:
        raise InputError(
            path, f"unsupported scan format '{suffix}' (expected .bin, .pcd, .ply or .npy)"
        )
    points = readers[suffix](path)
    if len(points) == 0:
        raise InputError(path, "empty scan (no points)")
    return points


def write_scan_bin(path: PathLike, points: np.ndarray) -> None:
    """Write ``(N, 4)`` (or ``(N, 3)``, zero intensity) points as a KITTI float32 ``.bin``."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] not in (3, 4):
        raise InputError(path, f"points must have shape (N, 4), got {points.shape}")
    if points.shape[1] == 3:
        points = np.column_stack([points, np.zeros(len(points), np.float32)])
    write_atomic(path, np.ascontiguousarray(points, dtype="<f4").tobytes())


def _read_bin(path: PathLike) -> np.ndarray:
    raw = _read_bytes(path)
    if len(raw) % 16:
        raise InputError(
            path, f"file size {len(raw)} bytes is not a multiple of 16 (float32 x y z i)"
        )
    return np.frombuffer(raw, dtype="<f4").reshape(-1, 4).astype(np.float32)


def _assemble(path: PathLike, columns: dict[str, np.ndarray], n: int) -> np.ndarray:
    """Pick x, y, z and intensity out of named 1-D columns -> ``(n, 4)`` float32."""
    missing = [c for c in "xyz" if c not in columns]
    if missing:
        raise InputError(path, f"no {', '.join(missing)} field (fields: {', '.join(columns)})")
    intensity = next((columns[k] for k in _INTENSITY_NAMES if k in columns), np.zeros(n))
    return np.column_stack([columns["x"], columns["y"], columns["z"], intensity]).astype(np.float32)


def _split_header(path: PathLike, raw: bytes, last_key: str) -> tuple[list[list[str]], int]:
    """Header lines (split into words, blank and ``#`` lines dropped) up to and including the
    line whose first word is ``last_key``; also the byte offset where the data starts."""
    lines: list[list[str]] = []
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise InputError(path, f"header has no '{last_key}' line (truncated or not a scan)")
        words = raw[pos:end].decode("ascii", errors="replace").split()
        pos = end + 1
        if not words or words[0].startswith("#"):
            continue
        lines.append(words)
        if words[0].lower() == last_key:
            return lines, pos


def _ascii_table(
    path: PathLike, raw: bytes, data_start: int, skip: int, n: int, ncols: int
) -> np.ndarray:
    """``n`` lines of ``ncols`` numbers after ``skip`` lines of the data starting at byte
    ``data_start`` -> ``(n, ncols)`` float64. Blank lines are ignored."""
    first_line = raw.count(b"\n", 0, data_start) + 1
    text = raw[data_start:].decode("ascii", errors="replace")
    numbered = [
        (lineno, line.split())
        for lineno, line in enumerate(text.splitlines(), start=first_line)
        if line.strip()
    ]
    numbered = numbered[skip : skip + n]
    if len(numbered) < n:
        raise InputError(path, f"truncated: header says {n} points, found {len(numbered)} lines")
    for lineno, fields in numbered:
        if len(fields) != ncols:
            raise InputError(path, f"line {lineno} has {len(fields)} columns, expected {ncols}")
    try:
        return np.array([fields for _, fields in numbered], dtype=np.float64).reshape(n, ncols)
    except ValueError:
        raise InputError(path, "point data has a non-numeric value") from None


def _binary_table(path: PathLike, raw: bytes, offset: int, dtype: np.dtype, n: int) -> np.ndarray:
    available = len(raw) - offset
    if available < n * dtype.itemsize:
        raise InputError(
            path,
            f"truncated: {n} points need {n * dtype.itemsize} bytes of data, found {available}",
        )
    return np.frombuffer(raw, dtype=dtype, count=n, offset=offset)


_PCD_TYPES = {"F": "f", "I": "i", "U": "u"}


def _read_pcd(path: PathLike) -> np.ndarray:
    raw = _read_bytes(path)
    lines, data_start = _split_header(path, raw, "data")
    header = {words[0].upper(): words[1:] for words in lines}
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in header:
            raise InputError(path, f"PCD header has no {key} line")
    names = [f.lower() for f in header["FIELDS"]]
    types = header["TYPE"]
    try:
        sizes = [int(s) for s in header["SIZE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        if "POINTS" in header:
            n = int(header["POINTS"][0])
        else:
            n = int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
    except (ValueError, IndexError, KeyError):
        raise InputError(path, "malformed PCD header (SIZE/COUNT/POINTS/WIDTH/HEIGHT)") from None
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise InputError(path, "PCD header FIELDS, SIZE, TYPE and COUNT differ in length")
    fmt = header["DATA"][0].lower() if header["DATA"] else ""
    if fmt == "binary_compressed":
        raise InputError(
            path,
            "DATA binary_compressed PCD is unsupported; re-save it as binary or ascii "
            "(e.g. pcl_convert_pcd_ascii_binary in.pcd out.pcd 1)",
        )
    if fmt not in ("ascii", "binary"):
        raise InputError(path, f"unknown PCD DATA format '{fmt}'")
    columns: dict[str, np.ndarray] = {}
    if fmt == "binary":
        try:
            # Field names may repeat (PCL pads with "_"), so the record uses positional names.
            dtype = np.dtype(
                [
                    (f"f{k}", f"<{_PCD_TYPES[t.upper()]}{s}", (c,))
                    for k, (t, s, c) in enumerate(zip(types, sizes, counts, strict=True))
                ]
            )
        except (KeyError, TypeError):
            raise InputError(path, f"unsupported PCD TYPE/SIZE {types}/{sizes}") from None
        table = _binary_table(path, raw, data_start, dtype, n)
        for k, name in enumerate(names):
            columns.setdefault(name, table[f"f{k}"][:, 0])
    else:
        table = _ascii_table(path, raw, data_start, 0, n, sum(counts))
        starts = np.cumsum([0] + counts[:-1])
        for name, start in zip(names, starts, strict=True):
            columns.setdefault(name, table[:, start])
    return _assemble(path, columns, n)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">"}


def _read_ply(path: PathLike) -> np.ndarray:
    raw = _read_bytes(path)
    if not raw.startswith(b"ply"):
        raise InputError(path, "not a PLY file (no 'ply' magic line)")
    lines, data_start = _split_header(path, raw, "end_header")
    fmt = next((w[1] for w in lines if w[0] == "format" and len(w) > 1), None)
    if fmt != "ascii" and fmt not in _PLY_ENDIAN:
        raise InputError(path, f"unsupported PLY format '{fmt}'")

    # elements: [name, count, [(property, type) or (property, None) for list properties]]
    elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []
    for words in lines:
        try:
            if words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1][2].append((words[4].lower(), None))
            elif words[0] == "property":
                elements[-1][2].append((words[2].lower(), _PLY_TYPES[words[1]]))
        except (IndexError, ValueError, KeyError):
            raise InputError(path, f"malformed PLY header line '{' '.join(words)}'") from None
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise InputError(path, "PLY file has no vertex element")
    iv = names.index("vertex")
    _, n, props = elements[iv]
    # List properties have no fixed size, so data before or inside the vertices cannot be skipped.
    if any(t is None for e in elements[: iv + 1] for _, t in e[2]):
        raise InputError(
            path, "PLY list properties before or in the vertex element are unsupported"
        )

    columns: dict[str, np.ndarray] = {}
    if fmt == "ascii":
        skip = sum(e[1] for e in elements[:iv])
        table = _ascii_table(path, raw, data_start, skip, n, len(props))
        for k, (name, _) in enumerate(props):
            columns.setdefault(name, table[:, k])
    else:
        endian = _PLY_ENDIAN[fmt]
        skip = sum(e[1] * sum(np.dtype(t).itemsize for _, t in e[2]) for e in elements[:iv])
        dtype = np.dtype([(f"f{k}", f"{endian}{t}") for k, (_, t) in enumerate(props)])
        record = _binary_table(path, raw, data_start + skip, dtype, n)
        for k, (name, _) in enumerate(props):
            columns.setdefault(name, record[f"f{k}"])
    return _assemble(path, columns, n)


def _load_npy(path: PathLike) -> np.ndarray:
    try:
        array = np.load(io.BytesIO(_read_bytes(path)), allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise InputError(path, f"not a valid .npy file ({e})") from None
    if not isinstance(array, np.ndarray):  # np.load also opens .npz archives
        raise InputError(path, "not a valid .npy file (it is an .npz archive)")
    return array


def _read_npy(path: PathLike) -> np.ndarray:
    array = _load_npy(path)
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "fiu":
        raise InputError(
            path,
            f"expected a numeric (N, 3) or (N, 4+) array, got shape {array.shape} "
            f"dtype {array.dtype}",
        )
    if array.shape[1] == 3:
        return np.column_stack([array, np.zeros(len(array))]).astype(np.float32)
    return array[:, :4].astype(np.float32)


# --------------------------------------------------------------------------------------------
# SemanticKITTI labels


def read_labels(path: PathLike, expected_count: int | None = None) -> np.ndarray:
    """SemanticKITTI ``.label`` -> ``(N,)`` uint16 class ids (low 16 bits of each uint32)."""
    raw = _read_bytes(path)
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


# --------------------------------------------------------------------------------------------
# KITTI odometry dataset layout


def _read_only(a: np.ndarray) -> np.ndarray:
    # Cached arrays are shared between callers; freezing them stops one caller corrupting another.
    a.setflags(write=False)
    return a


class KittiSequence:
    """One sequence of the KITTI odometry layout under ``root``.

    ``root/sequences/NN/{velodyne/%06d.bin, calib.txt, times.txt}`` are required;
    ``root/poses/NN.txt``, ``sequences/NN/labels/%06d.label`` and per-point relative
    timestamps ``sequences/NN/timestamps/%06d.npy`` (float32 seconds) are optional. Frames
    are the sorted ``.bin`` files. Everything but the scans is read and checked on
    construction.
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

        calib_path = self.sequence_dir / "calib.txt"
        calib = read_calib(calib_path)
        if "Tr" not in calib:
            raise InputError(calib_path, "no 'Tr' (Velodyne to camera 0) entry")
        self._Tr = _read_only(calib["Tr"])

        times_path = self.sequence_dir / "times.txt"
        self._times = _read_only(read_times(times_path))
        if len(self._times) != n:
            raise InputError(
                times_path, f"{len(self._times)} timestamps but {n} scans in {velodyne}"
            )

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

    def point_times(self, i: int) -> np.ndarray | None:
        """Frame ``i``'s ``(N,)`` float32 per-point times (seconds, relative), or None."""
        path = self.sequence_dir / "timestamps" / f"{self._scan_paths[i].stem}.npy"
        if not path.exists():
            return None
        times = _load_npy(path)
        n = self._point_count(i)
        if times.shape != (n,) or times.dtype.kind not in "fiu":
            raise InputError(
                path, f"expected {n} numeric point times, got shape {times.shape} {times.dtype}"
            )
        return times.astype(np.float32)

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
