"""Precomputed backbone: per-scan feature files written by any external network.

For a scan ``.../000123.bin`` (or frame 123) the folder must hold ``000123.npy`` or
``000123.txt``: an (N, D) array, row-aligned with the scan's N points.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from gloam_jax.errors import InputError


class PrecomputedBackbone:
    """Features read from ``folder/<scan name>.npy`` (or ``.txt``): (N, D) float32."""

    name = "precomputed"

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)

    def options(self) -> dict[str, Any]:
        """Keyword arguments that rebuild this backbone (JSON-serialisable)."""
        return {"folder": str(self.folder)}

    def file_for(
        self, path: str | os.PathLike[str] | None = None, frame: int | None = None
    ) -> Path:
        """The feature file of a scan, by the scan's file name or else its frame index."""
        if path is not None:
            stem = Path(path).stem
        elif frame is not None:
            stem = f"{int(frame):06d}"
        else:
            raise InputError(self.folder, "a precomputed feature file needs the scan path or frame")
        npy = self.folder / f"{stem}.npy"
        txt = self.folder / f"{stem}.txt"
        if npy.is_file():
            return npy
        if txt.is_file():
            return txt
        raise InputError(npy, f"feature file not found (nor {txt.name})")

    def __call__(
        self,
        scan: np.ndarray,
        *,
        path: str | os.PathLike[str] | None = None,
        frame: int | None = None,
    ) -> np.ndarray:
        """Features (N, D) float32 of a raw scan (N, 3+), read from its file."""
        file = self.file_for(path, frame)
        try:
            if file.suffix == ".npy":
                features = np.load(file, allow_pickle=False)
            else:
                features = np.loadtxt(file, dtype=np.float64, ndmin=2)
        except (OSError, ValueError, EOFError) as e:
            raise InputError(file, f"cannot read features ({e})") from None
        if features.ndim != 2:
            raise InputError(file, f"expected an (N, D) feature array, got shape {features.shape}")
        if features.dtype.kind not in "fiu":
            raise InputError(file, f"features must be numeric, got dtype {features.dtype}")
        if len(features) != len(scan):
            raise InputError(
                file, f"has {len(features)} feature rows but the scan has {len(scan)} points"
            )
        if not np.all(np.isfinite(features)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(features), axis=1))[0])
            raise InputError(file, f"features contain NaN or infinite values (first in row {bad})")
        return features.astype(np.float32)
