"""Bird's-eye PNG previews of a simulated (or any KITTI-layout) sequence."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gloam_jax.io import KittiSequence, write_figure
from gloam_jax.simulate.trajectory import interpolate_poses
from gloam_jax.simulate.world import CLASS_NAMES, ROAD, SIDEWALK, TERRAIN

# SemanticKITTI ground classes (road, parking, sidewalk, other-ground, terrain).
GROUND_CLASSES = (ROAD, 44, SIDEWALK, 49, TERRAIN)

# SemanticKITTI-like colours (RGB 0..1) for the classes the simulator emits.
CLASS_COLOURS = {
    10: (0.39, 0.59, 0.96),
    11: (0.39, 0.90, 0.96),
    18: (0.31, 0.12, 0.71),
    30: (0.12, 0.12, 1.0),
    31: (1.0, 0.16, 0.78),
    40: (1.0, 0.0, 1.0),
    44: (1.0, 0.59, 1.0),
    48: (0.29, 0.0, 0.29),
    50: (1.0, 0.78, 0.0),
    51: (1.0, 0.47, 0.20),
    52: (1.0, 0.59, 0.0),
    70: (0.0, 0.69, 0.0),
    71: (0.53, 0.24, 0.0),
    72: (0.59, 0.94, 0.31),
    80: (1.0, 0.94, 0.59),
    81: (1.0, 0.0, 0.0),
    252: (0.39, 0.59, 0.96),
    253: (1.0, 0.16, 0.78),
    254: (0.12, 0.12, 1.0),
}


def _colours(labels: np.ndarray) -> np.ndarray:
    lut = np.full((1 << 16, 3), 0.5)
    for k, c in CLASS_COLOURS.items():
        lut[k] = c
    return lut[labels]


def _save(fig, path: Path) -> None:
    write_figure(path, fig, dpi=130, bbox_inches="tight")


def _figure(size=(9, 9)):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    return fig


def _legend(ax, labels: np.ndarray) -> None:
    from matplotlib.lines import Line2D

    present = [k for k in CLASS_COLOURS if np.any(labels == k)]
    handles = [
        Line2D([], [], marker="o", ls="", color=CLASS_COLOURS[k], label=CLASS_NAMES[k])
        for k in present
    ]
    ax.legend(handles=handles, loc="upper right", fontsize=7, markerscale=1.2, framealpha=0.8)


def deskewed_points(seq: KittiSequence, i: int, T_world_lidar: np.ndarray) -> np.ndarray:
    """Frame i's points in the world frame, each moved by the pose at its own timestamp.

    Poses between frames are interpolated on SE(3); without per-point times the frame pose is
    used for every point. Returns (N, 3).
    """
    pts = seq.scan(i)[:, :3].astype(np.float64)
    dt = seq.point_times(i)
    times = seq.times
    if dt is None or len(times) < 2:
        return pts @ T_world_lidar[i, :3, :3].T + T_world_lidar[i, :3, 3]
    # Few distinct times per frame (one per column): interpolate per time, not per point.
    t_unique, inv = np.unique(times[i] + dt.astype(np.float64), return_inverse=True)
    T_pts = interpolate_poses(times, T_world_lidar, t_unique)[inv.ravel()]
    return np.einsum("nij,nj->ni", T_pts[:, :3, :3], pts) + T_pts[:, :3, 3]


def render_scan_classes(
    points: np.ndarray, labels: np.ndarray | None, path: Path, title: str
) -> Path:
    """Bird's-eye PNG of one scan (N, 3+) within 60 m, coloured by SemanticKITTI class (N,)
    (grey without labels). Returns ``path``."""
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    lab = labels if labels is not None else np.zeros(len(points), np.uint16)
    order = np.argsort(points[:, 2])  # draw high points last: walls over ground
    ax.scatter(points[order, 0], points[order, 1], s=0.15, c=_colours(lab[order]), linewidths=0)
    ax.set_aspect("equal")
    ax.set_xlim(-60, 60)
    ax.set_ylim(-60, 60)
    ax.set_xlabel("x (m, forward)")
    ax.set_ylabel("y (m, left)")
    ax.set_title(title)
    _legend(ax, lab)
    _save(fig, path)
    return path


def render_previews(
    seq: KittiSequence,
    out_dir: str | Path,
    *,
    frame: int = 0,
    map_frames: int = 50,
    max_points: int = 400_000,
) -> list[Path]:
    """Write ``scan_classes.png`` (one scan, by class) and ``map_classes.png`` (a map built
    from the ground-truth poses, deskewed with the per-point times). Returns the paths."""
    out_dir = Path(out_dir)
    T = seq.gt_poses_lidar
    if T is None:
        raise ValueError(f"{seq.root}: preview needs ground-truth poses")
    pts = seq.scan(frame)
    title = f"scan {frame}: {len(pts)} points, coloured by class"
    paths = [render_scan_classes(pts, seq.labels(frame), out_dir / "scan_classes.png", title)]

    n = min(len(seq), map_frames)
    rng = np.random.default_rng(0)
    per = max(max_points // n, 1)
    world, lab_all = [], []
    for i in range(n):
        p = deskewed_points(seq, i, T)
        li = seq.labels(i)
        # Structure only (walls, poles, trees): ground classes where labelled, else by height.
        if li is None:
            li = np.zeros(len(p), np.uint16)
            keep = p[:, 2] - T[i, 2, 3] > -1.4
        else:
            keep = ~np.isin(li, GROUND_CLASSES)
        idx = np.flatnonzero(keep)
        idx = rng.choice(idx, size=min(per, len(idx)), replace=False)
        world.append(p[idx])
        lab_all.append(li[idx])
    world, lab_all = np.concatenate(world), np.concatenate(lab_all)
    fig = _figure((10, 10))
    ax = fig.add_subplot(1, 1, 1)
    ax.scatter(world[:, 0], world[:, 1], s=0.1, c=_colours(lab_all), linewidths=0)
    ax.plot(T[:n, 0, 3], T[:n, 1, 3], "k-", lw=1.0, label="ground truth")
    ax.set_aspect("equal")
    ax.set_title(f"map of frames 0-{n - 1} from ground-truth poses, deskewed (no ground)")
    _legend(ax, lab_all)
    paths.append(out_dir / "map_classes.png")
    _save(fig, paths[-1])
    return paths
