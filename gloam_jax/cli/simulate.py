"""``gloam simulate``: a LiDAR sequence with ground truth, in the KITTI odometry layout."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer

from gloam_jax.cli.common import app, console, progress_bar, user_errors


def run_simulation(out: Path, frames: int, **kwargs) -> tuple[Path, float]:
    from gloam_jax.simulate import simulate as run_simulate

    t0 = time.perf_counter()
    with progress_bar() as bar:
        task = bar.add_task("simulating", total=frames, rate="")

        def step(i: int) -> None:
            fps = (i + 1) / max(time.perf_counter() - t0, 1e-9)
            bar.update(task, completed=i + 1, rate=f"{fps:.2f} frames/s")

        seq_dir = run_simulate(out, frames=frames, progress=step, **kwargs)
    return seq_dir, time.perf_counter() - t0


@app.command(
    epilog=(
        "Examples:\n\n"
        "  gloam simulate data/sim --frames 100\n\n"
        "  gloam simulate data/sim --trajectory ../shared/data/kitti_gt_poses/07.txt "
        "--start 0 --frames 300 --style suburban --sequence 07 --preview\n\n"
        "  gloam simulate data/sim --sensor vlp16 --no-motion-distortion --no-sensor-errors"
    )
)
@user_errors
def simulate(
    out: Annotated[Path, typer.Argument(help="Dataset root; written as OUT/sequences/NN/...")],
    trajectory: Annotated[
        Path | None,
        typer.Option(help="KITTI pose file to drive along (camera-0 poses); default: procedural."),
    ] = None,
    start: Annotated[int, typer.Option(help="First pose of the window.")] = 0,
    frames: Annotated[int, typer.Option(min=2, help="Number of scans.")] = 100,
    sensor: Annotated[str, typer.Option(help="hdl64, vlp16 or os1-64.")] = "hdl64",
    style: Annotated[str, typer.Option(help="urban, suburban or highway.")] = "urban",
    seed: Annotated[int, typer.Option(help="Scene and noise seed (output is deterministic).")] = 0,
    sequence: Annotated[str, typer.Option(help="Sequence id to write.")] = "00",
    motion_distortion: Annotated[
        bool, typer.Option(help="Cast each column from its own pose (raw, skewed sweeps).")
    ] = True,
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
    from gloam_jax.simulate import ErrorSwitches

    switches = ErrorSwitches(motion_distortion, moving_objects, detail, sensor_errors)
    seq_dir, elapsed = run_simulation(
        out,
        frames,
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
        f"wrote {frames} frames to {seq_dir} in {elapsed:.1f} s ({frames / elapsed:.2f} frames/s); "
        f"points per frame: mean {ppf['mean']:.0f}, min {ppf['min']}, max {ppf['max']}"
    )
    if preview:
        from gloam_jax.io import KittiSequence
        from gloam_jax.simulate.preview import render_previews

        paths = render_previews(KittiSequence(out, sequence), seq_dir / "preview")
        console.print("previews: " + ", ".join(str(p) for p in paths))
