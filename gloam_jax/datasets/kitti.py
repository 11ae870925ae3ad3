"""The KITTI odometry layout: ``ROOT/sequences/NN/velodyne/*.bin`` with ``--sequence NN``.

Also accepted: the sequence folder itself (``ROOT/sequences/NN``). ``calib.txt``,
``times.txt``, ``poses/NN.txt`` and per-point ``timestamps/`` are optional (see
:class:`gloam_jax.io.KittiSequence`). KITTI's raw HDL-64E scans are motion-distorted, so the
``auto`` deskew policy takes times from the azimuth when the sequence has none.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gloam_jax.datasets.base import Dataset, register
from gloam_jax.errors import InputError
from gloam_jax.io import KittiSequence


def _is_kitti(path: Path) -> bool:
    return (path / "sequences").is_dir() or (
        path.parent.name == "sequences" and (path / "velodyne").is_dir()
    )


@register("kitti", _is_kitti)
class KittiDataset(Dataset):
    kind = "kitti"
    distorted = True

    def __init__(self, path: Path, sequence: str | None) -> None:
        path = Path(path)
        if not (path / "sequences").is_dir() and (path / "velodyne").is_dir():
            if sequence is not None and sequence != path.name:
                raise InputError(path, f"is sequence {path.name}, not --sequence {sequence}")
            path, sequence = path.parent.parent, path.name
        if sequence is None:
            found = sorted(p.name for p in (path / "sequences").iterdir() if p.is_dir())
            if len(found) != 1:
                raise InputError(
                    path, f"name a sequence with --sequence (found: {', '.join(found)})"
                )
            sequence = found[0]
        self.sequence = KittiSequence(path, sequence)
        self.name = self.sequence.sequence
        self.defaults = list(self.sequence.defaults)

    def __len__(self) -> int:
        return len(self.sequence)

    def __repr__(self) -> str:
        return repr(self.sequence)

    def scan_path(self, i: int) -> Path:
        return self.sequence.scan_path(i)

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        return self.sequence.scan(i), self.sequence.point_times(i)

    def labels(self, i: int) -> np.ndarray | None:
        return self.sequence.labels(i)

    @property
    def has_point_times(self) -> bool:
        return self.sequence.has_point_times

    @property
    def times(self) -> np.ndarray:
        return self.sequence.times

    @property
    def Tr_cam_velo(self) -> np.ndarray:
        return self.sequence.Tr_cam_velo

    @property
    def gt_poses_cam(self) -> np.ndarray | None:
        return self.sequence.gt_poses_cam

    def check(self, frames: range) -> None:
        self.sequence.check(frames)
