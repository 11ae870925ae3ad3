"""Atomic file writes and the low-level reads that every reader in :mod:`gloam_jax.io` shares.

* Bad input raises :class:`~gloam_jax.errors.InputError` (``"<file>: <problem>"``), never a
  raw NumPy or OS error.
* Writers create parent folders and replace the target atomically (temp file in the same folder,
  then ``os.replace``), so a crash never leaves half a file.
* Text tables are whitespace-separated numbers, one row a line; blank lines and ``#`` comments
  are skipped, and reported line numbers are 1-based in the file.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import tempfile
from pathlib import Path
from typing import IO

import numpy as np

from gloam_jax.errors import InputError

__all__ = [
    "PathLike",
    "load_npy",
    "parse_rows",
    "read_bytes",
    "read_text",
    "write_atomic",
    "write_figure",
    "write_npz",
]

PathLike = str | os.PathLike[str]


def read_bytes(path: PathLike) -> bytes:
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


def read_text(source: PathLike | IO[str]) -> tuple[str, str]:
    """Return ``(text, name)`` of a path or an open text file."""
    if hasattr(source, "read"):
        return source.read(), str(getattr(source, "name", "<stream>"))
    raw = read_bytes(source)
    try:
        return raw.decode("utf-8"), os.fspath(source)
    except UnicodeDecodeError:
        raise InputError(source, "not a text file (invalid UTF-8)") from None


def parse_rows(text: str, name: str, ncols: int, what: str) -> np.ndarray:
    """Numeric table ``(N, ncols)`` float64 from the lines of ``text`` (the file ``name``).

    ``what`` names a row in messages (``"KITTI pose"``); an empty table is an error.
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


def load_npy(path: PathLike) -> np.ndarray:
    """The array of an ``.npy`` file (no pickles); anything else is an InputError."""
    data = read_bytes(path)
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except Exception as e:  # a damaged header fails in many ways (tokenize, syntax, ...)
        raise InputError(path, f"not a valid .npy file ({type(e).__name__}: {e})") from None
    if not isinstance(array, np.ndarray):  # np.load also opens .npz archives
        raise InputError(path, "not a valid .npy file (it is an .npz archive)")
    return array


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
