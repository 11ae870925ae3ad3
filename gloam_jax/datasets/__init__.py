"""Datasets: where scans, their times and (optionally) ground truth come from.

A loader turns a path into a :class:`Dataset`; loaders register by name with
:func:`register`, and :func:`open_dataset` picks the first whose ``detect`` accepts the path
(or the one named). Three ship: ``kitti`` (the KITTI odometry layout, a root with
``--sequence``), ``folder`` (any folder of ``.bin``/``.pcd``/``.ply``/``.npy`` scans) and
``rosbag`` (ROS 1 and ROS 2 bags and MCAP files, with ``--topic``).
A new format plugs in by registering a loader; the pipeline sees only the interface.
"""

# The shipped loaders register themselves on import, in this order (each imports the registry
# from datasets.base, so nothing here imports back into this package's __init__).
from gloam_jax.datasets import folder, kitti, rosbag  # noqa: F401
from gloam_jax.datasets.base import LOADERS, Dataset, Loader, open_dataset, register

__all__ = ["LOADERS", "Dataset", "Loader", "open_dataset", "register"]
