"""A per-sequence world: scene family and parameters, sensor and its errors, drive, all from a seed.

A :class:`WorldSpec` says everything that makes one simulated sequence differ from another:
the scene family and its drawn parameters (:mod:`gloam_jax.simulate.styles`), the sensor model
and its error parameters, motion distortion on or off, and the drive (a window of a real KITTI
trajectory, ``speed_scale`` times as fast). :func:`draw_world` draws one reproducibly from a
seed; ``simulate(world=...)`` and ``gloam simulate --world FILE`` simulate it and record it as
``world.json`` beside the scans, which :func:`load_world` reads back (JSON or YAML).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import yaml

from gloam_jax.errors import InputError, check_setting, is_int
from gloam_jax.simulate.sensors import SENSORS, SensorModel, get_sensor
from gloam_jax.simulate.styles import STYLES, StyleParams, draw_params

WORLD_FORMAT = 1

# Per sensor: azimuth columns to choose from, and ranges of the error parameters (m, degrees,
# fraction). Columns are per 0.1 s sweep: VLP-16 at 0.2 deg, OS1-64 in its 1024 and 2048 modes.
SENSOR_RANGES: dict[str, dict[str, tuple]] = {
    "hdl64": dict(num_columns=(2000,), range_noise=(0.01, 0.03), elevation_bias_deg=(0.0, 0.3),
                  beam_jitter_deg=(0.0, 0.02), dropout=(0.0, 0.05)),
    "vlp16": dict(num_columns=(1800,), range_noise=(0.02, 0.04), elevation_bias_deg=(-0.2, 0.2),
                  beam_jitter_deg=(0.0, 0.03), dropout=(0.0, 0.05)),
    "hdl32": dict(num_columns=(2200,), range_noise=(0.015, 0.03), elevation_bias_deg=(-0.2, 0.2),
                  beam_jitter_deg=(0.0, 0.03), dropout=(0.0, 0.05)),
    "os1-64": dict(num_columns=(1024, 2048), range_noise=(0.015, 0.05),
                   elevation_bias_deg=(-0.15, 0.15), beam_jitter_deg=(0.0, 0.03),
                   dropout=(0.0, 0.08)),
}  # fmt: skip
SPEED_RANGE = (0.75, 1.35)  # speed_scale: faster or slower than the recorded drive
DISTORTION_PROB = 0.85  # chance a drawn world has motion distortion, when not given


@dataclass(frozen=True)
class SensorSpec:
    """A sensor preset by name with its own error parameters (m, degrees, fraction)."""

    name: str
    num_columns: int
    range_noise: float  # 1-sigma at short range
    elevation_bias_deg: float  # rays leave this much higher than reported
    beam_jitter_deg: float  # 1-sigma per-shot angular error
    dropout: float  # chance a return is lost

    def __post_init__(self) -> None:
        if self.name not in SENSORS:
            raise InputError(
                None, f"unknown sensor {self.name!r}; choose one of {', '.join(SENSORS)}"
            )
        check_setting(is_int(self.num_columns, 8), "sensor.num_columns", "an integer >= 8",
                      self.num_columns)  # fmt: skip
        for name, lo, hi in (("range_noise", 0.0, 0.5), ("elevation_bias_deg", -2.0, 2.0),
                             ("beam_jitter_deg", 0.0, 1.0), ("dropout", 0.0, 0.99)):  # fmt: skip
            value = getattr(self, name)
            check_setting(_number(value) and lo <= value <= hi, f"sensor.{name}",
                          f"a number from {lo} to {hi}", value)  # fmt: skip

    def model(self, num_beams: int | None = None, num_columns: int | None = None) -> SensorModel:
        """The preset with these errors; ``num_beams`` / ``num_columns`` thin it for quick runs."""
        columns = self.num_columns if num_columns is None else num_columns
        base = get_sensor(self.name, num_beams=num_beams, num_columns=columns)
        return replace(base, range_noise=self.range_noise, dropout=self.dropout,
                       elevation_bias_deg=self.elevation_bias_deg,
                       beam_jitter_deg=self.beam_jitter_deg)  # fmt: skip


@dataclass(frozen=True)
class WorldSpec:
    """One sequence's world. ``trajectory``: the KITTI sequence id of the pose file driven
    along (frames ``[start, start + frames * speed_scale]`` of it), or ``"procedural"``."""

    seed: int  # the scene's and the noise's seed
    family: str
    scene: StyleParams
    sensor: SensorSpec
    motion_distortion: bool
    trajectory: str
    start: int
    frames: int
    speed_scale: float

    def __post_init__(self) -> None:
        check_setting(is_int(self.seed, 0), "seed", "an integer >= 0", self.seed)
        if self.family not in STYLES:
            raise InputError(None, f"unknown scene family {self.family!r}; choose one of "
                             f"{', '.join(STYLES)}")  # fmt: skip
        _check_scene(self.scene)
        check_setting(isinstance(self.motion_distortion, bool), "motion_distortion",
                      "true or false", self.motion_distortion)  # fmt: skip
        kitti_id = isinstance(self.trajectory, str) and self.trajectory.isdigit()
        rule = "a KITTI sequence id such as '07', or 'procedural'"
        check_setting(kitti_id or self.trajectory == "procedural", "trajectory", rule,
                      self.trajectory)  # fmt: skip
        check_setting(is_int(self.start, 0), "start", "an integer >= 0", self.start)
        check_setting(is_int(self.frames, 2), "frames", "an integer >= 2", self.frames)
        check_setting(_number(self.speed_scale) and 0.25 <= self.speed_scale <= 4.0,
                      "speed_scale", "a number from 0.25 to 4", self.speed_scale)  # fmt: skip

    def to_dict(self) -> dict:
        return {"format": WORLD_FORMAT, **json.loads(json.dumps(asdict(self)))}

    @classmethod
    def from_dict(cls, data: object) -> WorldSpec:
        """A world from :meth:`to_dict`'s output; InputError (no source) says what is wrong."""
        if not isinstance(data, dict):
            raise InputError(None, "a world must be a mapping of settings")
        data = dict(data)
        if data.pop("format", WORLD_FORMAT) != WORLD_FORMAT:
            raise InputError(None, f"world format must be {WORLD_FORMAT}")
        data.pop("drive", None)  # world.json's measured drive: an outcome, not a setting
        _check_keys(data, cls, "world")
        _check_keys(data["scene"], StyleParams, "scene")
        _check_keys(data["sensor"], SensorSpec, "sensor")
        pairs = {f.name for f in fields(StyleParams) if "tuple" in str(f.type)}
        scene = {k: tuple(v) if k in pairs and isinstance(v, list) else v
                 for k, v in data["scene"].items()}  # fmt: skip
        return cls(
            **{**data, "scene": StyleParams(**scene), "sensor": SensorSpec(**data["sensor"])}
        )

    def sensor_model(
        self, num_beams: int | None = None, num_columns: int | None = None
    ) -> SensorModel:
        """The world's sensor with its errors (see :meth:`SensorSpec.model`)."""
        return self.sensor.model(num_beams, num_columns)


def draw_world(
    seed: int,
    *,
    family: str,
    sensor: str,
    trajectory: str = "procedural",
    start: int = 0,
    frames: int = 60,
    motion_distortion: bool | None = None,
) -> WorldSpec:
    """A world of ``family`` seen by ``sensor``, its parameters drawn from ``seed`` inside the
    family's and the sensor's ranges (``styles.RANGES``, ``SENSOR_RANGES``, ``SPEED_RANGE``);
    motion distortion drawn (on with probability ``DISTORTION_PROB``) unless given."""
    check_setting(is_int(seed, 0), "seed", "an integer >= 0", seed)
    if family not in STYLES:
        raise InputError(
            None, f"unknown scene family {family!r}; choose one of {', '.join(STYLES)}"
        )
    if sensor not in SENSOR_RANGES:
        raise InputError(
            None, f"unknown sensor {sensor!r}; choose one of {', '.join(SENSOR_RANGES)}"
        )
    rng = np.random.default_rng([seed, 0x3021D])
    scene = draw_params(family, rng)
    r = SENSOR_RANGES[sensor]
    sensor_spec = SensorSpec(
        name=sensor,
        num_columns=int(rng.choice(r["num_columns"])),
        **{k: round(float(rng.uniform(*r[k])), 4) for k in
           ("range_noise", "elevation_bias_deg", "beam_jitter_deg", "dropout")},
    )  # fmt: skip
    distortion = bool(rng.random() < DISTORTION_PROB)
    speed = round(float(rng.uniform(*SPEED_RANGE)), 3)
    return WorldSpec(
        seed=seed,
        family=family,
        scene=scene,
        sensor=sensor_spec,
        motion_distortion=distortion if motion_distortion is None else motion_distortion,
        trajectory=trajectory,
        start=start,
        frames=frames,
        speed_scale=speed,
    )


def load_world(path: str | Path) -> WorldSpec:
    """A world from a JSON or YAML file (a sequence's ``world.json``); errors name the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise InputError(path, f"cannot read the world file ({err.strerror})") from None
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as err:
        first = str(err).splitlines()[0]
        raise InputError(
            path, f"not valid {'JSON' if path.suffix == '.json' else 'YAML'}: {first}"
        ) from None
    try:
        return WorldSpec.from_dict(data)
    except (InputError, TypeError) as err:
        raise InputError(path, getattr(err, "problem", str(err))) from None


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _check_keys(data: object, cls: type, what: str) -> None:
    if not isinstance(data, dict):
        raise InputError(None, f"{what} must be a mapping of settings, not {data!r}")
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(data) - set(names))
    missing = [n for n in names if n not in data and _required(cls, n)]
    if unknown:
        raise InputError(None, f"unknown {what} setting {unknown[0]!r}; known: {', '.join(names)}")
    if missing:
        raise InputError(None, f"{what} lacks {', '.join(missing)}")


def _required(cls: type, name: str) -> bool:
    f = next(f for f in fields(cls) if f.name == name)
    return f.default is f.default_factory  # both MISSING: no default


def _check_scene(p: StyleParams) -> None:
    for f in fields(StyleParams):
        value, name = getattr(p, f.name), f"scene.{f.name}"
        if f.name == "guard_rails":
            check_setting(isinstance(value, bool), name, "true or false", value)
        elif isinstance(value, tuple):
            ok = len(value) == 2 and all(_number(v) and v >= 0 for v in value)
            check_setting(ok and value[0] <= value[1], name, "a pair lo <= hi of numbers >= 0",
                          value)  # fmt: skip
        elif f.name == "cross_slope":
            check_setting(_number(value) and abs(value) <= 1, name, "a number from -1 to 1", value)
        else:
            check_setting(_number(value) and value >= 0, name, "a number >= 0", value)
    for name in ("building_density", "parked_car_prob", "hedge_fence_prob", "facade_detail",
                 "clutter_density"):  # fmt: skip
        check_setting(getattr(p, name) <= 1, f"scene.{name}", "a fraction from 0 to 1",
                      getattr(p, name))  # fmt: skip
    for name in ("tree_spacing", "pole_spacing", "actor_interval_s"):  # loops step by these
        check_setting(getattr(p, name) >= 0.5, f"scene.{name}", "a number >= 0.5", getattr(p, name))
