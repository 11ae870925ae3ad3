"""``gloam run``, ``gloam eval`` and ``gloam demo``: odometry on a sequence, and its score."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from gloam_jax import __version__
from gloam_jax.cli.common import (
    CACHE_HELP,
    DataArg,
    SequenceOpt,
    StartOpt,
    StrideOpt,
    TopicOpt,
    app,
    cache_dir,
    console,
    error_lines,
    frame_progress,
    mark_latest,
    metrics_table,
    run_folder,
    use_compilation_cache,
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
    try:
        result = metrics.evaluate(gt_poses, est_poses, precision=precision, source=str(est))
    except InputError as err:  # a path too short for the devkit's segments: no RTE, as run
        if len(gt_poses) < 2 or "segment" not in err.problem:
            raise
        result = metrics.evaluate_without_rte(gt_poses, est_poses, err.problem, source=str(est))
        console.print(f"RTE unavailable ({err.problem})")
    else:
        console.print(metrics_table(result, f"{est.name} vs {gt.name}"))
    for line in error_lines(result):
        console.print(line)
    if json_out is not None:
        write_json(json_out, result)
    if plot is not None:
        if "rte_unavailable" in result:
            from gloam_jax.metrics import plot_trajectory

            plot_trajectory(est_poses, gt_poses, plot, f"{est.name}: ATE only")
        else:
            metrics.plot_evaluation(gt_poses, est_poses, None, plot, title=est.name)


def run_odometry(
    data: Path,
    sequence: str | None,
    config,
    run_dir: Path,
    features: Path | None = None,
    *,
    start: int = 0,
    frames: int | None = None,
    stride: int = 1,
    topic: str | None = None,
    on_bad_scan: str = "stop",
    resume=None,
    flush_every: int = 100,
) -> dict:
    """``gloam run`` into ``run_dir`` (``resume``: continuing that folder's Checkpoint), with
    its summary; an interrupt exits with 130 (SIGINT) or 143 (SIGTERM), the poses kept."""
    from gloam_jax.datasets import open_dataset
    from gloam_jax.interrupt import Terminated
    from gloam_jax.pipeline import run_dataset, select_frames

    dataset = open_dataset(data, sequence, topic=topic)
    chosen = select_frames(len(dataset), start, frames, stride)
    console.print(
        f"{dataset.kind} data {data} ({dataset.name}): {len(chosen)} of {len(dataset)} scans"
    )
    for key, value in dataset.details.items():
        console.print(f"  {key}: {value}", highlight=False)
    for note in dataset.defaults:
        console.print(f"  default: {note}")
    if resume is not None:
        console.print(f"  resuming {run_dir}: {resume.ended}")
    which = (f" --sequence {sequence}" if sequence else "") + (f" --topic {topic}" if topic else "")
    again = f"gloam run {data}{which} --resume {run_dir}"
    try:
        with frame_progress(f"{config.method} {dataset.name}", len(chosen)) as step:
            result = run_dataset(dataset, config, run_dir, chosen, progress=step,
                                 features_dir=features, on_bad_scan=on_bad_scan,
                                 resume=resume, flush_every=flush_every)  # fmt: skip
    except KeyboardInterrupt as stop:
        written = _frames_written(run_dir)
        if written:
            console.print(f"interrupted: {written} frames written to {run_dir}; go on: {again}")
        else:
            console.print("interrupted before the first frames were written")
        raise typer.Exit(143 if isinstance(stop, Terminated) else 130) from None
    except InputError:
        if written := _frames_written(run_dir):
            console.print(f"{written} frames written to {run_dir}; after a fix, or to skip "
                          f"the scan: {again} --on-bad-scan skip")  # fmt: skip
        raise
    console.print(f"  {result['deskew']['reason']}")
    if result["map"]["setting"] == "auto":  # resolved by the scans' sensor: say how
        console.print(f"  local map: {result['map']['reason']}")
    choice = result["model_choice"]
    if "decision" in choice:  # a learned method: which model ran, on which sensor, and why
        from gloam_jax.sensor import SensorSignature

        found = choice["sensor"]
        described = "not measured" if found is None else SensorSignature.from_dict(found).describe()
        console.print(f"  model: {choice['model'] or 'none'}, method {choice['method']}")
        console.print(f"  sensor of the scans: {described}")
        console.print(f"  {choice['decision']}: {choice['reason']}")
    for warning in result.get("warnings", []):
        console.print(f"  warning: {warning}")
    if "per_length" in result:
        console.print(metrics_table(result, f"{dataset.name}: estimate vs ground truth"))
    elif "rte_unavailable" in result:
        console.print(f"RTE unavailable ({result['rte_unavailable']})")
    for line in error_lines(result):
        console.print(line)
    if result["skipped_frames"]:
        skipped = ", ".join(map(str, result["skipped_frames"]))
        console.print(f"  skipped (bad scans, motion prior kept): frame(s) {skipped}")
    if result["frames_after_a_gap"]:
        console.print(f"  {len(result['frames_after_a_gap'])} gap(s) in the scan times (dropped "
                      "scans), predicted over the real time step")  # fmt: skip
    flagged = len(result["degenerate_frames"]) + len(result["bad_input_frames"])
    console.print(
        f"median {result['median_ms_per_frame']:.1f} ms/frame; {flagged} frame(s) fell back on "
        f"the motion prior; results: {run_dir}"
    )
    return result


def _frames_written(run_dir: Path) -> int:
    """How many frames' poses a run folder holds (its metrics.json says)."""
    import json

    metrics = run_dir / "metrics.json"
    return json.loads(metrics.read_text()).get("frames_done", 0) if metrics.exists() else 0


def method_settings(config: Path | None, method: str | None, weights: Path | None):
    """The settings of ``--config`` or ``--method`` (a shipped config), with ``--weights``;
    weights for a method that learns nothing are an error, not ignored."""
    import dataclasses

    from gloam_jax.config import load_config
    from gloam_jax.learned import METHODS

    if config is not None and method is not None:
        raise InputError(None, "give --method or --config, not both")
    if method is not None and method not in METHODS:
        raise InputError(None, f"unknown --method '{method}' (one of {', '.join(METHODS)})")
    settings = load_config(method if method is not None else config)
    if weights is not None:
        if not any(METHODS[settings.method]):
            raise InputError(
                weights,
                f"method '{settings.method}' learns nothing, so it takes no --weights "
                "(use gicp_da, gicp_ce or gloam)",
            )
        settings = dataclasses.replace(settings, model=str(weights))
    return settings


@app.command(
    epilog=(
        "Examples:\n\n"
        "  gloam run data/sim --sequence 00\n\n"
        "  gloam run ../shared/data/real_kitti16   (any folder of .bin/.pcd/.ply/.npy scans)\n\n"
        "  gloam run drive.bag --topic /ouster/points   (ROS 1 or 2 bag, or .mcap)\n\n"
        "  gloam run /data/kitti --sequence 07 --method gloam --start 100 --frames 500 "
        "--stride 2 --out results/gloam\n\n"
        "  gloam run data/sim --sequence 00 --method gloam --weights model.npz\n\n"
        "  gloam run /data/drive --resume results/2026-01-01_12-00-00 --on-bad-scan skip"
    )
)
@user_errors
def run(
    data: DataArg,
    sequence: SequenceOpt = None,
    topic: TopicOpt = None,
    method: Annotated[
        str | None,
        typer.Option(help="gicp, gicp_da, gicp_ce or gloam: the shipped settings of that method."),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="YAML settings: a file, or a shipped config's name (gicp, gloam, ...)."),
    ] = None,
    start: StartOpt = 0,
    frames: Annotated[int | None, typer.Option(min=2, help="At most N scans.")] = None,
    stride: StrideOpt = 1,
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
    on_bad_scan: Annotated[
        str,
        typer.Option(
            help="A scan that cannot be read or is wrong (damaged, in millimetres): stop there "
            "(naming it; the poses before it are kept) or skip it (its pose from the motion "
            "prior, flagged in frames.json)."
        ),
    ] = "stop",
    resume: Annotated[
        Path | None,
        typer.Option(
            help="Continue this unfinished run folder (interrupted, killed or stopped) from its "
            "last written frame, with its own settings and frames."
        ),
    ] = None,
    flush_every: Annotated[
        int, typer.Option(min=1, max=100, help="Frames between two writes of the poses.")
    ] = 100,
    compilation_cache: Annotated[bool, typer.Option(help=CACHE_HELP)] = True,
) -> None:
    """Run LiDAR odometry on a KITTI sequence, a folder of scans (real or simulated) or a
    ROS bag / MCAP recording, and score it when ground truth exists. Poses are written every
    100 frames and on Ctrl-C or SIGTERM; --resume continues such a run."""
    if on_bad_scan not in ("stop", "skip"):
        raise InputError(None, f"--on-bad-scan must be stop or skip, not {on_bad_scan!r}")
    if compilation_cache:
        use_compilation_cache()
    if resume is not None:
        resume_run(data, sequence, topic, resume, on_bad_scan, flush_every,
                   {"--method": method, "--config": config, "--weights": weights,
                    "--features": features, "--start": start or None, "--frames": frames,
                    "--stride": None if stride == 1 else stride})  # fmt: skip
        return
    settings = method_settings(config, method, weights)
    from gloam_jax.pipeline import unfinished_runs

    for unfinished, ended in unfinished_runs(out).items():
        console.print(f"note: {unfinished} was {ended}; --resume {unfinished} continues it")
    with run_folder(out) as run_dir:
        run_odometry(data, sequence, settings, run_dir, features, start=start, frames=frames,
                     stride=stride, topic=topic, on_bad_scan=on_bad_scan,
                     flush_every=flush_every)  # fmt: skip


def resume_run(data: Path, sequence: str | None, topic: str | None, run_dir: Path,
               on_bad_scan: str, flush_every: int, given: dict) -> None:  # fmt: skip
    """Continue the unfinished run in ``run_dir`` with the settings and frames it recorded;
    ``given``: the other options on the command line, which must be left out."""
    from gloam_jax.config import load_config
    from gloam_jax.pipeline import Checkpoint

    named = [name for name, value in given.items() if value is not None]
    if named:
        raise InputError(
            None, f"--resume continues a run with its own settings and frames: leave out "
            f"{', '.join(named)}"
        )  # fmt: skip
    checkpoint = Checkpoint.read(run_dir)
    record = checkpoint.record
    features = None if record["features_dir"] is None else Path(record["features_dir"])
    run_odometry(data, sequence, load_config(run_dir / "config.yaml"), run_dir, features,
                 start=record["start"], frames=record["count"], stride=record["stride"],
                 topic=topic, on_bad_scan=on_bad_scan, resume=checkpoint,
                 flush_every=flush_every)  # fmt: skip
    mark_latest(run_dir)


@app.command(epilog="Example:\n\n  gloam demo --frames 400 --out results")
@user_errors
def demo(
    frames: Annotated[
        int, typer.Option(min=20, help="Scans to simulate (400: 350 m, devkit segments to 300 m).")
    ] = 400,
    out: Annotated[Path, typer.Option(help="Results folder (a timestamped run inside).")] = Path(
        "results"
    ),
    seed: Annotated[int, typer.Option(help="Scene seed.")] = 0,
    compilation_cache: Annotated[bool, typer.Option(help=CACHE_HELP)] = True,
) -> None:
    """Simulate an urban drive (cached), run GICP and Generalized LOAM (the shipped model)
    odometry on it, and score both on the devkit's segments."""
    from gloam_jax.config import load_config
    from gloam_jax.simulate.sequence import FORMAT_VERSION

    if compilation_cache:
        use_compilation_cache()
    data = cache_dir() / f"demo-{__version__}-f{FORMAT_VERSION}-seed{seed}-n{frames}"
    seq_dir, elapsed = run_simulation(data, frames, seed=seed, style="urban", sequence="00")
    console.print(f"simulated sequence: {seq_dir} ({elapsed:.1f} s; cached for the next run)")
    gicp, gloam = load_config("gicp"), load_config("gloam")  # the shipped configs/*.yaml
    with run_folder(out) as run_dir:
        results = {c.method: run_odometry(data, "00", c, run_dir / c.method) for c in (gicp, gloam)}
    table = Table(title="GICP vs Generalized LOAM on the demo drive")
    columns = ("method", "t_err (%)", "r_err (deg/100 m)", "ATE rmse (m)", "ms/frame, registration",
               "ms/frame, features")  # fmt: skip
    for column in columns:
        table.add_column(column, justify="right")
    for method, r in results.items():
        if "t_err_percent" not in r:
            continue
        features = r.get("median_ms_features")  # the backbone's, on the host: learned methods
        table.add_row(
            method, f"{r['t_err_percent']:.3f}", f"{r['r_err_deg_per_100m']:.3f}",
            f"{r['ate']['rmse']:.3f}", f"{r['median_ms_per_frame']:.0f}",
            "-" if features is None else f"{features:.0f}",
        )  # fmt: skip
    console.print(table)
