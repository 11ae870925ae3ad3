"""Scene families: which parts a scene has and how they are laid out, one layout per family.

* ``urban``, ``suburban``, ``highway``: streets (buildings, hedges, fences, guard rails, parked
  cars, poles and signs, trees, moving road users), told apart by their parameters.
* ``forest``: a narrow road without curbs through woods several rows deep, trunks under tall
  crowns and undergrowth, on rough sloping ground, with a rare barn, fence or sign.
* ``yard``: an industrial yard or parking lot: a drive aisle between wide paved bands
  (SemanticKITTI ``parking``) with cars parked in rows, stacks of shipping containers
  (``other-structure``), tall lamp posts, perimeter fences and wide warehouses.
"""

from __future__ import annotations

import numpy as np

from gloam_jax.simulate.scene import SceneBuilder
from gloam_jax.simulate.styles import StyleParams
from gloam_jax.simulate.trajectory import Trajectory
from gloam_jax.simulate.world import (
    CAR,
    FENCE,
    OTHER_STRUCTURE,
    PARKING,
    PATTERN_SLATS,
    POLE,
    ROAD,
    TERRAIN,
    TRUCK,
    VEGETATION,
    Scene,
)

CONTAINER_HALF = np.array([6.06, 2.44, 2.59]) / 2  # ISO 20 ft container (m); 40 ft is 12.19 long
_CONTAINER_GAP = 0.02  # stacked containers sit on corner castings: a visible seam


class ForestBuilder(SceneBuilder):
    """Woods in depth beside a narrow road; ``tree_spacing`` sets their density."""

    def woods(self) -> None:
        rng, p = self.rng, self.p
        for side in (1, -1):
            s = rng.uniform(0, p.tree_spacing)
            while s < self.path.length:
                # Denser near the road's edge (a cleared verge of 1-3 m), thinning inwards.
                lateral = self.edge + rng.uniform(1.0, 3.0) + min(rng.exponential(10.0), 45.0)
                trunk_r = rng.uniform(0.1, 0.4)
                conifer = rng.random() < 0.5
                if conifer:  # a tall narrow crown low on a short trunk
                    trunk_h = rng.uniform(1.0, 3.0)
                    crown = np.array([rng.uniform(1.2, 2.2)] * 2 + [rng.uniform(3.0, 7.0)])
                else:
                    trunk_h = rng.uniform(3.0, 6.0)
                    crown = np.array([rng.uniform(2.0, 4.5)] * 2 + [rng.uniform(2.0, 4.0)])
                placed = self._place(s, side, lateral, [trunk_r * 2, trunk_r * 2, 1], clearance=2.0)
                if placed is not None:
                    self.tree(placed[0], trunk_r, trunk_h, crown)
                if rng.random() < p.clutter_density:  # undergrowth between the trunks
                    radii = np.array([rng.uniform(0.4, 1.4)] * 2 + [rng.uniform(0.3, 0.9)])
                    bush = self._place(
                        s + rng.uniform(-1, 1), side, lateral + rng.uniform(-3, 3), radii,
                        clearance=self.edge + 0.3,
                    )  # fmt: skip
                    if bush is not None:
                        xy = bush[0]
                        self.ells.add([*xy, self.ground_z(xy) + 0.5 * radii[2]], radii,
                                      rng.uniform(0, np.pi), VEGETATION, porosity=0.35)  # fmt: skip
                s += p.tree_spacing * rng.uniform(0.3, 1.2)


class YardBuilder(SceneBuilder):
    """A drive aisle through paved parking bands; ``sidewalk_width`` is the band's width."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.ground_labels = (ROAD, PARKING, TERRAIN)

    def car_rows(self) -> None:
        """Two rows of cars per side, nose to nose, parked across the aisle; some trucks."""
        rng = self.rng
        for side in (1, -1):
            for row in (0, 1):
                lateral = self.road_half + 3.0 + row * 5.2
                s = rng.uniform(0, 3)
                while s < self.path.length:
                    if rng.random() < self.p.parked_car_prob:
                        length = rng.uniform(4.0, 4.9)
                        half, yaw = [length / 2, 0.95, 0.8], np.pi / 2 + rng.normal(0, 0.04)
                        placed = self._place(s, side, lateral, half, yaw_offset=yaw)
                        if placed is not None:
                            self._car(*placed, TRUCK if rng.random() < 0.1 else CAR, length)
                    s += rng.uniform(2.5, 2.9)

    def containers(self) -> None:
        """Rows of container stacks (1-3 high) behind the cars, in the outer parking bands."""
        rng = self.rng
        behind_cars = self.road_half + 10.8  # the two car rows end here (see car_rows)
        for side in (1, -1):
            s = rng.uniform(0, 20)
            while s < self.path.length:
                half = CONTAINER_HALF * np.array([rng.choice([1.0, 2.0]), 1.0, 1.0])  # 20/40 ft
                if rng.random() < self.p.clutter_density:
                    lateral = behind_cars + half[1] + rng.uniform(0.0, 4.0)
                    yaw = rng.normal(0, 0.02)
                    for k in range(int(rng.integers(1, 5))):  # containers side by side
                        lat = lateral + 2 * k * (half[1] + 0.3)
                        placed = self._place(s, side, lat, half, yaw_offset=yaw,
                                             clearance=behind_cars)  # fmt: skip
                        if placed is None:
                            continue
                        xy, z = placed[0], self.ground_z(placed[0])
                        for level in range(int(rng.integers(1, 4))):
                            zc = z + half[2] + level * (2 * half[2] + _CONTAINER_GAP)
                            self.boxes.add([*xy, zc], half, placed[1], OTHER_STRUCTURE)
                s += 2 * half[0] + rng.uniform(3.0, 30.0)

    def lamp_posts(self) -> None:
        """Tall lamp posts in the parking bands with a lamp head on top."""
        rng = self.rng
        for side in (1, -1):
            s = rng.uniform(0, self.p.pole_spacing)
            while s < self.path.length:
                height, r = rng.uniform(8.0, 12.0), rng.uniform(0.1, 0.16)
                lateral = self.road_half + rng.uniform(0.6, 1.2)
                placed = self._place(s, side, lateral, [r, r, height / 2], clearance=self.road_half)
                if placed is not None:
                    xy, yaw = placed
                    z = self.ground_z(xy)
                    self.cyls.add([*xy, z + height / 2], [r, r, height / 2], 0.0, POLE)
                    self.boxes.add([*xy, z + height + 0.15], [0.45, 0.25, 0.15], yaw, POLE)
                s += self.p.pole_spacing * rng.uniform(0.8, 1.2)

    def perimeter_fence(self) -> None:
        """A chain-link fence along the outer edge of each band, with gates."""
        rng = self.rng
        for side in (1, -1):
            s = 0.0
            while s < self.path.length:
                length = rng.uniform(15.0, 40.0)
                half = np.array([length / 2, 0.03, rng.uniform(0.9, 1.2)])
                placed = self._place(s + length / 2, side, self.edge + 0.5, half,
                                     clearance=self.edge)  # fmt: skip
                if placed is not None:
                    xy, yaw = placed
                    self.boxes.add([*xy, self.ground_z(xy) + half[2] - 0.05], half, yaw, FENCE,
                                   pattern=(PATTERN_SLATS, 0.08, 0.3, 0))  # fmt: skip
                s += length + rng.uniform(4.0, 9.0)  # a gate


def _street(b: SceneBuilder) -> None:
    # Larger structures first, so smaller ones fill the gaps they leave.
    b.buildings()
    b.hedges_fences_walls()
    b.guard_rails()
    b.parked_cars()
    b.poles_and_signs()
    b.trees_and_bushes()


def _forest(b: ForestBuilder) -> None:
    b.buildings()
    b.hedges_fences_walls()
    b.parked_cars()
    b.poles_and_signs()
    b.woods()


def _yard(b: YardBuilder) -> None:
    b.buildings()
    b.perimeter_fence()
    b.containers()
    b.lamp_posts()
    b.car_rows()
    b.trees_and_bushes()


_LAYOUTS = {
    "urban": (SceneBuilder, _street),
    "suburban": (SceneBuilder, _street),
    "highway": (SceneBuilder, _street),
    "forest": (ForestBuilder, _forest),
    "yard": (YardBuilder, _yard),
}
FAMILIES: tuple[str, ...] = tuple(_LAYOUTS)


def build_scene(
    traj: Trajectory,
    style: str = "urban",
    seed: int = 0,
    *,
    mount_height: float = 1.73,
    dynamic: bool = True,
    detail: bool = True,
    params: StyleParams | None = None,
) -> Scene:
    """Procedural scene of family ``style`` around ``traj``. ``dynamic``: moving road users;
    ``detail``: recessed windows, ledges and annexes (non-planar detail); ``params``: the
    scene's parameters (default: the family's, ``styles.STYLES[style]``)."""
    builder_cls, layout = _LAYOUTS.get(style, (SceneBuilder, _street))  # SceneBuilder refuses
    b = builder_cls(traj, style, seed, mount_height, dynamic, detail, params)
    ground = b.ground()
    layout(b)
    b.moving_actors()
    boxes = b.boxes.build(0)
    cyls = b.cyls.build(len(boxes))
    ells = b.ells.build(len(boxes) + len(cyls))
    return Scene(style, ground, boxes, cyls, ells)
