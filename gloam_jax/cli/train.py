"""``gloam init-model`` and ``gloam train``: the model file, trained by TPE or gradients."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Annotated

import typer

from gloam_jax.cli.common import (
    CACHE_HELP,
    Tasks,
    app,
    console,
    err_console,
    progress_bar,
    use_compilation_cache,
    user_errors,
)
from gloam_jax.errors import InputError
from gloam_jax.interrupt import Terminated, stop_on

CACHE_HELP_PREPARED = "Folder for prepared training windows (shared by runs)."


@app.command(
    name="init-model",
    epilog="Example:\n\n  gloam init-model data/sim 05 07 --out model.npz",
)
@user_errors
def init_model(
    data: Annotated[Path, typer.Argument(help="KITTI-layout root with training sequences.")],
    sequences: Annotated[list[str], typer.Argument(help="Training sequence ids.")],
    out: Annotated[Path, typer.Option(help="Model file to write (.npz).")] = Path("model.npz"),
    every: Annotated[int, typer.Option(min=1, help="Use every N-th scan for the PCA.")] = 25,
    backbone: Annotated[str, typer.Option(help="Feature backbone: geometric, net.")] = "geometric",
    backbone_options: Annotated[
        str, typer.Option(help="Its options as a YAML mapping, e.g. '{drop: [density]}'.")
    ] = "{}",
    features: Annotated[
        Path | None, typer.Option(help="Fit on per-scan feature files here instead.")
    ] = None,
    seed: Annotated[int, typer.Option(help="MLP initialisation seed.")] = 0,
    init: Annotated[
        str, typer.Option(help="random, or gicp (start near plain GICP, for training).")
    ] = "random",
) -> None:
    """Fit the frozen PCA on training scans and write a model file with untrained MLPs."""
    from gloam_jax.config import parse_mapping
    from gloam_jax.features import get_backbone
    from gloam_jax.models import save_model
    from gloam_jax.training.problem import fit_initial_model

    options = parse_mapping(backbone_options)
    if options is None:
        raise InputError(
            None, f"--backbone-options must be a YAML mapping, not {backbone_options!r}"
        )
    extractor = (
        get_backbone("precomputed", folder=features)
        if features is not None
        else get_backbone(backbone, **options)
    )
    with progress_bar() as bar:
        step = Tasks(bar)

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
    name="model-info",
    epilog="Examples:\n\n  gloam model-info\n\n  gloam model-info net\n\n"
    "  gloam model-info runs/grad/model.npz --json",
)
@user_errors
def model_info(
    model: Annotated[
        str, typer.Argument(help="A model file, or a shipped model's name (default, net).")
    ] = "default",
    json_out: Annotated[
        bool, typer.Option("--json", help="Print the file's metadata as JSON instead.")
    ] = False,
) -> None:
    """How a model file was made: backbone, training, selection and every test score."""
    import json

    from gloam_jax.features import get_backbone
    from gloam_jax.metrics import format_spread
    from gloam_jax.models import load_model
    from gloam_jax.preprocess import PreprocessConfig, on_grid

    def say(line: str) -> None:  # one line each, however narrow the terminal: easy to grep
        console.print(line, soft_wrap=True, markup=False, highlight=False)

    m = load_model(model)
    prov = m.provenance
    if json_out:
        sensors = None if m.sensors is None else [s.to_dict() for s in m.sensors]
        info = {"backbone": m.backbone_name, "backbone_options": m.backbone_options,
                "eps": m.eps, "max_thickness": m.max_thickness, "sensors": sensors,
                "provenance": prov}  # fmt: skip
        console.print_json(json.dumps(info, default=str))
        return
    trained = prov.get("config", {})
    say(
        f"{model}: backbone {m.backbone_name} {m.backbone_options or ''}, PCA keeps "
        f"{100 * float(sum(m.pca.explained_variance_ratio)):.1f} % of the variance, eps {m.eps:g}"
        + ("" if m.max_thickness is None else f", max_thickness {m.max_thickness:g}")
    )
    # built without backbone()'s check of its width against the PCA's: model-info shows both
    geometric = m.backbone_name == "geometric" and get_backbone("geometric", **m.backbone_options)
    if geometric and on_grid(geometric, PreprocessConfig()) is not None:
        say("features: made on the odometry's voxel grid (the default preprocessing's voxels "
            "and range band), not per raw point")  # fmt: skip
    if m.sensors is None:
        say("sensors: not recorded (an older file: gloam run runs it when named, with a warning)")
    for s in m.sensors or ():
        say(f"trained for sensor {s.describe()}")
    if m.novelty is not None:
        fit = prov.get("novelty", {})
        say(
            f"novelty: MLP inputs clamped to d2 {float(m.novelty.radius2):.2f} (quantile "
            f"{fit.get('quantile')} of {fit.get('points')} training points)"
        )
    if "mode" not in prov:
        say(f"untrained (not written by gloam train): {prov or 'no provenance'}")
        return
    say(
        f"trained: {prov.get('mode')} ({prov.get('method')}), seed {prov.get('seed')}, "
        + (f"{prov['steps']} steps" if "steps" in prov else f"{prov.get('trials')} trials")
        + f", data {trained.get('data')}, "
        f"sequences {', '.join(map(str, trained.get('sequences', [])))}"
    )
    if "selected_on" in prov:
        versus = prov.get("validation_gicp")
        say(
            f"chosen on {prov['selected_on']}: {prov.get('objective')} {prov['selected_value']:.4f}"
            + ("" if versus is None else f" (plain GICP {versus:.4f})")
        )
    scores = prov.get("test_scores", [])
    if not scores:
        say("test split: not scored")
    for s in scores:
        say(
            f"test ({s['method']}): worlds {_world_span(s['worlds'])}, simulation seeds "
            f"{','.join(map(str, s['sim_seeds']))}: t_err {format_spread(s['t_err'])} %, r_err "
            f"{format_spread(s['r_err'])} deg/100 m ({s['commit'].split()[0]}, {s['date'][:10]})"
        )


def _world_span(worlds: list[str]) -> str:
    """``301-310 (10)`` for consecutive ids, else ``302, 305, 307 (3)``."""
    ids = [int(w) if str(w).isdigit() else None for w in worlds]
    consecutive = None not in ids and ids == list(range(ids[0], ids[0] + len(ids)))
    shown = f"{worlds[0]}-{worlds[-1]}" if consecutive and len(ids) > 1 else ", ".join(worlds)
    return f"{shown} ({len(worlds)})"


@app.command(
    epilog="Example:\n\n  gloam novelty runs/grad/model.npz --config configs/train_protocol.yaml "
    "--out runs/grad/model_novelty.npz"
)
@user_errors
def novelty(
    model: Annotated[str, typer.Argument(help="A trained model file (or default, net).")],
    config: Annotated[Path, typer.Option(help="The training config whose train worlds it saw.")],
    out: Annotated[Path, typer.Option(help="Model file to write (.npz).")],
    quantile: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="Training points' d2 quantile kept as is.")
    ] = 0.99,
    cache: Annotated[Path | None, typer.Option(help=CACHE_HELP_PREPARED)] = None,
) -> None:
    """Clamp a model's MLP inputs to the feature region of its training worlds."""
    from gloam_jax.config import load_config
    from gloam_jax.models import load_model, save_model
    from gloam_jax.training.config import TrainConfig
    from gloam_jax.training.novelty import fit_model_novelty

    cfg = load_config(config, TrainConfig)
    with progress_bar() as bar:
        fitted = fit_model_novelty(
            load_model(model), cfg, quantile=quantile, cache_dir=cache,
            progress=Tasks(bar),
        )  # fmt: skip
    save_model(out, fitted)
    record = fitted.provenance["novelty"]
    console.print(
        f"feature region fitted on {record['points']} training points: MLP inputs clamped "
        f"to d2 {float(fitted.novelty.radius2):.2f}; {out}",
        highlight=False,
    )


@app.command(
    epilog=(
        "Examples:\n\n"
        "  gloam train --config configs/train_grad.yaml --out runs/grad\n\n"
        "  gloam train --mode tpe --config configs/train_tpe.yaml --out runs/tpe --trials 300\n\n"
        "  gloam train --config configs/train_tpe.yaml --out runs/tpe --workers 4 "
        "--storage postgresql://gloam:secret@db-host/gloam --study-name search1\n\n"
        "Rerunning a command with the same --out resumes it (and may raise --trials or --steps); "
        "the same TPE command on another machine, with the same --storage and study name, "
        "joins the search. Ctrl-C or SIGTERM ends the running trials as failed (exit 130 or "
        "143); rerun to resume."
    )
)
@user_errors
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
    cache: Annotated[Path | None, typer.Option(help=CACHE_HELP_PREPARED)] = None,
    storage: Annotated[
        str | None,
        typer.Option(
            help="TPE study database URL (default sqlite:///OUT/study.db); a PostgreSQL URL "
            "(pip install 'gloam-jax[postgres]') is shared by workers on several machines."
        ),
    ] = None,
    study_name: Annotated[
        str | None, typer.Option(help="TPE study name (default: the --out folder's name).")
    ] = None,
    workers: Annotated[int, typer.Option(min=1, help="TPE worker processes on this machine.")] = 1,
    compilation_cache: Annotated[bool, typer.Option(help=CACHE_HELP)] = True,
) -> None:
    """Train the MLPs by TPE (the paper's black-box search) or by gradients through GICP."""
    if compilation_cache:
        use_compilation_cache()
    try:
        with stop_on(signal.SIGTERM):
            _train(config, mode, data, out, trials, seed, steps, learning_rate, cache, storage,
                   study_name, workers)  # fmt: skip
    except KeyboardInterrupt as stop:
        code = 143 if isinstance(stop, Terminated) else 130
        what = "SIGTERM" if code == 143 else "interrupted"
        err_console.print(
            f"[red]{what}:[/red] the running work ended as failed; rerun the same command "
            f"to resume ({out})",
            highlight=False,
        )
        raise typer.Exit(code) from None


def _train(config, mode, data, out, trials, seed, steps, learning_rate, cache, storage,
           study_name, workers) -> None:  # fmt: skip
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
    tpe = {"n_trials": trials, "storage": storage, "study_name": study_name}
    tpe = {k: v for k, v in tpe.items() if v is not None}
    cfg = dataclasses.replace(cfg, tpe=dataclasses.replace(cfg.tpe, **tpe))
    if seed is not None:
        cfg = dataclasses.replace(cfg, seed=seed)
    grad = {"steps": steps, "learning_rate": learning_rate}
    grad = {k: v for k, v in grad.items() if v is not None}
    cfg = dataclasses.replace(cfg, grad=dataclasses.replace(cfg.grad, **grad))
    store = None
    if cfg.mode == "tpe":
        from gloam_jax.training import tpe as tpe_mode

        # The storage and its study are checked before any data is prepared.
        store = tpe_mode.open_storage(cfg, out)
        tpe_mode.check_study(store, tpe_mode.study_name(cfg, out), cfg)
    elif workers != 1 or storage is not None or study_name is not None:
        raise InputError(None, "--workers, --storage and --study-name are for --mode tpe")
    with progress_bar() as bar:
        step = Tasks(bar)

        problem = setup(cfg, out, cache_dir=cache, progress=step)
        label = "TPE trials" if cfg.mode == "tpe" else "gradient steps"

        def tick(done: int, total: int, best: float) -> None:
            step(label, done, total, rate=f"best t_err {100 * best:.3f} %")

        if cfg.mode == "tpe":
            from gloam_jax.training.tpe import train_tpe

            model = train_tpe(problem, tick, workers=workers, cache_dir=cache, storage=store)
        else:
            from gloam_jax.training.grad import train_grad

            model = train_grad(problem, tick)
    info = model.provenance
    if "fallback" in info:
        chosen = (
            f"plain GICP ({cfg.objective} {info['selected_value']:.4g} on validation; the best "
            f"weights validated, the start included, {info['fallback']['from_value']:.4g}: not "
            f"{100 * cfg.min_gain:g} % better), training t_err"
        )
    elif info["selected_on"] == "validation":
        chosen = (
            f"chosen on validation ({cfg.objective} {info['selected_value']:.4g}), training t_err"
        )
    else:
        chosen = "best training t_err"
    console.print(
        f"{cfg.mode}: {chosen} {100 * info['train_t_err']:.3f} % "
        f"({info['wall_s']:.0f} s of training); model: {out / 'model.npz'}, "
        f"curve: {out / 'loss_curve.png'}"
    )
