"""What a simulated world is made of: SemanticKITTI classes, solid primitives, the ground.

The world is a ground height field (road, curbs, sidewalks, terrain) plus three kinds of solid
primitives, each stored as flat arrays: yaw-rotated boxes, vertical cylinders and yaw-rotated
ellipsoids. Every primitive has a class id, a reflectivity, a porosity (the chance a ray passes
through, for foliage and hedges), an optional surface pattern (recessed windows, fence slats)
and a constant velocity with an activity window, for moving road users. World frame: z up,
metres, seconds. :mod:`gloam_jax.simulate.scene` lays a street out of these parts;
:mod:`gloam_jax.simulate.raycast` casts rays against them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import map_coordinates

# SemanticKITTI class ids (labels/*.label, low 16 bits).
UNLABELED, CAR, BICYCLE, TRUCK, PERSON, BICYCLIST = 0, 10, 11, 18, 30, 31
ROAD, PARKING, SIDEWALK, BUILDING, FENCE, OTHER_STRUCTURE = 40, 44, 48, 50, 51, 52
VEGETATION, TRUNK, TERRAIN, POLE, TRAFFIC_SIGN = 70, 71, 72, 80, 81
MOVING_CAR, MOVING_BICYCLIST, MOVING_PERSON = 252, 253, 254

CLASS_NAMES = {
    UNLABELED: "unlabeled",
    CAR: "car",
    BICYCLE: "bicycle",
    TRUCK: "truck",
    PERSON: "person",
    BICYCLIST: "bicyclist",
    ROAD: "road",
    PARKING: "parking",
    SIDEWALK: "sidewalk",
    BUILDING: "building",
    FENCE: "fence",
    OTHER_STRUCTURE: "other-structure",
    VEGETATION: "vegetation",
    TRUNK: "trunk",
    TERRAIN: "terrain",
    POLE: "pole",
    TRAFFIC_SIGN: "traffic-sign",
    MOVING_CAR: "moving-car",
    MOVING_BICYCLIST: "moving-bicyclist",
    MOVING_PERSON: "moving-person",
}

# Surface patterns of a primitive's vertical faces.
PATTERN_NONE, PATTERN_WINDOWS, PATTERN_SLATS = 0, 1, 2

GRID_RES = 0.5  # ground grid spacing (m)

REFLECTIVITY = {
    ROAD: 0.22,
    PARKING: 0.25,
    SIDEWALK: 0.3,
    TERRAIN: 0.38,
    BUILDING: 0.35,
    FENCE: 0.32,
    OTHER_STRUCTURE: 0.3,
    VEGETATION: 0.45,
    TRUNK: 0.3,
    POLE: 0.45,
    TRAFFIC_SIGN: 0.95,
    CAR: 0.4,
    TRUCK: 0.42,
    MOVING_CAR: 0.4,
    MOVING_PERSON: 0.3,
    MOVING_BICYCLIST: 0.33,
}


@dataclass
class Primitives:
    """N primitives of one kind. ``size`` is the box half-extents, the cylinder's
    (radius, radius, half height) or the ellipsoid's radii; ``center`` is at time 0."""

    center: np.ndarray  # (N, 3)
    size: np.ndarray  # (N, 3)
    yaw: np.ndarray  # (N,)
    velocity: np.ndarray  # (N, 3)
    t_start: np.ndarray  # (N,) exists from ...
    t_end: np.ndarray  # (N,) ... to, seconds
    label: np.ndarray  # (N,) int32
    reflectivity: np.ndarray  # (N,)
    porosity: np.ndarray  # (N,)
    pattern: np.ndarray  # (N, 4): type, period along the face, period in z (or fill), depth
    uid: np.ndarray  # (N,) uint32, decorrelates per-primitive randomness

    def __len__(self) -> int:
        return len(self.label)

    def take(self, idx: np.ndarray) -> Primitives:
        return Primitives(**{k: v[idx] for k, v in self.__dict__.items()})

    def bounding_radius(self) -> np.ndarray:
        return np.linalg.norm(self.size, axis=1)


@dataclass
class PrimitiveList:
    """Primitives of one kind collected one :meth:`add` at a time, then :meth:`build` as arrays."""

    rows: list[tuple] = field(default_factory=list)

    def add(
        self,
        center,
        size,
        yaw=0.0,
        label=UNLABELED,
        *,
        porosity=0.0,
        pattern=(0, 0, 0, 0),
        velocity=(0.0, 0.0, 0.0),
        t_range=(-np.inf, np.inf),
        reflectivity=None,
    ) -> None:
        refl = REFLECTIVITY.get(label, 0.3) if reflectivity is None else reflectivity
        self.rows.append((center, size, yaw, velocity, t_range, label, refl, porosity, pattern))

    def build(self, uid_offset: int) -> Primitives:
        n = len(self.rows)
        cols = list(zip(*self.rows, strict=True)) if n else [()] * 9

        def arr(i, shape, dtype=np.float64):
            return np.asarray(cols[i], dtype=dtype).reshape((n, *shape))

        t_range = arr(4, (2,))
        return Primitives(
            center=arr(0, (3,)),
            size=arr(1, (3,)),
            yaw=arr(2, ()),
            velocity=arr(3, (3,)),
            t_start=t_range[:, 0],
            t_end=t_range[:, 1],
            label=arr(5, (), np.int32),
            reflectivity=arr(6, ()),
            porosity=arr(7, ()),
            pattern=arr(8, (4,)),
            uid=(uid_offset + np.arange(n)).astype(np.uint32),
        )


@dataclass
class Ground:
    """Height field on a regular grid: cell (i, j) is at origin + (i, j) * GRID_RES."""

    origin: np.ndarray  # (2,) x, y of cell (0, 0)
    base_height: np.ndarray  # (NX, NY) road height + bumps + terrain relief
    path_distance: np.ndarray  # (NX, NY) horizontal distance to the driven path
    road_half_width: float
    sidewalk_width: float
    curb_height: float
    labels: tuple[int, int, int] = (ROAD, SIDEWALK, TERRAIN)  # road, the band beside, beyond

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height at (K, 2) points (numpy twin of the ray caster's lookup)."""
        ij = ((xy - self.origin) / GRID_RES).T
        base = map_coordinates(self.base_height, ij, order=1, mode="nearest")
        dist = map_coordinates(self.path_distance, ij, order=1, mode="nearest")
        return base + self.curb_height * _smoothstep((dist - self.road_half_width) / 0.08)


@dataclass
class Scene:
    """A whole world: the ground and the boxes, cylinders and ellipsoids standing on it."""

    style: str
    ground: Ground
    boxes: Primitives
    cylinders: Primitives
    ellipsoids: Primitives


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)
