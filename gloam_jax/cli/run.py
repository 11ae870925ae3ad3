"""``gloam run``, ``gloam eval`` and ``gloam demo``: odometry on a sequence, and its score."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from gloam_jax import __version__
from gloam_jax.cli.common import (
    app,
    cache_dir,
    console,
    metrics_table,
    progress_bar,
    run_folder,
    user_errors,
    write_json,
)
from gloam_jax.cli.simulate import run_simulation
from gloam_jax.errors import InputError


@app.command(
    name="eval",
    epilog=(
        "Examples:\n\n"
        "  gloam eval data/sim/poses/00.txt results/latest/00_poses_kitti.txt\n\n"
        "  gloam eval GT.txt EST.txt --json metrics.json --plot errors.png"
    ),
)
@user_errors
def eval_(
    gt: Annotated[Path, typer.Argument(help="Ground-truth KITTI pose file.")],
    est: Annotated[Path, typer.Argument(help="Estimated KITTI pose file (same length).")],
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the metrics here.")] = None,
    plot: Annotated[Path | None, typer.Option(help="Write a trajectory/error PNG here.")] = None,
    precision: Annotated[
        str, typer.Option(help="devkit (official float32 numbers) or float64 (exact).")
    ] = "devkit",
) -> None:
    """Score a trajectory exactly as the KITTI odometry devkit does (RTE), plus ATE."""
    from gloam_jax import io, metrics

    if precision not in ("devkit", "float64"):
        raise InputError(None, f"--precision must be devkit or float64, not {precision!r}")
    gt_poses, est_poses = io.read_kitti_poses(gt), io.read_kitti_poses(est)
    if len(gt_poses) != len(est_poses):
        raise InputError(est, f"{len(est_poses)} poses vs {len(gt_poses)} in {gt}")
    result = metrics.evaluate(gt_poses, est_poses, precision=precision, source=str(est))
    console.print(metrics_table(result, f"{est.name} vs {gt.name}"))
    ate = result["ate"]
    console.print(f"ATE (SE(3)-aligned): rmse {ate['rmse']:.3f} m, max {ate['max']:.3f} m")
    if json_out is not None:
        write_json(json_out, result)
    if plot is not None:
        metrics.plot_evaluation(gt_poses, est_poses, None, plot, title=est.name)


def run_odometry(
    data: Path,
    sequence: str,
    config,
    frames: int | None,
    run_dir: Path,
    features: Path | None = None,
) -> dict:
    from gloam_jax.io import KittiSequence
    from gloam_jax.pipeline import run_sequence

    total = len(KittiSequence(data, sequence)) if frames is None else frames
    with progress_bar() as bar:
        task = bar.add_task(f"{config.method} {sequence}", total=total, rate="")

        def step(i: int, ms: float) -> None:
            bar.update(task, completed=i + 1, rate=f"{ms:.0f} ms/frame")

        result = run_sequence(
            data, sequence, config, run_dir, frames=frames, progress=step, features_dir=features
        )
    if "per_length" in result:
        console.print(metrics_table(result, f"sequence {sequence}: estimate vs ground truth"))
    elif "rte_unavailable" in result:
        console.print(f"RTE unavailable ({result['rte_unavailable']})")
    if "ate" in result:
        console.print(f"ATE (SE(3)-aligned): rmse {result['ate']['rmse']:.3f} m")
    flagged = len(result["degenerate_frames"]) + len(result["bad_input_frames"])
    console.print(
        f"median {result['median_ms_per_frame']:.1f} ms/frame; {flagged} frame(s) fell back on "
        f"the motion prior; results: {run_dir}"
    )
    return result


@app.command(
    epilog=(
        "Examples:\n\n"
        "  gloam run data/sim --sequence 00\n\n"
        "  gloam run /data/kitti --sequence 07 --config configs/gicp.yaml --frames 500 "
        "--out results/gicp\n\n"
        "  gloam run data/sim --sequence 00 --config configs/gloam.yaml --weights model.npz"
    )
)
@user_errors
def run(
    data: Annotated[Path, typer.Argument(help="KITTI-layout root (sequences/, poses/).")],
    sequence: Annotated[str, typer.Option(help="Sequence id, e.g. 00.")] = "00",
    config: Annotated[
        Path | None,
        typer.Option(help="YAML settings: a file, or a shipped config's name (gicp, gloam, ...)."),
    ] = None,
    frames: Annotated[int | None, typer.Option(min=2, help="Only the first N scans.")] = None,
    out: Annotated[Path, typer.Option(help="Results root; a timestamped run inside.")] = Path(
        "results"
    ),
    weights: Annotated[
        Path | None, typer.Option(help="Model file for the learned methods (gloam init-model).")
    ] = None,
    features: Annotated[
        Path | None,
        typer.Option(help="Folder of per-scan features (NNNNNN.npy/.txt) instead of the model's."),
    ] = None,
) -> None:
    """Run LiDAR odometry on a KITTI-layout sequence (real or simulated) and score it."""
    import dataclasses

    from gloam_jax.config import load_config

    settings = load_config(config)
    if weights is not None:
        settings = dataclasses.replace(settings, model=str(weights))
    with run_folder(out) as run_dir:
        run_odometry(data, sequence, settings, frames, run_dir, features)


@app.command(epilog="Example:\n\n  gloam demo --frames 150 --out results")
@user_errors
def demo(
    frames: Annotated[
        int, typer.Option(min=20, help="Scans to simulate (>100 m of driving).")
    ] = 150,
    out: Annotated[Path, typer.Option(help="Results folder (a timestamped run inside).")] = Path(
        "results"
    ),
    seed: Annotated[int, typer.Option(help="Scene seed.")] = 0,
) -> None:
    """Simulate a short urban drive (cached), run GICP and Generalized LOAM (the shipped
    model) odometry on it, and score both."""
    from gloam_jax.config import load_config
    from gloam_jax.simulate.sequence import FORMAT_VERSION

    data = cache_dir() / f"demo-{__version__}-f{FORMAT_VERSION}-seed{seed}-n{frames}"
    seq_dir, elapsed = run_simulation(data, frames, seed=seed, style="urban", sequence="00")
    console.print(f"simulated sequence: {seq_dir} ({elapsed:.1f} s; cached for the next run)")
    gicp, gloam = load_config("gicp"), load_config("gloam")  # the shipped configs/*.yaml
    with run_folder(out) as run_dir:
        results = {
            c.method: run_odometry(data, "00", c, None, run_dir / c.method) for c in (gicp, gloam)
        }
    table = Table(title="GICP vs Generalized LOAM on the demo drive")
    for column in ("method", "t_err (%)", "r_err (deg/100 m)", "ATE rmse (m)", "ms/frame"):
        table.add_column(column, justify="right")
    for method, r in results.items():
        if "t_err_percent" not in r:
            continue
        table.add_row(
            method, f"{r['t_err_percent']:.3f}", f"{r['r_err_deg_per_100m']:.3f}",
            f"{r['ate']['rmse']:.3f}", f"{r['median_ms_per_frame']:.0f}",
        )  # fmt: skip
    console.print(table)
