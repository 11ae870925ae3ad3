"""Any folder of scans, as KISS-ICP's generic loader: ``.bin``, ``.pcd``, ``.ply`` or ``.npy``
files sorted by name (numbers in names compared as numbers: ``2.pcd`` before ``10.pcd``).

Optional files beside the scans: ``calib.txt`` (its ``Tr``: LiDAR to the frame of the ground
truth; without it, the LiDAR frame), ``times.txt`` (one time a scan, s; without it, 10 Hz),
``poses.txt`` (ground truth, KITTI format; without it, no scoring; a missing file number is a
gap in time) and per-point times, as a
PCD/PLY time field (``t``, ``time``, ``timestamp``, ...) or ``timestamps/<scan name>.npy``.
Each default taken is listed in ``defaults``. Scans are not assumed motion-distorted: the
``auto`` deskew policy deskews only with per-point times.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gloam_jax.datasets.base import Dataset, register
from gloam_jax.errors import InputError
from gloam_jax.io import read_calib, read_kitti_poses, read_times
from gloam_jax.io.files import load_npy
from gloam_jax.io.kitti import default_times
from gloam_jax.io.scans import SCAN_SUFFIXES, check_scan, has_time_field, read_scan_with_times


def _natural(path: Path) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def _scans(path: Path) -> list[Path]:
    return [p for p in path.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES]


@register("folder", lambda path: path.is_dir() and bool(_scans(path)))
class FolderDataset(Dataset):
    kind = "folder"
    distorted = False

    def __init__(self, path: Path, sequence: str | None = None) -> None:
        path = Path(path)
        if not path.is_dir():
            raise InputError(path, "not a folder of scans")
        scans = sorted(_scans(path), key=_natural)
        if not scans:
            raise InputError(path, "no .bin, .pcd, .ply or .npy scans")
        suffixes = sorted({p.suffix.lower() for p in scans})
        if len(suffixes) > 1:
            counts = ", ".join(
                f"{s}: {sum(p.suffix.lower() == s for p in scans)}" for s in suffixes
            )
            raise InputError(path, f"scans of several formats ({counts}); keep one per folder")
        self.folder, self._paths = path, scans
        self.name = sequence or path.resolve().name
        self.defaults: list[str] = []
        n = len(scans)
        calib = path / "calib.txt"
        if calib.exists():
            entries = read_calib(calib)
            if "Tr" not in entries:
                raise InputError(calib, "no 'Tr' (LiDAR to ground-truth frame) entry")
            self._Tr = entries["Tr"]
        else:
            self._Tr = np.eye(4)
            self.defaults.append("no calib.txt: poses in the LiDAR frame")
        times = path / "times.txt"
        if times.exists():
            self._times = read_times(times)
            if len(self._times) != n:
                raise InputError(times, f"{len(self._times)} timestamps but {n} scans")
        else:
            self._times, note = default_times(scans)
            self.defaults.append(note)
        poses = path / "poses.txt"
        self._gt = None
        if poses.exists():
            self._gt = read_kitti_poses(poses)
            if len(self._gt) != n:
                raise InputError(poses, f"{len(self._gt)} poses but {n} scans")
        else:
            self.defaults.append("no poses.txt: no ground truth, not scored")
        self._time_files = (path / "timestamps").is_dir()
        self._time_field = has_time_field(scans[0])

    def __len__(self) -> int:
        return len(self._paths)

    def __repr__(self) -> str:
        return f"FolderDataset({str(self.folder)!r}, frames={len(self)})"

    def scan_path(self, i: int) -> Path:
        return self._paths[i]

    def _times_path(self, i: int) -> Path:
        return self.folder / "timestamps" / f"{self._paths[i].stem}.npy"

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        scan, times = read_scan_with_times(self._paths[i])
        if self._time_files:
            path = self._times_path(i)
            times = load_npy(path)
            if times.shape != (len(scan),) or times.dtype.kind not in "fiu":
                raise InputError(
                    path, f"expected {len(scan)} point times, got shape {times.shape} {times.dtype}"
                )
        return scan, times

    @property
    def has_point_times(self) -> bool:
        return self._time_files or self._time_field

    @property
    def times(self) -> np.ndarray:
        return self._times

    @property
    def Tr_cam_velo(self) -> np.ndarray:
        return self._Tr

    @property
    def gt_poses_cam(self) -> np.ndarray | None:
        return self._gt

    def check(self, frames: range) -> None:
        for i in frames:
            check_scan(self._paths[i])
            if self._time_files and not self._times_path(i).exists():
                raise InputError(self._times_path(i), "missing: the other scans have point times")
