"""Spinning-LiDAR beam models.

A sensor sweeps 360 deg clockwise seen from above in ``sweep_s`` seconds, starting and ending
behind the vehicle, so that it faces forward (+x) at mid-sweep, as the KITTI HDL-64E does when
the cameras are triggered. Column ``c`` of ``num_columns`` is fired at the normalised time
``u = (c + 0.5) / num_columns`` and azimuth ``pi * (1 - 2 u)`` (radians, counter-clockwise from
+x), so ``u = 0.5 * (1 - azimuth / pi)``: the convention KISS-ICP uses for KITTI.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from gloam_jax.errors import InputError, check_setting, is_int


@dataclass(frozen=True)
class SensorModel:
    """Geometry and error model of a spinning LiDAR. Angles in degrees, lengths in metres."""

    name: str
    elevations_deg: tuple[float, ...]  # nominal beam elevations, top to bottom
    num_columns: int  # azimuth steps per sweep
    max_range: float
    min_range: float
    mount_height: float  # above the road
    sweep_s: float = 0.1
    range_noise: float = 0.02  # 1-sigma at short range, normal incidence
    range_noise_per_m: float = 2e-4  # added sigma per metre of range
    elevation_bias_deg: float = 0.22  # systematic: rays leave this much higher than reported
    beam_range_offset_std: float = 0.015  # per-beam constant range offset, drawn from the seed
    dropout: float = 0.02  # random loss of returns
    beam_jitter_deg: float = 0.0  # 1-sigma angular error of each shot, elevation and azimuth
    intensity_noise: float = 0.02  # 1-sigma, on intensities in [0, 1]
    mixed_pixel_prob: float = 0.3  # chance a depth-edge return lands between the two surfaces
    mixed_pixel_gap: float = 0.5  # depth jump (m) that counts as an edge

    @property
    def num_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def num_rays(self) -> int:
        return self.num_beams * self.num_columns

    def column_times(self) -> np.ndarray:
        """Firing time of each column relative to mid-sweep, seconds: (num_columns,)."""
        u = (np.arange(self.num_columns) + 0.5) / self.num_columns
        return (u - 0.5) * self.sweep_s

    def column_azimuths(self) -> np.ndarray:
        """Azimuth of each column, radians, decreasing from +pi to -pi: (num_columns,)."""
        u = (np.arange(self.num_columns) + 0.5) / self.num_columns
        return np.pi * (1.0 - 2.0 * u)

    def directions(
        self,
        elevation_offset_deg: float | np.ndarray = 0.0,
        azimuth_offset_deg: float | np.ndarray = 0.0,
    ) -> np.ndarray:
        """Unit ray directions in the sensor frame, column-major: (num_columns, num_beams, 3).

        The offsets (degrees) are scalars or per ray, (num_columns, num_beams).
        """
        el = np.deg2rad(np.asarray(self.elevations_deg)[None, :] + elevation_offset_deg)
        az = self.column_azimuths()[:, None] + np.deg2rad(azimuth_offset_deg)
        return np.stack(
            [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0.0 * az], axis=-1
        )

    def without_errors(self) -> SensorModel:
        """The same geometry with every sensor imperfection switched off."""
        return replace(
            self,
            range_noise=0.0,
            range_noise_per_m=0.0,
            elevation_bias_deg=0.0,
            beam_range_offset_std=0.0,
            dropout=0.0,
            intensity_noise=0.0,
            mixed_pixel_prob=0.0,
            beam_jitter_deg=0.0,
        )


def _hdl64_elevations() -> tuple[float, ...]:
    # Two laser blocks: the upper 32 finely spaced (+2.0 .. -8.33), the lower 32 coarser
    # (-8.83 .. -24.8), as on the HDL-64E S2.
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return tuple(float(e) for e in np.concatenate([upper, lower]))


SENSORS: dict[str, SensorModel] = {
    "hdl64": SensorModel(
        name="hdl64",
        elevations_deg=_hdl64_elevations(),
        num_columns=2000,
        max_range=120.0,
        min_range=2.5,
        mount_height=1.73,
    ),
    "vlp16": SensorModel(
        name="vlp16",
        elevations_deg=tuple(float(e) for e in np.linspace(15.0, -15.0, 16)),
        num_columns=1800,
        max_range=100.0,
        min_range=1.0,
        mount_height=1.73,
        range_noise=0.03,
        elevation_bias_deg=0.0,
    ),
    # Velodyne HDL-32E: 32 beams 1.33 deg apart over +10.67 .. -30.67 deg, about 0.16 deg
    # between columns at 10 Hz. A training-only sensor (docs/worlds.md): its ring spacing lies
    # between the HDL-64's and the VLP-16's.
    "hdl32": SensorModel(
        name="hdl32",
        elevations_deg=tuple(float(e) for e in np.linspace(10.67, -30.67, 32)),
        num_columns=2200,
        max_range=100.0,
        min_range=1.0,
        mount_height=1.73,
        range_noise=0.02,
        elevation_bias_deg=0.0,
    ),
    # Ouster OS1-64: 64 beams spaced uniformly over +-16.6 deg, 1024 (or 2048) columns.
    "os1-64": SensorModel(
        name="os1-64",
        elevations_deg=tuple(float(e) for e in np.linspace(16.6, -16.6, 64)),
        num_columns=1024,
        max_range=120.0,
        min_range=1.0,
        mount_height=1.73,
        range_noise=0.03,
        elevation_bias_deg=0.0,
    ),
}


def get_sensor(
    name: str, *, num_beams: int | None = None, num_columns: int | None = None
) -> SensorModel:
    """A preset by name, optionally thinned (every k-th beam, fewer columns) for quick tests."""
    if name not in SENSORS:
        raise InputError(None, f"unknown sensor {name!r}; choose one of {', '.join(SENSORS)}")
    sensor = SENSORS[name]
    if num_beams is not None:
        check_setting(is_int(num_beams, 1) and num_beams <= sensor.num_beams, "num_beams",
                      f"an integer from 1 to {sensor.num_beams} ({name})", num_beams)  # fmt: skip
        idx = np.round(np.linspace(0, sensor.num_beams - 1, num_beams)).astype(int)
        sensor = replace(sensor, elevations_deg=tuple(sensor.elevations_deg[i] for i in idx))
    if num_columns is not None:
        check_setting(is_int(num_columns, 8), "num_columns", "an integer >= 8", num_columns)
        sensor = replace(sensor, num_columns=int(num_columns))
    return sensor
