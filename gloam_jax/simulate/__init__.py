"""LiDAR simulator: procedural street scenes, spinning-LiDAR beam models, KITTI-layout output."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from gloam_jax.errors import InputError
from gloam_jax.simulate.families import FAMILIES, build_scene
from gloam_jax.simulate.sensors import SENSORS, SensorModel, get_sensor
from gloam_jax.simulate.sequence import (
    ErrorSwitches,
    FrameScan,
    SimulationConfig,
    SweepSimulator,
    write_sequence,
)
from gloam_jax.simulate.spec import SensorSpec, WorldSpec, draw_world, load_world
from gloam_jax.simulate.styles import STYLES, StyleParams
from gloam_jax.simulate.trajectory import (
    Trajectory,
    load_kitti_trajectory,
    procedural_trajectory,
    with_speed,
)
from gloam_jax.simulate.world import CLASS_NAMES, Scene


def simulate(
    out: str | Path,
    *,
    world: WorldSpec | None = None,
    trajectory: str | Path | None = None,
    start: int | None = None,
    frames: int | None = None,
    sensor: str | None = None,
    style: str | None = None,
    seed: int | None = None,
    sequence: str = "00",
    switches: ErrorSwitches | None = None,
    num_beams: int | None = None,
    num_columns: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Simulate ``frames`` scans into ``out`` (KITTI odometry layout); returns the sequence dir.

    trajectory: a KITTI camera-0 pose file to drive along (window ``[start, start + frames)``),
    or None for a procedural drive. num_beams / num_columns thin the sensor for quick runs;
    switches: the error sources (all on by default). Defaults: start 0, frames 100, sensor
    hdl64, style urban, seed 0. ``world`` (see :mod:`gloam_jax.simulate.spec`) sets the
    scene, sensor, window, seed and motion distortion instead, and is recorded as world.json.
    """
    if world is not None:
        return _simulate_world(out, world, trajectory, sequence, switches, num_beams,
                               num_columns, progress,
                               given=dict(start=start, frames=frames, sensor=sensor,
                                          style=style, seed=seed))  # fmt: skip
    start, frames = 0 if start is None else start, 100 if frames is None else frames
    sensor, style = sensor or "hdl64", style or "urban"
    seed = 0 if seed is None else seed
    switches = ErrorSwitches() if switches is None else switches
    model = get_sensor(sensor, num_beams=num_beams, num_columns=num_columns)
    if trajectory is None:
        traj = procedural_trajectory(frames, seed)
    else:
        traj = load_kitti_trajectory(trajectory, start, frames)
    config = SimulationConfig(
        sequence=sequence,
        sensor=sensor,
        style=style,
        seed=seed,
        trajectory="procedural" if trajectory is None else str(Path(trajectory).resolve()),
        start=start,
        frames=frames,
        switches=switches,
        num_beams=model.num_beams,
        num_columns=model.num_columns,
    )
    return write_sequence(out, config, traj, model, progress=progress)


def _simulate_world(out, world, trajectory, sequence, switches, num_beams, num_columns,
                    progress, given) -> Path:  # fmt: skip
    clash = [name for name, value in given.items() if value is not None]
    if clash:
        raise InputError(None, f"the world sets {', '.join(clash)}: change them in the world")
    if switches is not None and switches.motion_distortion != world.motion_distortion:
        raise InputError(None, "the world sets motion distortion: change it in the world")
    if (trajectory is None) != (world.trajectory == "procedural") or (
        trajectory is not None and Path(trajectory).stem != world.trajectory
    ):
        wanted = "no pose file" if world.trajectory == "procedural" else f"{world.trajectory}.txt"
        raise InputError(trajectory, f"the world drives along {wanted}; pass that as trajectory")
    switches = ErrorSwitches() if switches is None else switches
    switches = replace(switches, motion_distortion=world.motion_distortion)
    model = world.sensor_model(num_beams, num_columns)
    # The recorded drive, resampled at 10 Hz after speeding it up: it spans more poses.
    span = int(np.ceil((world.frames - 1) * world.speed_scale)) + 2
    if trajectory is None:
        traj = procedural_trajectory(span, world.seed)
    else:
        traj = load_kitti_trajectory(trajectory, world.start, span)
    traj = with_speed(traj, world.speed_scale, world.frames)
    config = SimulationConfig(
        sequence=sequence,
        sensor=world.sensor.name,
        style=world.family,
        seed=world.seed,
        trajectory="procedural" if trajectory is None else str(Path(trajectory).resolve()),
        start=world.start,
        frames=world.frames,
        switches=switches,
        num_beams=model.num_beams,
        num_columns=model.num_columns,
        world=world,
    )
    return write_sequence(out, config, traj, model, progress=progress)


__all__ = [
    "CLASS_NAMES",
    "FAMILIES",
    "SENSORS",
    "STYLES",
    "ErrorSwitches",
    "FrameScan",
    "Scene",
    "SensorModel",
    "SensorSpec",
    "StyleParams",
    "SimulationConfig",
    "SweepSimulator",
    "Trajectory",
    "WorldSpec",
    "build_scene",
    "draw_world",
    "get_sensor",
    "load_kitti_trajectory",
    "load_world",
    "procedural_trajectory",
    "simulate",
    "with_speed",
    "write_sequence",
]
