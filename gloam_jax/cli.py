"""The ``gloam`` command line: simulate, eval, demo."""

from __future__ import annotations

import functools
import json
import os
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Annotated, TypeVar

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from gloam_jax import __version__
from gloam_jax.errors import InputError

app = typer.Typer(
    help="gloam-jax: learned GICP LiDAR odometry in JAX, with a LiDAR simulator and KITTI tools.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)
console = Console()
err_console = Console(stderr=True, soft_wrap=True)
F = TypeVar("F", bound=Callable)


def _user_errors(fn: F) -> F:
    """Report bad input as one line and exit with status 2, instead of a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except InputError as err:
            err_console.print(f"[red]error:[/red] {err}", highlight=False)
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def _version(value: bool) -> None:
    if value:
        console.print(f"gloam-jax {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")
    ] = False,
) -> None:
    """gloam-jax command line."""


def _progress() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )


class _Tasks:
    """A progress callback ``(what, done, total)`` that gives each ``what`` its own bar."""

    def __init__(self, bar: Progress) -> None:
        self.bar, self.ids = bar, {}

    def __call__(self, what: str, done: int, total: int, rate: str = "") -> None:
        if what not in self.ids:
            self.ids[what] = self.bar.add_task(what, total=total, rate="")
        self.bar.update(self.ids[what], completed=done, rate=rate)


def _run_simulation(out: Path, frames: int, **kwargs) -> tuple[Path, float]:
    from gloam_jax.simulate import simulate as run_simulate

    t0 = time.perf_counter()
    with _progress() as bar:
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
@_user_errors
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
    seq_dir, elapsed = _run_simulation(
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


def _metrics_table(result: dict, title: str) -> Table:
    table = Table(title=title)
    table.add_column("segment (m)", justify="right")
    table.add_column("t_err (%)", justify="right")
    table.add_column("r_err (deg/100 m)", justify="right")
    table.add_column("segments", justify="right")
    for length, row in result["per_length"].items():
        table.add_row(
            length,
            f"{row['t_err_percent']:.3f}",
            f"{row['r_err_deg_per_100m']:.3f}",
            str(row["num_segments"]),
        )
    table.add_row(
        "[bold]all",
        f"[bold]{result['t_err_percent']:.3f}",
        f"[bold]{result['r_err_deg_per_100m']:.3f}",
        f"[bold]{result['num_segments']}",
    )
    return table


def _write_json(path: Path, data: dict) -> None:
    from gloam_jax.io import write_atomic

    write_atomic(path, json.dumps(data, indent=2))


@app.command(
    name="eval",
    epilog=(
        "Examples:\n\n"
        "  gloam eval data/sim/poses/00.txt results/latest/00_poses_kitti.txt\n\n"
        "  gloam eval GT.txt EST.txt --json metrics.json --plot errors.png"
    ),
)
@_user_errors
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
    console.print(_metrics_table(result, f"{est.name} vs {gt.name}"))
    ate = result["ate"]
    console.print(f"ATE (SE(3)-aligned): rmse {ate['rmse']:.3f} m, max {ate['max']:.3f} m")
    if json_out is not None:
        _write_json(json_out, result)
    if plot is not None:
        metrics.plot_evaluation(gt_poses, est_poses, None, plot, title=est.name)


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "gloam-jax"


def _run_dir(out: Path) -> Path:
    """A new timestamped folder's path under ``out``; the run creates it as it writes, so
    one that fails on bad input leaves nothing behind."""
    return out / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def _mark_latest(run_dir: Path) -> None:
    """Point ``out/latest`` at a finished run."""
    latest = run_dir.parent / "latest"
    if latest.is_symlink() or latest.exists():
        latest.unlink()
    latest.symlink_to(run_dir.name)


def _run_odometry(
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
    with _progress() as bar:
        task = bar.add_task(f"{config.method} {sequence}", total=total, rate="")

        def step(i: int, ms: float) -> None:
            bar.update(task, completed=i + 1, rate=f"{ms:.0f} ms/frame")

        result = run_sequence(
            data, sequence, config, run_dir, frames=frames, progress=step, features_dir=features
        )
    if "per_length" in result:
        console.print(_metrics_table(result, f"sequence {sequence}: estimate vs ground truth"))
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
@_user_errors
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
    run_dir = _run_dir(out)
    _run_odometry(data, sequence, settings, frames, run_dir, features)
    _mark_latest(run_dir)


@app.command(
    name="init-model",
    epilog="Example:\n\n  gloam init-model data/sim 05 07 --out model.npz",
)
@_user_errors
def init_model(
    data: Annotated[Path, typer.Argument(help="KITTI-layout root with training sequences.")],
    sequences: Annotated[list[str], typer.Argument(help="Training sequence ids.")],
    out: Annotated[Path, typer.Option(help="Model file to write (.npz).")] = Path("model.npz"),
    every: Annotated[int, typer.Option(min=1, help="Use every N-th scan for the PCA.")] = 25,
    backbone: Annotated[str, typer.Option(help="Feature backbone: geometric.")] = "geometric",
    features: Annotated[
        Path | None, typer.Option(help="Fit on per-scan feature files here instead.")
    ] = None,
    seed: Annotated[int, typer.Option(help="MLP initialisation seed.")] = 0,
    init: Annotated[
        str, typer.Option(help="random, or gicp (start near plain GICP, for training).")
    ] = "random",
) -> None:
    """Fit the frozen PCA on training scans and write a model file with untrained MLPs."""
    from gloam_jax.features import get_backbone
    from gloam_jax.models import save_model
    from gloam_jax.training.problem import fit_initial_model

    extractor = (
        get_backbone("precomputed", folder=features)
        if features is not None
        else get_backbone(backbone)
    )
    with _progress() as bar:
        step = _Tasks(bar)

        model = fit_initial_model(
            data,
            sequences,
            extractor,
            every=every,
            seed=seed,
            init=init,
            # A folder of files is the user's, not the model's: runs name theirs with --features.
            keep_backbone_options=features is None,
            progress=step,
        )
    save_model(out, model)
    console.print(
        f"PCA keeps {100 * float(sum(model.pca.explained_variance_ratio)):.1f} % of the "
        f"variance; model (untrained MLPs, {init} init, seed {seed}): {out}"
    )


@app.command(
    epilog=(
        "Examples:\n\n"
        "  gloam train --config configs/train_grad.yaml --out runs/grad\n\n"
        "  gloam train --mode tpe --config configs/train_tpe.yaml --out runs/tpe --trials 300\n\n"
        "Rerunning a command with the same --out resumes it."
    )
)
@_user_errors
def train(
    config: Annotated[
        Path | None, typer.Option(help="YAML training settings (configs/train_*.yaml).")
    ] = None,
    mode: Annotated[str | None, typer.Option(help="tpe or grad (overrides the config).")] = None,
    data: Annotated[
        Path | None, typer.Option(help="KITTI-layout root of the training sequences.")
    ] = None,
    out: Annotated[Path, typer.Option(help="Run folder (resumed when it exists).")] = Path(
        "runs/train"
    ),
    trials: Annotated[
        int | None, typer.Option("--trials", "--n-trials", min=1, help="TPE trials (overrides).")
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option(help="Seed of the start model, TPE's sampler and point subsets (overrides)."),
    ] = None,
    steps: Annotated[int | None, typer.Option(min=1, help="Gradient steps (overrides).")] = None,
    learning_rate: Annotated[
        float | None, typer.Option(min=0.0, help="Adam's learning rate (overrides).")
    ] = None,
    cache: Annotated[
        Path | None, typer.Option(help="Folder for prepared training windows (shared by runs).")
    ] = None,
) -> None:
    """Train the MLPs by TPE (the paper's black-box search) or by gradients through GICP."""
    import dataclasses

    from gloam_jax.config import load_config
    from gloam_jax.training.config import TrainConfig
    from gloam_jax.training.problem import setup

    cfg = load_config(config, TrainConfig)
    if mode is not None:
        if mode not in ("tpe", "grad"):
            raise InputError(None, f"--mode must be tpe or grad, not {mode!r}")
        cfg = dataclasses.replace(cfg, mode=mode)
    if data is not None:
        cfg = dataclasses.replace(cfg, data=str(data))
    if trials is not None:
        cfg = dataclasses.replace(cfg, tpe=dataclasses.replace(cfg.tpe, n_trials=trials))
    if seed is not None:
        cfg = dataclasses.replace(cfg, seed=seed)
    grad = {"steps": steps, "learning_rate": learning_rate}
    grad = {k: v for k, v in grad.items() if v is not None}
    cfg = dataclasses.replace(cfg, grad=dataclasses.replace(cfg.grad, **grad))
    with _progress() as bar:
        step = _Tasks(bar)

        problem = setup(cfg, out, cache_dir=cache, progress=step)
        label = "TPE trials" if cfg.mode == "tpe" else "gradient steps"

        def tick(done: int, total: int, best: float) -> None:
            step(label, done, total, rate=f"best t_err {100 * best:.3f} %")

        if cfg.mode == "tpe":
            from gloam_jax.training.tpe import train_tpe

            model = train_tpe(problem, tick)
        else:
            from gloam_jax.training.grad import train_grad

            model = train_grad(problem, tick)
    info = model.provenance
    console.print(
        f"{cfg.mode}: best training t_err {100 * info['train_t_err']:.3f} % "
        f"({info['wall_s']:.0f} s of training); model: {out / 'model.npz'}, "
        f"curve: {out / 'loss_curve.png'}"
    )


@app.command(epilog="Example:\n\n  gloam demo --frames 150 --out results")
@_user_errors
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

    data = _cache_dir() / f"demo-{__version__}-f{FORMAT_VERSION}-seed{seed}-n{frames}"
    seq_dir, elapsed = _run_simulation(data, frames, seed=seed, style="urban", sequence="00")
    console.print(f"simulated sequence: {seq_dir} ({elapsed:.1f} s; cached for the next run)")
    gicp, gloam = load_config("gicp"), load_config("gloam")  # the shipped configs/*.yaml
    run_dir = _run_dir(out)
    results = {
        c.method: _run_odometry(data, "00", c, None, run_dir / c.method) for c in (gicp, gloam)
    }
    _mark_latest(run_dir)
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


if __name__ == "__main__":
    app()
