"""Point cloud files: ``.bin`` (KITTI), ``.pcd``, ``.ply`` and ``.npy`` scans.

A scan is a float32 ``(N, 4)`` array ``[x, y, z, intensity]`` in the sensor frame, metres.
Points with NaN coordinates are returned as they are, not an error: later stages drop and count
them. A KITTI ``.bin`` holds the points as little-endian float32 ``x y z i`` records. PCD and PLY
files may carry per-point times in a field named ``t``, ``time``, ``timestamp``,
``time_offset`` or ``offset_time`` (any unit or origin: see :mod:`gloam_jax.preprocess`).
PCD's ``binary_compressed`` data is LZF-compressed, one field after another (PCL's layout);
liblzf itself (``python-neo-lzf``) packs and unpacks it. PLY files are read by ``plyfile``.

PCD is parsed here, not by ``pypcd4``: pypcd4 1.5 reads a binary file cut short as fewer points
without a word (a 50-point file missing one point's bytes came back as 49 points), stops
reading a header after 10 lines, gives PCL's repeated ``_`` padding fields random names and
needs pydantic; this parser is short, checks every size against the header, and is fuzzed
(tests/test_fuzz.py).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import lzf
import numpy as np
import plyfile

from gloam_jax.errors import InputError
from gloam_jax.io.files import PathLike, load_npy, read_bytes, write_atomic

__all__ = [
    "SCAN_SUFFIXES",
    "check_scan",
    "has_time_field",
    "read_scan",
    "scan_from_columns",
    "read_scan_with_times",
    "write_scan_bin",
    "write_scan_pcd",
]

SCAN_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")

# Field names taken as intensity, in order of preference (PCL, PLY exporters, SemanticKITTI).
_INTENSITY_NAMES = ("intensity", "i", "reflectance", "remission", "scalar_intensity")
# Field names taken as per-point time, in order of preference (Ouster "t" in ns, Velodyne "time"
# in s, Hesai and Robosense "timestamp" in absolute s, Livox "offset_time" in ns).
TIME_NAMES = ("t", "time", "timestamp", "time_offset", "offset_time", "timestamps")


def read_scan(path: PathLike) -> np.ndarray:
    """Point cloud file -> ``(N, 4)`` float32 ``[x, y, z, intensity]``; format by extension.

    ``.bin`` (KITTI float32 x y z i), ``.pcd`` (ascii / binary / binary_compressed, any field
    order and numeric type), ``.ply`` (the vertex element of any PLY), ``.npy`` (``(N, 3)`` or
    ``(N, 4+)``). Intensity is zero when the file has none. NaN points are kept.
    """
    return read_scan_with_times(path)[0]


def read_scan_with_times(path: PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`read_scan` and the file's per-point times ``(N,)`` as stored (float64, or int64
    for integer fields), or None when it has no time field (``.bin`` and ``.npy`` never do)."""
    suffix = Path(path).suffix.lower()
    readers: dict[str, Callable[[PathLike], dict[str, np.ndarray]]] = {
        ".bin": _read_bin,
        ".pcd": _read_pcd,
        ".ply": _read_ply,
        ".npy": _read_npy,
    }
    if suffix not in readers:
        raise InputError(
            path, f"unsupported scan format '{suffix}' (expected .bin, .pcd, .ply or .npy)"
        )
    return scan_from_columns(readers[suffix](path), path)


def scan_from_columns(
    columns: dict[str, np.ndarray], source: PathLike | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Named 1-D point columns (any file's or message's fields, names lower case) -> the scan
    ``(N, 4)`` float32 ``[x, y, z, intensity]`` and its per-point times ``(N,)`` as stored
    (int64 for integer fields, else float64), or None without a time field."""
    points = _assemble(source, columns)
    if len(points) == 0:
        raise InputError(source, "empty scan (no points)")
    times = next((columns[k] for k in TIME_NAMES if k in columns), None)
    if times is not None:
        times = times.astype(np.int64 if times.dtype.kind in "iu" else np.float64)
    return points, times


def check_scan(path: PathLike) -> None:
    """Cheap checks of a scan file before any frame is computed: it exists and is not empty,
    a ``.bin``'s size is a multiple of 16, a ``.pcd``/``.ply``/``.npy`` header parses and its
    binary data is as long as the header says. The points themselves are not read."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SCAN_SUFFIXES:
        raise InputError(
            path, f"unsupported scan format '{suffix}' (expected .bin, .pcd, .ply or .npy)"
        )
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except OSError as err:
        raise InputError(path, f"cannot be read ({err.strerror})") from None
    if size == 0:
        raise InputError(path, "empty file")
    if suffix == ".bin":
        if size % 16:
            raise InputError(
                path, f"file size {size} bytes is not a multiple of 16 (float32 x y z i)"
            )
    elif suffix == ".npy":
        load_npy_header(path, head)
    elif suffix == ".pcd":
        if b"\nDATA" not in head and not head.startswith(b"DATA"):
            head = read_bytes(path)  # a header longer than 64 KiB
        names, dtype, n, fmt, start = _pcd_header(path, head)
        if fmt == "binary" and size < start + n * dtype.itemsize:
            raise InputError(
                path, f"truncated: {n} points need {n * dtype.itemsize} bytes of data, "
                f"found {size - start}"
            )  # fmt: skip
        if fmt == "binary_compressed":
            if len(head) < start + 8:
                raise InputError(path, "truncated: binary_compressed PCD without its size words")
            packed, unpacked = np.frombuffer(head, "<u4", count=2, offset=start).tolist()
            if unpacked != n * dtype.itemsize or size < start + 8 + packed:
                raise InputError(path, "truncated or inconsistent binary_compressed data")
    elif suffix == ".ply":
        if not head.startswith(b"ply"):
            raise InputError(path, "not a PLY file (no 'ply' magic line)")
        _split_header(path, head if b"end_header" in head else read_bytes(path), "end_header")


def has_time_field(path: PathLike) -> bool:
    """Whether a scan file carries per-point times: a PCD or PLY header naming a time field
    (``t``, ``time``, ``timestamp``, ...); ``.bin`` and ``.npy`` scans never do."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".pcd", ".ply"):
        return False
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if suffix == ".pcd":
        names = _pcd_header(path, head if b"DATA" in head else read_bytes(path))[0]
    else:
        lines, _ = _split_header(
            path, head if b"end_header" in head else read_bytes(path), "end_header"
        )
        names = [w[-1].lower() for w in lines if w[0] == "property"]
    return any(name in TIME_NAMES for name in names)


def load_npy_header(path: PathLike, head: bytes) -> None:
    """Check an ``.npy`` file's header: a numeric (N, 3) or (N, 4+) array."""
    import io as _io

    try:
        stream = _io.BytesIO(head)
        version = np.lib.format.read_magic(stream)
        read = {(1, 0): np.lib.format.read_array_header_1_0}.get(
            version, np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read(stream)
    except (ValueError, OSError, SyntaxError):
        raise InputError(path, "not a valid .npy file (header unreadable)") from None
    if len(shape) != 2 or shape[1] < 3 or dtype.kind not in "fiu":
        raise InputError(
            path, f"expected a numeric (N, 3) or (N, 4+) array, got shape {shape} dtype {dtype}"
        )


def write_scan_bin(path: PathLike, points: np.ndarray) -> None:
    """Write ``(N, 4)`` (or ``(N, 3)``, zero intensity) points as a KITTI float32 ``.bin``."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] not in (3, 4):
        raise InputError(path, f"points must have shape (N, 4), got {points.shape}")
    if points.shape[1] == 3:
        points = np.column_stack([points, np.zeros(len(points), np.float32)])
    write_atomic(path, np.ascontiguousarray(points, dtype="<f4").tobytes())


def _read_bin(path: PathLike) -> np.ndarray:
    raw = read_bytes(path)
    if len(raw) % 16:
        raise InputError(
            path, f"file size {len(raw)} bytes is not a multiple of 16 (float32 x y z i)"
        )
    table = np.frombuffer(raw, dtype="<f4").reshape(-1, 4)
    return dict(zip(("x", "y", "z", "intensity"), table.T, strict=True))


def _assemble(path: PathLike | None, columns: dict[str, np.ndarray]) -> np.ndarray:
    """Pick x, y, z and intensity out of named 1-D columns -> ``(n, 4)`` float32."""
    missing = [c for c in "xyz" if c not in columns]
    if missing:
        raise InputError(path, f"no {', '.join(missing)} field (fields: {', '.join(columns)})")
    n = len(columns["x"])
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


def _ascii_table(path: PathLike, raw: bytes, data_start: int, n: int, ncols: int) -> np.ndarray:
    """The first ``n`` lines of ``ncols`` numbers of the data starting at byte ``data_start``
    -> ``(n, ncols)`` float64. Blank lines are ignored."""
    first_line = raw.count(b"\n", 0, data_start) + 1
    text = raw[data_start:].decode("ascii", errors="replace")
    numbered = [
        (lineno, line.split())
        for lineno, line in enumerate(text.splitlines(), start=first_line)
        if line.strip()
    ]
    numbered = numbered[:n]
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


def _pcd_header(path: PathLike, raw: bytes) -> tuple[list[str], np.dtype, int, str, int]:
    """A PCD header -> (field names, one point's record type, points, DATA format, data
    offset). Checks the header only, not the data."""
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
    if fmt not in ("ascii", "binary", "binary_compressed"):
        raise InputError(path, f"unknown PCD DATA format '{fmt}'")
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
    return names, dtype, n, fmt, data_start


def _read_pcd(path: PathLike) -> dict[str, np.ndarray]:
    raw = read_bytes(path)
    names, dtype, n, fmt, data_start = _pcd_header(path, raw)
    columns: dict[str, np.ndarray] = {}
    if fmt == "binary":
        table = _binary_table(path, raw, data_start, dtype, n)
        for k, name in enumerate(names):
            columns.setdefault(name, table[f"f{k}"][:, 0])
    elif fmt == "binary_compressed":
        data = _pcd_decompress(path, raw, data_start, n * dtype.itemsize)
        # PCL stores each field's values together (all x, then all y, ...).
        offset = 0
        for k, name in enumerate(names):
            field = dtype[f"f{k}"]
            values = np.frombuffer(data, field.base, count=n * field.shape[0], offset=offset)
            offset += n * field.itemsize
            columns.setdefault(name, values.reshape(n, -1)[:, 0])
    else:
        counts = [dtype[f"f{k}"].shape[0] for k in range(len(names))]
        table = _ascii_table(path, raw, data_start, n, sum(counts))
        starts = np.cumsum([0] + counts[:-1])
        for name, start in zip(names, starts, strict=True):
            columns.setdefault(name, table[:, start])
    return columns


def _pcd_decompress(path: PathLike, raw: bytes, start: int, expected: int) -> bytes:
    """The data of a binary_compressed PCD: two uint32 sizes (compressed, uncompressed), then
    the LZF stream."""
    if len(raw) < start + 8:
        raise InputError(path, "truncated: binary_compressed PCD without its size words")
    packed, unpacked = np.frombuffer(raw, "<u4", count=2, offset=start).tolist()
    if unpacked != expected:
        raise InputError(
            path,
            f"compressed data unpacks to {unpacked} bytes, the header's points need {expected}",
        )
    if len(raw) < start + 8 + packed:
        raise InputError(
            path, f"truncated: {packed} bytes of compressed data, found {len(raw) - start - 8}"
        )
    try:
        data = lzf.decompress(raw[start + 8 : start + 8 + packed], unpacked) if unpacked else b""
    except ValueError:  # liblzf's "error in compressed data": a reference out of bounds
        data = None
    if data is None or len(data) != unpacked:  # None: the data unpacks to more than that
        raise InputError(path, f"corrupt LZF data (does not unpack to {unpacked} bytes)")
    return data


def write_scan_pcd(path: PathLike, points: np.ndarray, data: str = "binary",
                   times: np.ndarray | None = None) -> None:  # fmt: skip
    """Write ``(N, 4)`` float32 points (and optional float64 per-point ``times``, field ``t``)
    as a PCD v0.7 file, ``data`` ``binary``, ``binary_compressed`` or ``ascii``."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 4:
        raise InputError(path, f"points must have shape (N, 4), got {points.shape}")
    n = len(points)
    fields = [("x", "F", 4), ("y", "F", 4), ("z", "F", 4), ("intensity", "F", 4)]
    columns = [points[:, k] for k in range(4)]
    if times is not None:
        fields.append(("t", "F", 8))
        columns.append(np.asarray(times, np.float64))
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(f[0] for f in fields)}\nSIZE {' '.join(str(f[2]) for f in fields)}\n"
        f"TYPE {' '.join(f[1] for f in fields)}\nCOUNT {' '.join('1' for _ in fields)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode("ascii")
    if data == "ascii":
        body = "".join(
            " ".join(repr(float(v)) for v in row) + "\n" for row in zip(*columns, strict=True)
        )
        payload = body.encode("ascii")
    elif data == "binary":
        dtype = np.dtype([(f[0], f"<f{f[2]}") for f in fields])
        record = np.empty(n, dtype)
        for (name, _, _), column in zip(fields, columns, strict=True):
            record[name] = column
        payload = record.tobytes()
    elif data == "binary_compressed":
        raw = b"".join(np.ascontiguousarray(c, f"<f{f[2]}").tobytes()
                       for f, c in zip(fields, columns, strict=True))  # fmt: skip
        # liblzf's worst case: one control byte per 32 literal bytes, plus one.
        packed = lzf.compress(raw, len(raw) + len(raw) // 32 + 1) if raw else b""
        payload = np.array([len(packed), len(raw)], "<u4").tobytes() + packed
    else:
        raise InputError(path, f"unknown PCD DATA format '{data}'")
    write_atomic(path, header + payload)


def _read_ply(path: PathLike) -> dict[str, np.ndarray]:
    """The vertex element's scalar properties, by plyfile (ascii or binary, either byte order;
    other elements and list properties anywhere are read past)."""
    try:
        ply = plyfile.PlyData.read(os.fspath(path))
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except (plyfile.PlyParseError, ValueError, UnicodeDecodeError) as err:
        raise InputError(path, f"not a readable PLY file ({' '.join(str(err).split())})") from None
    except MemoryError:  # plyfile allocates an ascii element's rows before reading them
        raise InputError(path, "PLY header counts more elements than the file can hold") from None
    if "vertex" not in ply:
        raise InputError(path, "PLY file has no vertex element")
    vertex = ply["vertex"].data
    return {
        name.lower(): vertex[name] for name in vertex.dtype.names if vertex[name].dtype != object
    }


def _read_npy(path: PathLike) -> dict[str, np.ndarray]:
    array = load_npy(path)
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "fiu":
        raise InputError(
            path,
            f"expected a numeric (N, 3) or (N, 4+) array, got shape {array.shape} "
            f"dtype {array.dtype}",
        )
    return dict(zip(("x", "y", "z", "intensity"), array[:, :4].T, strict=False))
