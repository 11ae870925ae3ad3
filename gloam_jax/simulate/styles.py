"""Scene families and their parameters: each family's defaults, the ranges worlds draw from.

A family (``urban``, ``suburban``, ``highway``, ``forest``, ``yard``) names both a layout
(:mod:`gloam_jax.simulate.families`) and its default :class:`StyleParams`. A per-sequence world
(:mod:`gloam_jax.simulate.spec`) draws its own parameters inside :data:`RANGES`, so that no two
worlds of a family look alike. Lengths in metres, densities as fractions.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np


@dataclass(frozen=True)
class StyleParams:
    """What one scene looks like. A pair ``(lo, hi)`` is drawn per object inside the scene."""

    road_half_width: tuple[float, float]
    sidewalk_width: tuple[float, float]  # the band beside the road (a parking area in yards)
    curb_height: float
    terrain_relief: float  # amplitude (m) of terrain undulation beyond the sidewalk
    building_density: float  # fraction of frontage with buildings
    building_setback: tuple[float, float]
    building_height: tuple[float, float]
    building_width: tuple[float, float]  # frontage of one building
    parked_car_prob: float
    tree_spacing: float
    pole_spacing: float
    hedge_fence_prob: float
    guard_rails: bool
    actor_interval_s: float  # mean time between new moving road users
    facade_detail: float = 0.8  # chance a building has recessed windows
    ground_roughness: float = 0.02  # amplitude (m) of bumps a few metres long, road included
    cross_slope: float = 0.0  # terrain grade (m/m) away from the road edge, rising to the left
    clutter_density: float = 0.0  # the family's own objects: undergrowth, container stacks


_STREET = dict(curb_height=0.14, guard_rails=False, building_width=(8.0, 14.0))

STYLES: dict[str, StyleParams] = {
    "urban": StyleParams(
        **_STREET | dict(building_width=(8.0, 24.0)),
        road_half_width=(5.0, 6.5), sidewalk_width=(2.5, 4.0), terrain_relief=0.3,
        building_density=0.85, building_setback=(0.0, 3.0), building_height=(7.0, 24.0),
        parked_car_prob=0.55, tree_spacing=14.0, pole_spacing=30.0, hedge_fence_prob=0.5,
        actor_interval_s=2.5,
    ),
    "suburban": StyleParams(
        **_STREET | dict(curb_height=0.11),
        road_half_width=(3.8, 4.8), sidewalk_width=(1.5, 2.2), terrain_relief=0.8,
        building_density=0.45, building_setback=(6.0, 14.0), building_height=(5.0, 9.0),
        parked_car_prob=0.25, tree_spacing=9.0, pole_spacing=40.0, hedge_fence_prob=0.8,
        actor_interval_s=4.0,
    ),
    "highway": StyleParams(
        **_STREET | dict(curb_height=0.0, guard_rails=True),
        road_half_width=(9.0, 11.0), sidewalk_width=(0.0, 0.0), terrain_relief=1.5,
        building_density=0.0, building_setback=(25.0, 40.0), building_height=(6.0, 10.0),
        parked_car_prob=0.0, tree_spacing=18.0, pole_spacing=60.0, hedge_fence_prob=0.15,
        actor_interval_s=3.0,
    ),
    # A narrow road through woods: tree trunks and crowns in depth, undergrowth, rough sloping
    # ground, and hardly anything built (a barn, a fence, a sign).
    "forest": StyleParams(
        road_half_width=(2.6, 3.4), sidewalk_width=(0.0, 0.0), curb_height=0.0,
        terrain_relief=2.0, building_density=0.08, building_setback=(8.0, 20.0),
        building_height=(4.0, 7.0), building_width=(6.0, 12.0), parked_car_prob=0.03,
        tree_spacing=2.2, pole_spacing=120.0, hedge_fence_prob=0.1, guard_rails=False,
        actor_interval_s=8.0, facade_detail=0.1, ground_roughness=0.05, cross_slope=0.08,
        clutter_density=0.6,
    ),
    # An industrial yard or parking lot: a drive aisle between paved parking bands with cars
    # in rows, container stacks, tall lamp posts, perimeter fences and wide warehouses.
    "yard": StyleParams(
        road_half_width=(3.5, 4.5), sidewalk_width=(20.0, 28.0), curb_height=0.0,
        terrain_relief=0.4, building_density=0.6, building_setback=(4.0, 15.0),
        building_height=(8.0, 14.0), building_width=(20.0, 50.0), parked_car_prob=0.7,
        tree_spacing=40.0, pole_spacing=25.0, hedge_fence_prob=0.0, guard_rails=False,
        actor_interval_s=6.0, facade_detail=0.2, ground_roughness=0.01, clutter_density=0.5,
    ),
}  # fmt: skip

# Per family, the range each drawn parameter comes from; the others keep the family's default.
# A pair-valued parameter draws a sub-range (see draw_params) inside the given one.
RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "urban": dict(
        building_density=(0.6, 1.0), building_setback=(0.0, 5.0), building_height=(6.0, 30.0),
        facade_detail=(0.3, 1.0), tree_spacing=(8.0, 30.0), parked_car_prob=(0.2, 0.8),
        pole_spacing=(20.0, 45.0), ground_roughness=(0.01, 0.04), cross_slope=(-0.03, 0.03),
        terrain_relief=(0.1, 0.6),
    ),
    "suburban": dict(
        building_density=(0.25, 0.7), building_setback=(4.0, 18.0), building_height=(4.0, 11.0),
        facade_detail=(0.2, 0.9), tree_spacing=(6.0, 16.0), parked_car_prob=(0.05, 0.5),
        hedge_fence_prob=(0.4, 1.0), ground_roughness=(0.01, 0.04), cross_slope=(-0.06, 0.06),
        terrain_relief=(0.3, 1.5),
    ),
    "highway": dict(
        tree_spacing=(10.0, 40.0), hedge_fence_prob=(0.0, 0.4), ground_roughness=(0.01, 0.03),
        cross_slope=(-0.1, 0.1), terrain_relief=(0.5, 3.0),
    ),
    "forest": dict(
        tree_spacing=(1.2, 4.0), clutter_density=(0.2, 1.0), building_density=(0.0, 0.15),
        ground_roughness=(0.03, 0.1), cross_slope=(-0.15, 0.15), terrain_relief=(1.0, 3.0),
        hedge_fence_prob=(0.0, 0.3),
    ),
    "yard": dict(
        building_density=(0.3, 0.9), building_setback=(2.0, 20.0), building_height=(6.0, 16.0),
        parked_car_prob=(0.3, 0.95), clutter_density=(0.2, 0.9), pole_spacing=(15.0, 40.0),
        sidewalk_width=(18.0, 32.0), ground_roughness=(0.005, 0.02), cross_slope=(-0.02, 0.02),
    ),
}  # fmt: skip


def draw_params(family: str, rng: np.random.Generator) -> StyleParams:
    """One scene's parameters, drawn uniformly inside ``RANGES[family]`` in field order.

    A pair-valued parameter becomes a sub-range half as wide as the given one, centred at a
    uniform draw (clipped to it): each world has its own typical setback, height, width.
    """
    base, drawn = STYLES[family], {}
    for f in fields(StyleParams):
        if f.name not in RANGES[family]:
            continue
        lo, hi = RANGES[family][f.name]
        if isinstance(getattr(base, f.name), tuple):
            centre, half = rng.uniform(lo, hi), 0.25 * (hi - lo)
            drawn[f.name] = (round(max(lo, centre - half), 3), round(min(hi, centre + half), 3))
        else:
            drawn[f.name] = round(float(rng.uniform(lo, hi)), 4)
    return replace(base, **drawn)
