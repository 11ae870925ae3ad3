"""Scenes that constrain a registration only in part, for calibrating degeneracy detection.

Each is laid along a straight drive on flat ground (+x, the LiDAR ``mount_height`` above it):

* ``tunnel``: two walls 10 m apart and a ceiling 6 m up; its axis is unconstrained.
* ``corridor``: two walls 5 m apart and 8 m high, open above: the same axis, less of a roof.
* ``barriers``: a bare highway between noise barriers 3 m high, 24 m apart.
* ``plane``: the ground alone: only height, roll and pitch are constrained.

They are deliberately featureless (no poles, no cars, no recesses): the hard limit that a real
tunnel only approaches.
"""

from __future__ import annotations

import numpy as np

from gloam_jax.errors import InputError
from gloam_jax.simulate.trajectory import Trajectory, default_Tr_cam_velo
from gloam_jax.simulate.world import (
    BUILDING,
    FENCE,
    GRID_RES,
    OTHER_STRUCTURE,
    Ground,
    PrimitiveList,
    Scene,
)

# kind: (half width between the walls (m), wall height (m), ceiling or None, wall class)
_KINDS = {
    "tunnel": (5.0, 6.0, True, OTHER_STRUCTURE),
    "corridor": (2.5, 8.0, False, BUILDING),
    "barriers": (12.0, 3.0, False, FENCE),
    "plane": (None, None, False, None),
}
DEGENERATE_KINDS = tuple(_KINDS)


def straight_trajectory(frames: int, speed: float = 10.0, *, margin: float = 60.0) -> Trajectory:
    """A 10 Hz drive along +x at ``speed`` m/s, the LiDAR at height 0, with ``margin`` metres of
    path before and after the frames (for the scenery)."""
    dt = 0.1
    pad = int(np.ceil(margin / max(speed, 0.1) / dt))
    n = frames + 2 * pad
    t = dt * (np.arange(n) - pad)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = speed * t
    return Trajectory(t, T, pad, frames, default_Tr_cam_velo(), f"straight({speed} m/s)")


def degenerate_scene(kind: str, traj: Trajectory, mount_height: float = 1.73) -> Scene:
    """The ``kind`` of scene (see the module) around a straight drive along +x."""
    if kind not in _KINDS:
        raise InputError(None, f"unknown degenerate scene {kind!r}; choose one of "
                         f"{', '.join(DEGENERATE_KINDS)}")  # fmt: skip
    half, height, ceiling, label = _KINDS[kind]
    x = traj.T_world_lidar[:, 0, 3]
    x0, x1 = float(x.min()) - 100.0, float(x.max()) + 100.0
    z0 = float(traj.T_world_lidar[0, 2, 3]) - mount_height
    shape = (int(np.ceil((x1 - x0) / GRID_RES)) + 1, int(np.ceil(240.0 / GRID_RES)) + 1)
    ground = Ground(
        origin=np.array([x0, -120.0]),
        base_height=np.full(shape, z0, np.float32),
        path_distance=np.zeros(shape, np.float32),
        road_half_width=1e6,  # all road: no curb anywhere
        sidewalk_width=0.0,
        curb_height=0.0,
    )
    boxes = PrimitiveList()
    if half is not None:
        length, centre = 0.5 * (x1 - x0), 0.5 * (x0 + x1)
        for side in (-1.0, 1.0):
            wall_centre = [centre, side * (half + 0.25), z0 + 0.5 * height]
            boxes.add(wall_centre, [length, 0.25, 0.5 * height], label=label)
        if ceiling:
            boxes.add([centre, 0.0, z0 + height + 0.25], [length, half + 0.5, 0.25], label=label)
    empty = PrimitiveList()
    built = boxes.build(0)
    return Scene(kind, ground, built, empty.build(len(built)), empty.build(len(built)))


__all__ = ["DEGENERATE_KINDS", "degenerate_scene", "straight_trajectory"]
