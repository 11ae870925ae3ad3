"""LiDAR simulator: procedural street scenes, spinning-LiDAR beam models, KITTI-layout output."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from gloam_jax.simulate.scene import STYLES, build_scene
from gloam_jax.simulate.sensors import SENSORS, SensorModel, get_sensor
from gloam_jax.simulate.sequence import (
    ErrorSwitches,
    FrameScan,
    SimulationConfig,
    SweepSimulator,
    write_sequence,
)
from gloam_jax.simulate.trajectory import (
    Trajectory,
    load_kitti_trajectory,
    procedural_trajectory,
)
from gloam_jax.simulate.world import CLASS_NAMES, Scene


def simulate(
    out: str | Path,
    *,
    trajectory: str | Path | None = None,
    start: int = 0,
    frames: int = 100,
    sensor: str = "hdl64",
    style: str = "urban",
    seed: int = 0,
    sequence: str = "00",
    switches: ErrorSwitches | None = None,
    num_beams: int | None = None,
    num_columns: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Simulate ``frames`` scans into ``out`` (KITTI odometry layout); returns the sequence dir.

    trajectory: a KITTI camera-0 pose file to drive along (window ``[start, start + frames)``),
    or None for a procedural drive. num_beams / num_columns thin the sensor for quick runs;
    switches: the error sources (all on by default).
    """
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


__all__ = [
    "CLASS_NAMES",
    "SENSORS",
    "STYLES",
    "ErrorSwitches",
    "FrameScan",
    "Scene",
    "SensorModel",
    "SimulationConfig",
    "SweepSimulator",
    "Trajectory",
    "build_scene",
    "get_sensor",
    "load_kitti_trajectory",
    "procedural_trajectory",
    "simulate",
    "write_sequence",
]
