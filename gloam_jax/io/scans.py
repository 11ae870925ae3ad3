"""Point cloud files: ``.bin`` (KITTI), ``.pcd``, ``.ply`` and ``.npy`` scans.

A scan is a float32 ``(N, 4)`` array ``[x, y, z, intensity]`` in the sensor frame, metres.
Points with NaN coordinates are returned as they are, not an error: later stages drop and count
them. A KITTI ``.bin`` holds the points as little-endian float32 ``x y z i`` records.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from gloam_jax.errors import InputError
from gloam_jax.io.files import PathLike, load_npy, read_bytes, write_atomic

__all__ = ["read_scan", "write_scan_bin"]

# Field names taken as intensity, in order of preference (PCL, PLY exporters, SemanticKITTI).
_INTENSITY_NAMES = ("intensity", "i", "reflectance", "remission", "scalar_intensity")


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
    raw = read_bytes(path)
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
    raw = read_bytes(path)
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
    raw = read_bytes(path)
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


def _read_npy(path: PathLike) -> np.ndarray:
    array = load_npy(path)
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "fiu":
        raise InputError(
            path,
            f"expected a numeric (N, 3) or (N, 4+) array, got shape {array.shape} "
            f"dtype {array.dtype}",
        )
    if array.shape[1] == 3:
        return np.column_stack([array, np.zeros(len(array))]).astype(np.float32)
    return array[:, :4].astype(np.float32)
