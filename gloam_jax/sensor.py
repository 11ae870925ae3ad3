"""Which spinning LiDAR recorded a set of scans, measured from the points alone.

A model's MLPs learned features of the sensors they were trained on (ring spacing sets the
point density the descriptors see). :func:`measure` reads a :class:`SensorSignature` off a few
raw scans in the sensor frame: the rings, the lowest and highest ring elevation, the points
per scan (which stands for the columns: rings times columns, less what returns nothing);
:func:`matches` says whether scans come from a sensor a model records, and why not.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from gloam_jax.errors import InputError

# Points nearer than this (horizontally) are left out: hits on the vehicle itself, and where
# the HDL-64E's per-laser origin offsets (about 0.1-0.2 m) move a point's elevation seen
# from the sensor's origin by degrees. Short of 2.9 m, where an HDL-32E's lowest ring
# (-30.67 deg, 1.73 m up) meets the road.
MIN_HORIZONTAL_RANGE = 2.0
AZIMUTH_BIN_DEG = 1.0  # several columns of every preset (0.16-0.35 deg apart), so each ring shows
# Two returns in one azimuth bin further apart in elevation than this are on two rings: the
# finest ring spacing (HDL-64E upper block, 0.33 deg) less the spread of one real KITTI ring
# across a bin (the per-laser offsets at different ranges: about 0.1 deg).
RING_GAP_DEG = 0.2
# The rings: the count that 1 % of the azimuth bins reach. The top rings see only sky over
# most of a highway, so the busiest bins count them; a few bins split a ring in two (a near
# and a far surface; real KITTI: 65 in the busiest bin of 64 rings), so not the very busiest.
RING_QUANTILE = 99.0
# Scans measured: three scans of real KITTI give the signature that all 16 give (rings 64-65,
# limits within 0.2 deg); a run or a training sequence reads no more than these up front.
SENSOR_SCANS = 3
# The elevation limits: percentiles of all points, so that a few stray returns (reflections
# below the road on real scans) do not set them.
LIMIT_PERCENT = 0.1


@dataclass(frozen=True)
class SensorSignature:
    """A sensor as its scans show it: ``rings`` (beams), ``low_deg`` / ``high_deg`` the
    lowest and highest ring elevation (degrees), ``points`` the median points per scan;
    ``name`` a preset's name where known (``hdl64``), for messages."""

    rings: int
    low_deg: float
    high_deg: float
    points: int
    name: str | None = None

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, data: object) -> SensorSignature:
        """A signature from :meth:`to_dict`'s output; a one-line InputError (no source) says
        what is wrong."""
        needed = {"rings", "low_deg", "high_deg", "points"}
        if not isinstance(data, dict) or not needed <= set(data):
            raise InputError(None, f"a sensor record needs {', '.join(sorted(needed))}: {data!r}")
        if set(data) - needed - {"name"}:
            unknown = sorted(set(data) - needed - {"name"})[0]
            raise InputError(None, f"unknown sensor record key {unknown!r}")
        rings, points, low, high = data["rings"], data["points"], data["low_deg"], data["high_deg"]
        whole = all(isinstance(v, int) and not isinstance(v, bool) for v in (rings, points))
        numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in (low, high))
        if not (whole and numbers and rings >= 1 and points >= 1 and -90 <= low < high <= 90):
            raise InputError(None, f"bad sensor record {data!r}: rings and points must be whole "
                             "numbers >= 1, -90 <= low_deg < high_deg <= 90")  # fmt: skip
        name = data.get("name")
        if name is not None and not isinstance(name, str):
            raise InputError(None, f"a sensor record's name must be text, not {name!r}")
        return cls(int(rings), float(low), float(high), int(points), name)

    def describe(self) -> str:
        """One line: ``hdl64: 64 rings, -24.8..+2.0 deg, 121k points/scan``."""
        label = f"{self.name}: " if self.name else ""
        return (f"{label}{self.rings} rings, {self.low_deg:+.1f}..{self.high_deg:+.1f} deg, "
                f"{self.points / 1e3:.0f}k points/scan")  # fmt: skip


def _elevations(scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth (degrees) of a scan's finite points beyond the minimum range."""
    xyz = np.asarray(scan, np.float64)[:, :3]
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    rho = np.hypot(xyz[:, 0], xyz[:, 1])
    far = rho > MIN_HORIZONTAL_RANGE
    elevation = np.degrees(np.arctan2(xyz[far, 2], rho[far]))
    return elevation, np.degrees(np.arctan2(xyz[far, 1], xyz[far, 0]))


def ring_counts(elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """Rings seen in each azimuth bin of one scan, (bins,): elevations (N,) sorted within the
    bin, split where neighbours lie more than :data:`RING_GAP_DEG` apart."""
    bins = np.floor((azimuth + 180.0) / AZIMUTH_BIN_DEG).astype(np.int64)
    order = np.lexsort((elevation, bins))
    bins, elevation = bins[order], elevation[order]
    new_ring = np.r_[True, (np.diff(bins) != 0) | (np.diff(elevation) > RING_GAP_DEG)]
    return np.bincount(bins[new_ring])


def measure(scans: Sequence[np.ndarray], name: str | None = None) -> SensorSignature:
    """The signature of a few raw scans (each (N, 3+), sensor frame, as recorded: not
    cropped or downsampled); motion distortion moves points along the azimuth and does not
    change their elevation. InputError when they hold too few points to tell."""
    if not scans:
        raise InputError(None, "no scans to measure the sensor on")
    parts = [_elevations(s) for s in scans]
    elevation = np.concatenate([e for e, _ in parts])
    if len(elevation) < 1000:
        raise InputError(None, f"{len(elevation)} points beyond {MIN_HORIZONTAL_RANGE:g} m in "
                         f"{len(scans)} scans: too few to measure the sensor")  # fmt: skip
    counts = np.concatenate([ring_counts(e, a) for e, a in parts])
    return SensorSignature(
        rings=int(round(np.percentile(counts, RING_QUANTILE))),
        low_deg=round(float(np.percentile(elevation, LIMIT_PERCENT)), 2),
        high_deg=round(float(np.percentile(elevation, 100.0 - LIMIT_PERCENT)), 2),
        points=int(np.median([len(s) for s in scans])),
        name=name,
    )


def try_measure(scans: Sequence[np.ndarray]) -> SensorSignature | None:
    """:func:`measure`, or None where the scans hold too few points to tell."""
    try:
        return measure(scans)
    except InputError:
        return None


# -- Tolerances. The presets' lowest rings lie 1.6 deg apart or more (VLP-16 -15, OS1-64
# -16.6, HDL-64E -24.8, HDL-32E -30.67), their highest 1.6 deg or more (+2, +10.67, +15,
# +16.6), and their ring counts a factor of 2 (16, 32, 64) but for the HDL-64E and OS1-64,
# whose limits differ by 8 deg and more.
LOW_TOLERANCE_DEG = 1.2  # the lowest ring sees the road on every scan; on real KITTI scans it
# stands at -24.1..-24.3 deg against the simulated HDL-64E's -24.8 (per-laser offsets, tilt).
HIGH_ABOVE_DEG = 2.0  # real KITTI's top: +3.2..+3.4 deg against +2.0 (the per-laser offsets
# lift near points); the next preset's top is 8.7 deg higher.
HIGH_BELOW_DEG = 8.0  # the top rings may see only sky: a simulated highway's VLP-16 showed
# +9.0 of its +15 deg, an HDL-32E's +8.0 of +10.7.
RINGS_BELOW = 0.5  # half the rings counted: sky (a simulated highway: 12 of a VLP-16's 16)
RINGS_ABOVE = 1.15  # a few more (a ring split by two surfaces), not another sensor's double
# Points per scan: scenes alone move it by up to 1.8x (a simulated VLP-16's highway against
# its urban world: the sky returns nothing); beyond 2.5x the columns differ (OS1-64 1024 and
# 2048) or the scans were thinned, and the point density the features see with them.
POINTS_FACTOR = 2.5


def matches(measured: SensorSignature, recorded: SensorSignature) -> tuple[bool, str]:
    """Whether scans of signature ``measured`` come from the sensor ``recorded``, and a short
    reason (what differs, or that all agree)."""
    m, r = measured, recorded
    checks = (
        (abs(m.low_deg - r.low_deg) <= LOW_TOLERANCE_DEG,
         f"lowest ring {m.low_deg:+.1f} deg, not {r.low_deg:+.1f}"),
        (r.high_deg - HIGH_BELOW_DEG <= m.high_deg <= r.high_deg + HIGH_ABOVE_DEG,
         f"highest ring {m.high_deg:+.1f} deg, not {r.high_deg:+.1f}"),
        (RINGS_BELOW * r.rings <= m.rings <= RINGS_ABOVE * r.rings,
         f"{m.rings} rings, not {r.rings}"),
        (r.points / POINTS_FACTOR <= m.points <= r.points * POINTS_FACTOR,
         f"{m.points} points per scan, not about {r.points}"),
    )  # fmt: skip
    problems = [why for ok, why in checks if not ok]
    label = r.name or "the recorded sensor"
    if problems:
        return False, f"not {label}: " + "; ".join(problems)
    return True, f"matches {label}"


def first_match(
    measured: SensorSignature, recorded: Sequence[SensorSignature]
) -> tuple[SensorSignature | None, str]:
    """The first of ``recorded`` that ``measured`` matches (None if none) and why."""
    reasons = []
    for r in recorded:
        ok, why = matches(measured, r)
        if ok:
            return r, why
        reasons.append(why)
    return None, "; ".join(reasons) if reasons else "no sensor recorded"


def merge(signatures: Sequence[SensorSignature]) -> list[SensorSignature]:
    """One signature per sensor among ``signatures`` (of several training sequences): each
    joins the first group it matches, and a group keeps what any of its scans showed (most
    rings, widest limits: one highway's sky does not narrow the record) and the median points."""
    groups: list[list[SensorSignature]] = []
    for s in signatures:
        group = next((g for g in groups if matches(s, g[0])[0] and s.name == g[0].name), None)
        if group is None:
            groups.append([s])
        else:
            group.append(s)
    return [
        SensorSignature(
            rings=max(s.rings for s in g),
            low_deg=min(s.low_deg for s in g),
            high_deg=max(s.high_deg for s in g),
            points=int(np.median([s.points for s in g])),
            name=g[0].name,
        )
        for g in groups
    ]
