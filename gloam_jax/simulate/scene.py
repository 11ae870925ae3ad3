"""The parts of a procedural scene built around a trajectory, and how they are placed.

A scene follows the driven path: a road with curbs and sidewalks, then buildings, hedges,
fences and walls, guard rails, parked cars, poles and signs, trees and bushes, and moving road
users, each placed so that it neither blocks the road nor overlaps another. Which parts a scene
has, and in what order, is its family's (:mod:`gloam_jax.simulate.families`); the primitives
and their conventions are in :mod:`gloam_jax.simulate.world`.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates
from scipy.spatial import cKDTree

from gloam_jax.errors import InputError
from gloam_jax.simulate.styles import STYLES, StyleParams
from gloam_jax.simulate.trajectory import Trajectory
from gloam_jax.simulate.world import (
    BUILDING,
    CAR,
    FENCE,
    GRID_RES,
    MOVING_BICYCLIST,
    MOVING_CAR,
    MOVING_PERSON,
    OTHER_STRUCTURE,
    PATTERN_SLATS,
    PATTERN_WINDOWS,
    POLE,
    ROAD,
    SIDEWALK,
    TERRAIN,
    TRAFFIC_SIGN,
    TRUNK,
    VEGETATION,
    Ground,
    PrimitiveList,
)


def smooth_field(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Unit-variance smooth noise on a grid, correlated over ``cell`` grid steps."""
    coarse = rng.normal(size=(shape[0] // max(int(cell), 1) + 3, shape[1] // max(int(cell), 1) + 3))
    ii = np.linspace(0, shape[0] / max(cell, 1.0), shape[0]) + 1
    jj = np.linspace(0, shape[1] / max(cell, 1.0), shape[1]) + 1
    grid = np.meshgrid(ii, jj, indexing="ij")
    return map_coordinates(coarse, grid, order=3, mode="nearest")


class _Path:
    """The driven road's centre line resampled every 0.5 m, with headings and a k-d tree."""

    def __init__(self, traj: Trajectory, mount_height: float) -> None:
        road = traj.T_world_lidar[:, :3, :3] @ np.array([0.0, 0.0, -mount_height])
        road = road + traj.T_world_lidar[:, :3, 3]
        seg = np.linalg.norm(np.diff(road, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        keep = np.concatenate([[True], seg > 1e-6])
        s, road = s[keep], road[keep]
        self.s = np.arange(0.0, s[-1], 0.5)
        self.points = np.stack([np.interp(self.s, s, road[:, k]) for k in range(3)], axis=1)
        d = np.gradient(self.points[:, :2], axis=0)
        self.tangent = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        self.normal = np.stack([-self.tangent[:, 1], self.tangent[:, 0]], axis=1)  # left
        self.tree = cKDTree(self.points[:, :2])
        self.length = float(self.s[-1])

    def at(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Road point (3,), unit tangent (2,) and left normal (2,) at arc length s."""
        i = int(np.clip(np.searchsorted(self.s, s), 0, len(self.s) - 1))
        return self.points[i], self.tangent[i], self.normal[i]

    def distance(self, xy: np.ndarray) -> np.ndarray:
        return self.tree.query(xy)[0]  # a few points: threads would cost more


class _Occupancy:
    """Coarse raster of used ground, so objects do not overlap each other."""

    def __init__(self, cell: float = 0.5) -> None:
        self.cell = cell
        self.used: set[tuple[int, int]] = set()

    def cells(self, xy: np.ndarray, half: np.ndarray, yaw: float) -> set[tuple[int, int]]:
        c, s = np.cos(yaw), np.sin(yaw)
        n = np.maximum(np.ceil(2 * half / self.cell).astype(int) + 1, 2)
        u, v = np.meshgrid(
            np.linspace(-half[0], half[0], n[0]), np.linspace(-half[1], half[1], n[1])
        )
        pts = xy + np.stack([c * u - s * v, s * u + c * v], axis=-1).reshape(-1, 2)
        return set(map(tuple, np.floor(pts / self.cell).astype(int)))

    def try_claim(self, xy, half, yaw) -> bool:
        cells = self.cells(np.asarray(xy), np.asarray(half), yaw)
        if cells & self.used:
            return False
        self.used |= cells
        return True


def _footprint_points(xy: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    u, v = np.meshgrid(np.linspace(-1, 1, 5) * half[0], np.linspace(-1, 1, 5) * half[1])
    return xy + np.stack([c * u - s * v, s * u + c * v], axis=-1).reshape(-1, 2)


class SceneBuilder:
    """Lays out one scene along a trajectory: placement helpers and the parts streets share.

    The families (:mod:`gloam_jax.simulate.families`) call the parts in their own order.
    """

    def __init__(
        self,
        traj: Trajectory,
        style: str,
        seed: int,
        mount_height: float,
        dynamic: bool,
        detail: bool,
        params: StyleParams | None = None,
    ) -> None:
        if style not in STYLES:
            raise InputError(
                None, f"unknown scene style {style!r}; choose one of {', '.join(STYLES)}"
            )
        self.traj, self.style = traj, style
        self.p = STYLES[style] if params is None else params
        self.rng = np.random.default_rng(seed)
        self.path = _Path(traj, mount_height)
        self.dynamic, self.detail = dynamic, detail
        self.road_half = float(self.rng.uniform(*self.p.road_half_width))
        self.sidewalk = float(self.rng.uniform(*self.p.sidewalk_width))
        self.edge = self.road_half + self.sidewalk  # where private ground starts
        self.occ = _Occupancy()
        self.ground_labels = (ROAD, SIDEWALK, TERRAIN)  # road, the band beside it, beyond
        self.boxes, self.cyls, self.ells = PrimitiveList(), PrimitiveList(), PrimitiveList()

    # -- placement helpers ---------------------------------------------------------------
    def _clear_of_road(self, xy, half, yaw, clearance) -> bool:
        return bool(
            self.path.distance(_footprint_points(np.asarray(xy), np.asarray(half), yaw)).min()
            > clearance
        )

    def _place(self, s: float, side: int, lateral: float, half, yaw_offset=0.0, clearance=None):
        """Centre and yaw of a footprint at arc length s, ``lateral`` metres to one side."""
        point, tangent, normal = self.path.at(s)
        xy = point[:2] + side * lateral * normal
        yaw = float(np.arctan2(tangent[1], tangent[0]) + yaw_offset)
        half = np.asarray(half, dtype=float)
        if clearance is not None and not self._clear_of_road(xy, half[:2], yaw, clearance):
            return None
        if not self.occ.try_claim(xy, half[:2], yaw):
            return None
        return xy, yaw

    def ground_z(self, xy) -> float:
        return float(self.path.points[self.path.tree.query(xy)[1], 2])

    # -- scene parts ---------------------------------------------------------------------
    def buildings(self) -> None:
        p, rng = self.p, self.rng
        if p.building_density <= 0:
            return
        for side in (1, -1):
            s = rng.uniform(0, 10)
            while s < self.path.length:
                width = rng.uniform(*p.building_width)
                if rng.random() > p.building_density:
                    s += rng.uniform(4.0, 14.0)
                    continue
                depth = rng.uniform(8.0, 16.0)
                setback = rng.uniform(*p.building_setback)
                height = rng.uniform(*p.building_height)
                half = np.array([width / 2, depth / 2, height / 2])
                placed = self._place(
                    s + width / 2,
                    side,
                    self.edge + setback + depth / 2,
                    half,
                    yaw_offset=rng.normal(0, 0.03),
                    clearance=self.edge,
                )
                if placed is not None:
                    self._building(placed, half, side)
                s += width + rng.uniform(0.0, 3.0)

    def _building(self, placed, half, side) -> None:
        (xy, yaw), rng = placed, self.rng
        z0 = self.ground_z(xy) - 0.3  # a little below grade so slopes leave no gap
        half = half + np.array([0, 0, 0.15])
        pattern = (0, 0, 0, 0)
        if self.detail and rng.random() < self.p.facade_detail:
            pattern = (
                PATTERN_WINDOWS,
                rng.uniform(2.4, 3.6),
                rng.uniform(2.8, 3.4),
                rng.uniform(0.15, 0.35),
            )
        self.boxes.add([*xy, z0 + half[2]], half, yaw, BUILDING, pattern=pattern)
        if self.detail and rng.random() < 0.6:  # cornice / ledge sticking out of the facade
            ledge = half + np.array([0.35, 0.35, 0.0])
            ledge[2] = rng.uniform(0.15, 0.3)
            self.boxes.add([*xy, z0 + 2 * half[2] - ledge[2]], ledge, yaw, BUILDING)
        if self.detail and rng.random() < 0.35:  # lower annex, making an L or stepped outline
            annex = half * np.array([rng.uniform(0.3, 0.6), rng.uniform(0.8, 1.1), 0.0])
            annex[2] = rng.uniform(1.5, 3.0)
            c, s = np.cos(yaw), np.sin(yaw)
            shift = (half[0] + annex[0]) * np.array([c, s]) * rng.choice([-1, 1])
            if self.occ.try_claim(xy + shift, annex[:2], yaw):
                self.boxes.add([*(xy + shift), z0 + annex[2]], annex, yaw, BUILDING)

    def parked_cars(self) -> None:
        rng = self.rng
        for side in (1, -1):
            s = rng.uniform(0, 6)
            while s < self.path.length:
                length = rng.uniform(4.0, 4.9)
                if rng.random() < self.p.parked_car_prob:
                    half = np.array([length / 2, 0.9, 0.75])
                    placed = self._place(
                        s,
                        side,
                        self.road_half - 1.15,
                        half,
                        yaw_offset=rng.normal(0, 0.03),
                        clearance=2.6,
                    )
                    if placed is not None:
                        self._car(*placed, CAR, length)
                s += length + rng.uniform(0.8, 2.5)

    def _car(self, xy, yaw, label, length, velocity=(0, 0, 0), t_range=(-np.inf, np.inf)) -> None:
        rng, z = self.rng, self.ground_z(xy)
        width = rng.uniform(1.7, 1.9)
        body_h = rng.uniform(0.6, 0.8)
        kw = dict(velocity=velocity, t_range=t_range)
        # Body clear of the road (rays pass under it) and a rounded cabin.
        self.boxes.add(
            [*xy, z + 0.3 + body_h / 2], [length / 2, width / 2, body_h / 2], yaw, label, **kw
        )
        c, s = np.cos(yaw), np.sin(yaw)
        back = -rng.uniform(0.1, 0.5) * np.array([c, s])
        self.ells.add(
            [*(xy + back), z + 0.3 + body_h], [length * 0.3, width * 0.46, 0.55], yaw, label, **kw
        )

    def poles_and_signs(self) -> None:
        rng = self.rng
        for side in (1, -1):
            s = rng.uniform(0, self.p.pole_spacing)
            while s < self.path.length:
                lateral = self.road_half + (0.5 if self.sidewalk > 0 else 2.0)
                if rng.random() < 0.7:  # street lamp with an arm over the road
                    height, r = rng.uniform(6.0, 9.0), rng.uniform(0.07, 0.13)
                    placed = self._place(s, side, lateral, [r, r, height / 2], clearance=2.5)
                    if placed is not None:
                        (xy, yaw), z = placed, self.ground_z(placed[0])
                        self.cyls.add([*xy, z + height / 2], [r, r, height / 2], 0.0, POLE)
                        _, _, n = self.path.at(s)
                        arm_xy = xy - side * 0.9 * n
                        self.boxes.add(
                            [*arm_xy, z + height - 0.1],
                            [0.9, 0.06, 0.06],
                            float(np.arctan2(n[1], n[0])),
                            POLE,
                        )
                else:  # traffic sign: thin pole, reflective panel facing the traffic
                    height, r = rng.uniform(2.2, 3.2), 0.04
                    placed = self._place(s, side, lateral, [0.4, 0.4, height / 2], clearance=2.5)
                    if placed is not None:
                        (xy, yaw), z = placed, self.ground_z(placed[0])
                        self.cyls.add([*xy, z + height / 2], [r, r, height / 2], 0.0, POLE)
                        panel = [0.03, rng.uniform(0.3, 0.45), rng.uniform(0.3, 0.45)]
                        self.boxes.add([*xy, z + height + panel[2] - 0.2], panel, yaw, TRAFFIC_SIGN)
                s += self.p.pole_spacing * rng.uniform(0.6, 1.4)

    def trees_and_bushes(self) -> None:
        rng = self.rng
        for side in (1, -1):
            s = rng.uniform(0, self.p.tree_spacing)
            while s < self.path.length:
                if self.style == "urban":
                    lateral = self.road_half + self.sidewalk * 0.75
                else:
                    lateral = self.edge + rng.uniform(2.0, 25.0 if self.style == "highway" else 9.0)
                trunk_r, trunk_h = rng.uniform(0.12, 0.3), rng.uniform(1.8, 3.5)
                crown = np.array([rng.uniform(1.5, 3.5)] * 2 + [rng.uniform(1.4, 3.0)])
                placed = self._place(s, side, lateral, [trunk_r * 2, trunk_r * 2, 1], clearance=2.0)
                if placed is not None:
                    self.tree(placed[0], trunk_r, trunk_h, crown)
                if self.style != "urban" and rng.random() < 0.5:  # a bush nearby
                    radii = np.array([rng.uniform(0.6, 1.5)] * 2 + [rng.uniform(0.5, 1.0)])
                    bush = self._place(
                        s + rng.uniform(2, 5),
                        side,
                        lateral + rng.uniform(-1, 2),
                        radii,
                        clearance=self.edge,
                    )
                    if bush is not None:
                        xy = bush[0]
                        self.ells.add(
                            [*xy, self.ground_z(xy) + 0.5 * radii[2]],
                            radii,
                            rng.uniform(0, np.pi),
                            VEGETATION,
                            porosity=0.25,
                        )
                s += self.p.tree_spacing * rng.uniform(0.5, 1.5)

    def tree(self, xy, trunk_r: float, trunk_h: float, crown: np.ndarray) -> None:
        """A trunk (cylinder) under a porous crown (ellipsoid radii ``crown``), on the ground."""
        rng, z = self.rng, self.ground_z(xy)
        self.cyls.add(
            [*xy, z + trunk_h / 2 - 0.1], [trunk_r, trunk_r, trunk_h / 2 + 0.1], 0.0, TRUNK
        )
        self.ells.add(
            [*xy, z + trunk_h + 0.7 * crown[2]],
            crown,
            rng.uniform(0, np.pi),
            VEGETATION,
            porosity=rng.uniform(0.3, 0.6),
        )

    def hedges_fences_walls(self) -> None:
        rng, p = self.rng, self.p
        for side in (1, -1):
            s = rng.uniform(0, 20)
            while s < self.path.length:
                length = rng.uniform(6.0, 25.0)
                if rng.random() < p.hedge_fence_prob:
                    kind = rng.choice(["hedge", "fence", "wall"], p=[0.4, 0.4, 0.2])
                    lateral = self.edge + rng.uniform(0.3, 1.5)
                    if kind == "hedge":
                        half = [length / 2, rng.uniform(0.4, 0.7), rng.uniform(0.5, 0.9)]
                        label, por, pattern = VEGETATION, 0.3, (0, 0, 0, 0)
                    elif kind == "fence":
                        half = [length / 2, 0.03, rng.uniform(0.5, 1.0)]
                        label, por = FENCE, 0.0
                        pattern = (PATTERN_SLATS, rng.uniform(0.1, 0.25), rng.uniform(0.4, 0.8), 0)
                    else:
                        half = [length / 2, 0.12, rng.uniform(0.6, 1.5)]
                        label, por, pattern = OTHER_STRUCTURE, 0.0, (0, 0, 0, 0)
                    half = np.asarray(half)
                    placed = self._place(
                        s + length / 2, side, lateral + half[1], half, clearance=self.edge
                    )
                    if placed is not None:
                        xy, yaw = placed
                        self.boxes.add(
                            [*xy, self.ground_z(xy) + half[2] - 0.05],
                            half,
                            yaw,
                            label,
                            porosity=por,
                            pattern=pattern,
                        )
                s += length + rng.uniform(5.0, 30.0)

    def guard_rails(self) -> None:
        if not self.p.guard_rails:
            return
        for side in (1, -1):
            s = 0.0
            while s < self.path.length:
                seg = 6.0
                placed = self._place(
                    s + seg / 2,
                    side,
                    self.road_half + 1.0,
                    [seg / 2, 0.05, 0.17],
                    clearance=self.road_half + 0.5,
                )
                if placed is not None:
                    xy, yaw = placed
                    z = self.ground_z(xy)
                    self.boxes.add([*xy, z + 0.6], [seg / 2, 0.05, 0.17], yaw, FENCE)
                    self.cyls.add([*xy, z + 0.35], [0.06, 0.06, 0.35], 0.0, FENCE)
                s += seg
            # Occasional noise-barrier walls further out.
            s = self.rng.uniform(0, 200)
            while s < self.path.length:
                length = self.rng.uniform(40, 120)
                half = np.array([length / 2, 0.15, self.rng.uniform(1.5, 2.2)])
                if self.rng.random() < 0.4:
                    placed = self._place(
                        s + length / 2,
                        side,
                        self.road_half + 6.0,
                        half,
                        clearance=self.road_half + 3.0,
                    )
                    if placed is not None:
                        xy, yaw = placed
                        self.boxes.add(
                            [*xy, self.ground_z(xy) + half[2] - 0.1], half, yaw, OTHER_STRUCTURE
                        )
                s += length + self.rng.uniform(50, 300)

    def moving_actors(self) -> None:
        """Cars, cyclists and pedestrians moving in straight lines for a few seconds each."""
        if not self.dynamic:
            return
        rng, traj = self.rng, self.traj
        t0, t1 = traj.frame_times[0], traj.frame_times[-1]
        t = t0 - 3.0
        while t < t1:
            ego = traj.poses_at(np.array([t]))[0, :2, 3]
            s_ego = self.path.s[self.path.tree.query(ego)[1]]
            kind = rng.choice(
                ["oncoming", "ahead", "cyclist", "pedestrian"], p=[0.4, 0.2, 0.15, 0.25]
            )
            duration = rng.uniform(5.0, 9.0)
            t_range = (t, t + duration)
            if kind in ("oncoming", "ahead"):
                speed = rng.uniform(6.0, 14.0)
                s0 = (
                    s_ego + rng.uniform(50.0, 90.0)
                    if kind == "oncoming"
                    else s_ego + rng.uniform(12, 30)
                )
                lateral, direction = (3.3, -1.0) if kind == "oncoming" else (0.0, 1.0)
                point, tangent, normal = self.path.at(s0)
                xy = point[:2] + lateral * normal
                vel = direction * speed * tangent
                # Centre at time 0 so that it is at xy at time t.
                xy0 = xy - vel * t
                yaw = float(np.arctan2(vel[1], vel[0]))
                self._car(xy0, yaw, MOVING_CAR, rng.uniform(4.0, 4.8), (*vel, 0.0), t_range)
            elif kind == "cyclist":
                speed = rng.uniform(3.5, 6.5)
                point, tangent, normal = self.path.at(s_ego + rng.uniform(10, 40))
                side = rng.choice([-1, 1])
                xy = point[:2] + side * (self.road_half - 0.8) * normal
                vel = speed * tangent * (1 if side < 0 else -1)
                xy0, yaw, z = xy - vel * t, float(np.arctan2(vel[1], vel[0])), point[2]
                kw = dict(velocity=(*vel, 0.0), t_range=t_range)
                self.boxes.add([*xy0, z + 0.5], [0.85, 0.05, 0.45], yaw, MOVING_BICYCLIST, **kw)
                self.ells.add([*xy0, z + 1.35], [0.3, 0.22, 0.45], yaw, MOVING_BICYCLIST, **kw)
            else:
                speed = rng.uniform(0.9, 1.7)
                point, tangent, normal = self.path.at(s_ego + rng.uniform(-10, 40))
                side = rng.choice([-1, 1])
                xy = point[:2] + side * (self.road_half + max(self.sidewalk, 1.5) * 0.5) * normal
                vel = speed * tangent * rng.choice([-1, 1])
                xy0, yaw, z = (
                    xy - vel * t,
                    float(np.arctan2(vel[1], vel[0])),
                    point[2] + self.p.curb_height,
                )
                kw = dict(velocity=(*vel, 0.0), t_range=(t, t + 3 * duration))
                self.ells.add([*xy0, z + 1.25], [0.15, 0.24, 0.38], yaw, MOVING_PERSON, **kw)
                self.ells.add([*xy0, z + 1.72], [0.11, 0.11, 0.13], yaw, MOVING_PERSON, **kw)
                self.boxes.add([*xy0, z + 0.45], [0.12, 0.17, 0.45], yaw, MOVING_PERSON, **kw)
            t += rng.exponential(self.p.actor_interval_s)

    def ground(self) -> Ground:
        rng = self.rng
        pts = self.path.points[:, :2]
        lo = pts.min(axis=0) - 140.0
        hi = pts.max(axis=0) + 140.0
        shape = tuple(np.ceil((hi - lo) / GRID_RES).astype(int) + 1)
        ii, jj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
        xy = lo + GRID_RES * np.stack([ii.ravel(), jj.ravel()], axis=1)
        dist, nearest = self.path.tree.query(xy, workers=-1)
        # Which side of the road: + left of the driving direction (for the cross slope).
        side = np.sign(np.sum((xy - self.path.points[nearest, :2]) * self.path.normal[nearest], 1))
        beyond = (side * np.maximum(dist - self.edge, 0.0)).reshape(shape)
        dist = dist.reshape(shape).astype(np.float32)
        road_z = self.path.points[nearest, 2].reshape(shape)
        # Road bumps a few cm over a few metres; terrain relief grows away from the road, and
        # the terrain rises on one side and falls on the other (a road cut into a hillside).
        bumps = self.p.ground_roughness * smooth_field(rng, shape, 6.0 / GRID_RES)
        relief = self.p.terrain_relief * smooth_field(rng, shape, 25.0 / GRID_RES)
        away = np.clip((dist - self.edge - 1.0) / 12.0, 0.0, 1.0)
        relief = relief + self.p.cross_slope * beyond
        # The nearest road height jumps where two stretches of road at different heights are
        # equally near (inside corners, slopes). Smoothing removes the step; it leaves the
        # height under the path itself unchanged (linear along it, constant across it), and
        # away from the road a much wider smoothing takes over.
        near_z = gaussian_filter(road_z, sigma=2.0 / GRID_RES, mode="nearest")
        far_z = gaussian_filter(road_z, sigma=12.0 / GRID_RES, mode="nearest")
        base = near_z * (1.0 - away) + far_z * away + bumps + relief * away
        return Ground(
            lo,
            base.astype(np.float32),
            dist,
            self.road_half,
            self.sidewalk,
            self.p.curb_height if self.sidewalk > 0 else 0.0,
            self.ground_labels,
        )
