"""What the ``gloam`` commands share: the app, consoles, one-line errors, progress, run folders.

Heavy modules (JAX, the pipeline, training) are imported inside the commands, so that
``gloam --version`` and ``--help`` start at once.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import json
import os
import sys
import time
from collections.abc import Callable, Iterator
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


def user_errors(fn: F) -> F:
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


def progress_bar() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )


@contextlib.contextmanager
def frame_progress(description: str, total: int, every: int | None = None) -> Iterator[Callable]:
    """A progress callback ``(k, ms)`` for ``total`` frames: rich's bar on a terminal; plain
    lines otherwise (nohup, SLURM, CI logs), every ``every`` frames (default: a tenth of the
    run, at most 100) and at the end, with frames/s and the time left."""
    if console.is_terminal:
        with progress_bar() as bar:
            task = bar.add_task(description, total=total, rate="")

            def step(k: int, ms: float) -> None:
                bar.update(task, completed=k + 1, rate=f"{ms:.0f} ms/frame")

            yield step
        return
    every = every or max(1, min(100, total // 10))
    start = time.perf_counter()

    def line(k: int, ms: float) -> None:
        done = k + 1
        if done % every and done != total:
            return
        elapsed = time.perf_counter() - start
        rate = done / elapsed if elapsed > 0 else float("inf")
        eta = (total - done) / rate if rate > 0 else 0.0
        print(
            f"{description}: frame {done}/{total} ({100 * done / total:.0f} %), "
            f"{rate:.1f} frames/s, {ms:.0f} ms last frame, ETA {eta:.0f} s",
            file=sys.stdout,
            flush=True,
        )

    yield line


# The scans a command reads, as `gloam run` and `gloam segment` take them.
DataArg = Annotated[
    Path,
    typer.Argument(
        help="KITTI root (sequences/, poses/), a folder of scans, a ROS 1 bag (.bag), a ROS 2 "
        "bag folder or an MCAP file (.mcap)."
    ),
]
SequenceOpt = Annotated[
    str | None, typer.Option(help="KITTI sequence id, e.g. 00 (needed when several).")
]
TopicOpt = Annotated[
    str | None,
    typer.Option(help="PointCloud2 topic of a ROS bag or MCAP file (needed when several)."),
]
StartOpt = Annotated[int, typer.Option(min=0, help="First scan (index).")]
StrideOpt = Annotated[int, typer.Option(min=1, help="Every k-th scan.")]


COMPILATION_CACHE_ENV = "GLOAM_COMPILATION_CACHE"
CACHE_HELP = (
    "JAX's persistent compilation cache (in the user cache folder): a second run compiles "
    "less. Also off with GLOAM_COMPILATION_CACHE=0."
)


def use_compilation_cache(enabled: bool | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache under ``cache_dir()/jax`` (so a second run
    skips most of the first frames' compilation); returns the folder, or None when off.

    ``enabled`` None follows the environment: ``GLOAM_COMPILATION_CACHE=0`` turns it off.
    Every compilation is kept: JAX's default keeps only those over 1 s, which leaves most of
    the first frames' many small ones to compile again (the cache stays small).
    """
    if enabled is None:
        enabled = os.environ.get(COMPILATION_CACHE_ENV, "1").lower() not in (
            "0",
            "false",
            "no",
            "off",
        )
    if not enabled:
        return None
    import jax

    folder = cache_dir() / "jax"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # an unwritable cache only costs speed
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder


class Tasks:
    """A progress callback ``(what, done, total)`` that gives each ``what`` its own bar."""

    def __init__(self, bar: Progress) -> None:
        self.bar, self.ids = bar, {}

    def __call__(self, what: str, done: int, total: int, rate: str = "") -> None:
        if what not in self.ids:
            self.ids[what] = self.bar.add_task(what, total=total, rate="")
        self.bar.update(self.ids[what], completed=done, rate=rate)


def metrics_table(result: dict, title: str) -> Table:
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


def error_lines(result: dict) -> list[str]:
    """The ATE and per-frame rotation drift lines of an evaluation (``metrics.evaluate``)."""
    lines = []
    if "ate" in result:
        ate = result["ate"]
        lines.append(f"ATE (SE(3)-aligned): rmse {ate['rmse']:.3f} m, max {ate['max']:.3f} m")
    drift = result.get("frame_rotation")
    if drift is not None:
        mean = " ".join(f"{v:+.2f}" for v in drift["mean_mdeg"])
        spread = " ".join(f"{v:.1f}" for v in drift["std_mdeg"])
        lines.append(
            f"rotation error a frame about x y z (KITTI: pitch yaw roll): drift {mean} mdeg "
            f"(mean), noise {spread} mdeg (std)"
        )
    return lines


def write_json(path: Path, data: dict) -> None:
    from gloam_jax.io import write_atomic

    write_atomic(path, json.dumps(data, indent=2))


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "gloam-jax"


@contextlib.contextmanager
def run_folder(out: Path) -> Iterator[Path]:
    """A new run folder under ``out``, made before the work starts (so an unwritable ``out``
    fails at once) and exclusively (runs started in the same second get ``-1``, ``-2``...).
    A run that fails before writing anything removes its folder (and ``out``, if it made it
    and it is empty), one that wrote results (an interrupted run's poses) keeps them; one that
    finishes becomes ``out/latest``."""
    latest = out / "latest"
    if latest.exists() and not latest.is_symlink():
        raise InputError(latest, "is not a link to a run; move it away to keep it")
    made_out = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
        for n in itertools.count():
            run_dir = out / (stamp if n == 0 else f"{stamp}-{n}")
            try:
                run_dir.mkdir()
                break
            except FileExistsError:
                continue
    except OSError as err:
        raise InputError(out, f"cannot create a run folder here ({err.strerror})") from None
    try:
        yield run_dir
    except BaseException:
        if not any(run_dir.iterdir()):
            run_dir.rmdir()
        if made_out and not any(out.iterdir()):
            out.rmdir()
        raise
    mark_latest(run_dir)


def mark_latest(run_dir: Path) -> None:
    """Point ``out/latest`` at a finished run, atomically (a new link renamed over the old)."""
    latest = run_dir.parent / "latest"
    temporary = run_dir.parent / f".latest-{os.getpid()}"
    temporary.unlink(missing_ok=True)
    temporary.symlink_to(run_dir.name)
    os.replace(temporary, latest)
