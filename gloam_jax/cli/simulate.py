"""``gloam simulate``: a LiDAR sequence with ground truth, in the KITTI odometry layout."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer

from gloam_jax.cli.common import app, console, progress_bar, user_errors


def run_simulation(out: Path, total: int, **kwargs) -> tuple[Path, float]:
    """Simulate ``total`` scans with a progress bar; kwargs go to ``simulate`` (its ``frames``
    is ``total`` unless given: a world sets the count itself). Returns folder and seconds."""
    from gloam_jax.simulate import simulate as run_simulate

    kwargs.setdefault("frames", total)
    t0 = time.perf_counter()
    with progress_bar() as bar:
        task = bar.add_task("simulating", total=total, rate="")

        def step(i: int) -> None:
            fps = (i + 1) / max(time.perf_counter() - t0, 1e-9)
            bar.update(task, completed=i + 1, rate=f"{fps:.2f} frames/s")

        seq_dir = run_simulate(out, progress=step, **kwargs)
    return seq_dir, time.perf_counter() - t0


@app.command(
    epilog=(
        "Examples:\n\n"
        "  gloam simulate data/sim --frames 100\n\n"
        "  gloam simulate data/sim --trajectory ../shared/data/kitti_gt_poses/07.txt "
        "--start 0 --frames 300 --style suburban --sequence 07 --preview\n\n"
        "  gloam simulate data/sim --sensor vlp16 --no-motion-distortion --no-sensor-errors\n\n"
        "  gloam simulate data/sim2 --world data/protocol2/sequences/301/world.json "
        "--trajectory ../shared/data/kitti_gt_poses/00.txt --sequence 301"
    )
)
@user_errors
def simulate(
    out: Annotated[Path, typer.Argument(help="Dataset root; written as OUT/sequences/NN/...")],
    trajectory: Annotated[
        Path | None,
        typer.Option(help="KITTI pose file to drive along (camera-0 poses); default: procedural."),
    ] = None,
    world: Annotated[
        Path | None,
        typer.Option(
            help="World file (JSON/YAML, e.g. a sequence's world.json): sets the scene, "
            "sensor, window, seed, distortion; do not pass those as well."
        ),
    ] = None,
    start: Annotated[
        int | None, typer.Option(help="First pose of the window [default: 0].")
    ] = None,
    frames: Annotated[
        int | None, typer.Option(min=2, help="Number of scans [default: 100].")
    ] = None,
    sensor: Annotated[
        str | None, typer.Option(help="hdl64, vlp16 or os1-64 [default: hdl64].")
    ] = None,
    style: Annotated[
        str | None,
        typer.Option(help="urban, suburban, highway, forest or yard [default: urban]."),
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option(help="Scene and noise seed (output is deterministic) [default: 0]."),
    ] = None,
    sequence: Annotated[str, typer.Option(help="Sequence id to write.")] = "00",
    motion_distortion: Annotated[
        bool | None,
        typer.Option(help="Cast each column from its own pose (raw, skewed sweeps) [default: on]."),
    ] = None,
    moving_objects: Annotated[
        bool, typer.Option(help="Moving cars, cyclists, pedestrians.")
    ] = True,
    detail: Annotated[
        bool, typer.Option(help="Non-planar detail: window recesses, ledges, annexes.")
    ] = True,
    sensor_errors: Annotated[
        bool,
        typer.Option(help="Elevation bias, per-beam offsets, range noise, mixed pixels, dropout."),
    ] = True,
    beams: Annotated[
        int | None, typer.Option(help="Keep only this many beams (quick runs).")
    ] = None,
    columns: Annotated[int | None, typer.Option(help="Azimuth steps per sweep.")] = None,
    preview: Annotated[bool, typer.Option(help="Write bird's-eye PNGs to NN/preview/.")] = False,
) -> None:
    """Simulate a LiDAR sequence with ground truth, in the KITTI odometry layout."""
    from gloam_jax.simulate import ErrorSwitches, load_world

    spec = None if world is None else load_world(world)
    if motion_distortion is None:  # the world's, else on
        motion_distortion = True if spec is None else spec.motion_distortion
    switches = ErrorSwitches(motion_distortion, moving_objects, detail, sensor_errors)
    frames_total = spec.frames if spec is not None else (frames or 100)
    seq_dir, elapsed = run_simulation(
        out,
        frames_total,
        world=spec,
        frames=frames,
        trajectory=trajectory,
        start=start,
        sensor=sensor,
        style=style,
        seed=seed,
        sequence=sequence,
        switches=switches,
        num_beams=beams,
        num_columns=columns,
    )
    meta = json.loads((seq_dir / "simulation.json").read_text())
    ppf = meta["points_per_frame"]
    console.print(
        f"wrote {frames_total} frames to {seq_dir} in {elapsed:.1f} s "
        f"({frames_total / elapsed:.2f} frames/s); "
        f"points per frame: mean {ppf['mean']:.0f}, min {ppf['min']}, max {ppf['max']}"
        + ("" if spec is None else f"; world recorded in {seq_dir / 'world.json'}")
    )
    if preview:
        from gloam_jax.io import KittiSequence
        from gloam_jax.simulate.preview import render_previews

        paths = render_previews(KittiSequence(out, sequence), seq_dir / "preview")
        console.print("previews: " + ", ".join(str(p) for p in paths))
