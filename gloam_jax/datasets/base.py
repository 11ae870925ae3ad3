"""The loader interface and registry: :class:`Dataset`, :func:`register`, :func:`open_dataset`
(re-exported by :mod:`gloam_jax.datasets`, which also imports the shipped loaders)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gloam_jax.errors import InputError


class Dataset:
    """What the pipeline reads. Subclasses set the attributes and implement the methods."""

    name: str  # prefix of the result files (``NN_poses_kitti.txt``)
    kind: str  # the loader's name
    distorted: bool  # raw scans known to be motion-distorted (auto deskew uses the azimuth)
    defaults: list[str]  # each default taken for a missing file, said once in the run summary
    # what the loader found (a recording's topic, message count, point fields), said once in
    # the run summary and kept in metrics.json
    details: dict[str, object] = {}

    def __len__(self) -> int:
        raise NotImplementedError

    def scan_path(self, i: int) -> Path:
        raise NotImplementedError

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Scan ``i`` ``(N, 4)`` float32 and its per-point times ``(N,)`` as stored, or None."""
        raise NotImplementedError

    def labels(self, i: int) -> np.ndarray | None:
        """Scan ``i``'s SemanticKITTI class ids ``(N,)``, or None where the data has none."""
        return None

    @property
    def has_point_times(self) -> bool:
        raise NotImplementedError

    @property
    def times(self) -> np.ndarray:
        """Scan timestamps (N,) s."""
        raise NotImplementedError

    @property
    def Tr_cam_velo(self) -> np.ndarray:
        """LiDAR-to-camera-0 extrinsic (4, 4); the identity without calibration."""
        raise NotImplementedError

    @property
    def gt_poses_cam(self) -> np.ndarray | None:
        """Ground truth (N, 4, 4) in the frame of ``Tr_cam_velo``, or None."""
        raise NotImplementedError

    def check(self, frames: range) -> None:
        """Cheap checks of the scans of ``frames`` (sizes, headers) before any is computed."""
        raise NotImplementedError


@dataclass(frozen=True)
class Loader:
    name: str
    detect: Callable[[Path], bool]  # does this path look like the loader's data?
    open: Callable[..., Dataset]  # (path, sequence or None, **options) -> dataset
    options: tuple[str, ...] = ()  # keyword options it takes (a recording's topic)


LOADERS: dict[str, Loader] = {}


def register(name: str, detect: Callable[[Path], bool], options: tuple[str, ...] = ()):
    """Class decorator: ``cls(path, sequence, **options)`` opens the data that
    ``detect(path)`` accepts. Loaders are tried in the order they registered."""

    def wrap(cls):
        LOADERS[name] = Loader(name, detect, cls, options)
        return cls

    return wrap


def open_dataset(
    path: str | Path, sequence: str | None = None, kind: str | None = None, **options
) -> Dataset:
    """The dataset at ``path``: by the loader named ``kind``, or the first that recognises it.
    ``options`` not None (``topic``) go to a loader that takes them, and are an error for
    another."""
    path = Path(path)
    if kind is not None:
        if kind not in LOADERS:
            raise InputError(None, f"unknown dataset kind '{kind}' (one of {', '.join(LOADERS)})")
        loader = LOADERS[kind]
    else:
        if not path.exists():
            raise InputError(path, "not found")
        loader = next((lo for lo in LOADERS.values() if lo.detect(path)), None)
        if loader is None:
            raise InputError(
                path,
                "neither a KITTI root (sequences/), a folder of .bin, .pcd, .ply or .npy scans, "
                "nor a ROS bag, ROS 2 bag folder or MCAP file",
            )
    given = {name: value for name, value in options.items() if value is not None}
    wrong = [name for name in given if name not in loader.options]
    if wrong:
        raise InputError(path, f"--{wrong[0]} does not apply to {loader.name} data")
    return loader.open(path, sequence, **given)
