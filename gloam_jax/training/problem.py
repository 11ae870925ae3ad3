"""What both training modes share: the run folder, the starting model, the prepared training
data, the trainable parameters and the hard-association evaluation of the training loss.

A run folder holds ``config.yaml`` (the settings, written once the setup has succeeded; a later
run in the same folder must use the same ones, except the counts of trials and steps, which it may
raise, and then resumes), ``init_model.npz`` (the start), ``cache/`` (prepared windows),
``history.json`` (training loss against wall time), ``loss_curve.png`` and, at the end,
``model.npz`` (the best weights found, with their provenance).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import time
from collections.abc import Callable, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax import io
from gloam_jax.config import config_dict, dump_config, load_config
from gloam_jax.errors import InputError
from gloam_jax.features import Backbone, NetBackbone, fit_pca, get_backbone
from gloam_jax.features.net import save_net, with_decode
from gloam_jax.learned import Learned
from gloam_jax.models import GLOAMModel, init_model, load_model, save_model, with_mlps
from gloam_jax.sensor import SENSOR_SCANS
from gloam_jax.sensor import measure as measure_sensor
from gloam_jax.sensor import merge as merge_sensors
from gloam_jax.training.batch import BatchData, Evaluator
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.data import load_windows, open_sequences
from gloam_jax.training.head import initial_head, prepare_head
from gloam_jax.training.objective import Score, score

Progress = Callable[[str, int, int], None]  # (what, done, total)
FINE_TUNED_NET = "net.npz"  # the fine-tuned backbone, beside the exported model.npz


def fit_initial_model(
    root: str | Path | Sequence[str | Path],
    sequences: list[str] | tuple[str, ...],
    extractor: Backbone,
    *,
    every: int = 25,
    seed: int = 0,
    init: str = "random",
    keep_backbone_options: bool = True,
    progress: Progress | None = None,
) -> GLOAMModel:
    """Fit the frozen PCA on every ``every``-th scan of the training sequences (of ``root``, or
    of each of several roots) and wrap it with initialised MLPs
    (:func:`gloam_jax.models.init_model`); the sensors are measured on the same scans, a
    sequence at a time (:func:`gloam_jax.sensor.merge`)."""
    rows, signatures = [], []
    for seq in open_sequences(root, sequences):
        name = seq.sequence
        frames = range(0, len(seq), every)
        scans = []  # the sequence's first few, for its sensor's signature
        for k, i in enumerate(frames):
            scan = seq.scan(i)
            rows.append(extractor(scan, path=seq.scan_path(i), frame=i))
            if k < SENSOR_SCANS:
                scans.append(scan)
            if progress is not None:
                progress(f"PCA features {name}", k + 1, len(frames))
        try:
            signatures.append(measure_sensor(scans))
        except InputError as err:
            raise InputError(seq.sequence_dir, err.problem) from None
    return init_model(
        jax.random.PRNGKey(seed),
        fit_pca(rows, seed=seed),
        backbone=extractor.name,
        backbone_options=extractor.options() if keep_backbone_options else {},
        init=init,
        sensors=tuple(merge_sensors(signatures)),
    )


def trainable_params(model: GLOAMModel, method: str, head: bool = False) -> Learned:
    """``model``'s parameters as training holds them (and checkpoints them): the MLPs
    ``method`` uses (the other None), eps as a fixed array leaf (its gradient is stopped) and,
    with ``head``, the net backbone's last layer (:mod:`gloam_jax.training.head`)."""
    start = model.learned.for_method(method)
    start = start._replace(eps=jnp.asarray(model.eps, jnp.float32))
    if model.max_thickness is not None:
        start = start._replace(max_thickness=jnp.asarray(model.max_thickness, jnp.float32))
    return start._replace(head=initial_head(model.backbone())) if head else start


def _fine_tunes(config: TrainConfig, model: GLOAMModel) -> bool:
    """Whether the run fine-tunes the backbone's last layer; InputError where it cannot."""
    if config.grad.head_learning_rate is None:
        return False
    if config.mode != "grad" or model.backbone_name != NetBackbone.name:
        raise InputError(
            None,
            "grad.head_learning_rate fine-tunes the net backbone in gradient mode; this run is "
            f"mode '{config.mode}' on backbone '{model.backbone_name}'",
        )
    return True


@dataclasses.dataclass
class Validation:
    """The validation windows' hard-association evaluators, one per root of
    ``validation_data``, and for each plain GICP's t_err on its windows (W_root,) (the
    ``gicp_ratio`` objective's reference; None for ``t_err``)."""

    evaluate: list[Evaluator]
    references: list[np.ndarray | None]


@dataclasses.dataclass
class Problem:
    """A prepared training run (see :func:`setup`)."""

    config: TrainConfig
    run_dir: Path
    model: GLOAMModel  # the start
    data: BatchData
    evaluate_hard: Evaluator  # the training loss as reported (hard association)
    reference: np.ndarray | None = None  # plain GICP's t_err per training window (gicp_ratio)
    validation: Validation | None = None  # what chooses the exported weights, if given

    @functools.cached_property
    def init_params(self) -> Learned:
        """The trainable parameters at the start (:func:`trainable_params`; once, since the
        fine-tuned layer's start is read from the backbone's weights file)."""
        head = _fine_tunes(self.config, self.model)
        return trainable_params(self.model, self.config.method, head)

    def training_loss(self, params: Learned) -> Score:
        """The objective, mean t_err (fraction) and r_err (rad/m) over the training windows,
        hard association: the numbers both modes are compared on."""
        result = self.evaluate_hard(params)
        return score(result.t_err, result.r_err, self.reference, self.config.worse_penalty)

    def plain_gicp(self) -> Learned | None:
        """:attr:`init_params` set to register as plain GICP (:meth:`Learned.as_gicp`); None
        when the eigenvalue MLP is trained but the configured regulariser is not the plane,
        which it cannot reproduce."""
        p = self.init_params
        if p.eigenvalue is not None and self.config.preprocess.regularizer != "plane":
            return None
        return p.as_gicp()

    def validation_loss(self, params: Learned) -> Score | None:
        """As :meth:`training_loss` on the validation windows, with several roots the objective
        of the worst root; None without them."""
        if self.validation is None:
            return None
        results = [evaluate(params) for evaluate in self.validation.evaluate]
        refs, penalty = self.validation.references, self.config.worse_penalty
        if len(results) == 1:
            return score(results[0].t_err, results[0].r_err, refs[0], penalty)
        t_err, r_err = (
            np.concatenate([getattr(r, k) for r in results]) for k in ("t_err", "r_err")
        )
        together = score(t_err, r_err, None if refs[0] is None else np.concatenate(refs), penalty)
        # Chosen on the worst root: weights must beat GICP on every simulation draw of the
        # worlds, not on their average (a large gain on one draw hid a loss on another).
        worst = max(score(r.t_err, r.r_err, ref, penalty).objective
                    for r, ref in zip(results, refs, strict=True))  # fmt: skip
        return together._replace(objective=worst)

    def export(self, params: Learned, path: Path, extra: dict[str, Any]) -> GLOAMModel:
        """Write ``params`` as a model file with its provenance; returns the model."""
        provenance = {
            "mode": self.config.mode,
            "method": self.config.method,
            "seed": self.config.seed,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "config": config_dict(self.config),
            **extra,
        }
        conversion = self.model.conversion if params.conversion is None else params.conversion
        eigenvalue = self.model.eigenvalue if params.eigenvalue is None else params.eigenvalue
        model = with_mlps(self.model, conversion, eigenvalue, provenance)
        if params.head is not None:
            # The fine-tuned network beside the model file, which names it relative to itself.
            backbone = self.model.backbone()
            net = with_decode(backbone.net, params.head.weight, params.head.bias)
            save_net(path.parent / FINE_TUNED_NET, net, {
                "fine_tuned_from": backbone.weights, "layers": "decode",
                "through": "the odometry loss (gloam train, gradient mode)",
                "intensity_mean": backbone.provenance.get("intensity_mean"),  # inputs unchanged
                "backbone_provenance": backbone.provenance, **provenance})  # fmt: skip
            model = dataclasses.replace(model, backbone_options={"weights": FINE_TUNED_NET})
        save_model(path, model)
        return load_model(path)


# What a resumed run may change: the counts (a run may be extended) and where its TPE study lives
# and how its workers keep in touch. Everything else binds a run folder and a study to a run.
UNBOUND = {
    "tpe": ("n_trials", "storage", "study_name", "heartbeat_interval", "grace_period"),
    "grad": ("steps",),
}


def binding_settings(config: TrainConfig) -> dict[str, Any]:
    """The settings that a run folder (and a TPE study) is bound to: all but :data:`UNBOUND`."""
    settings = config_dict(config)
    for section, keys in UNBOUND.items():
        for key in keys:
            settings[section].pop(key, None)
    return settings


def settings_hash(config: TrainConfig) -> str:
    """A short digest of :func:`binding_settings`: what a TPE study records as its run."""
    text = json.dumps(binding_settings(config), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _check_run_dir(config: TrainConfig, run_dir: Path) -> bool:
    """Check that a resumed run uses the folder's settings (the counts may change); returns
    whether the folder holds a run (its ``config.yaml``, written when a setup succeeded)."""
    path = run_dir / "config.yaml"
    if not path.exists():
        return False
    old, new = binding_settings(load_config(path, TrainConfig)), binding_settings(config)
    if old != new:
        changed = [k for k, v in new.items() if old.get(k) != v]
        raise InputError(
            path,
            f"this run folder holds a run with other settings ({', '.join(changed)}); "
            "use another --out to start a new one",
        )
    return True


def bounded(model: GLOAMModel, config: TrainConfig) -> GLOAMModel:
    """The start ``model`` with the config's ``max_thickness``, where it sets one."""
    if config.max_thickness is None:
        return model
    return dataclasses.replace(model, max_thickness=config.max_thickness)


def setup(
    config: TrainConfig,
    run_dir: str | Path,
    *,
    cache_dir: str | Path | None = None,
    progress: Progress | None = None,
    validation: bool = True,
) -> Problem:
    """Prepare a training run in ``run_dir``: the start model (``config.init_model``, or a PCA
    fitted on the training scans with initialised MLPs, saved as ``init_model.npz`` so a
    resumed run starts alike) and the prepared windows (cached in ``cache_dir``, default
    ``run_dir/cache``) and, with ``validation`` and the config's validation sequences, the
    validation windows (a TPE worker process, which does not export, skips them)."""
    run_dir = Path(run_dir)
    resumed = _check_run_dir(config, run_dir)
    # Every sequence is found before the preparation (minutes to hours), not after it.
    open_sequences(config.training_roots, config.sequences)
    if validation and config.validation:
        open_sequences(config.validation_roots, config.validation)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(run_dir, f"cannot create the run folder ({err.strerror})") from None
    start = run_dir / "init_model.npz"
    # A start left by a setup that failed (no config.yaml yet) may come from other settings.
    if resumed and start.is_file():
        model = load_model(start)
    else:
        if config.init_model is not None:
            model = load_model(config.init_model)
        else:
            options = {"weights": config.backbone_weights} if config.backbone == "net" else {}
            extractor = get_backbone(config.backbone, **options | config.backbone_options)
            model = fit_initial_model(
                config.training_roots,
                config.sequences,
                extractor,
                every=config.pca_every,
                seed=config.seed,
                init=config.init,
                progress=progress,
            )
        model = bounded(model, config)
        save_model(start, model)
    backbone = model.backbone()
    head = _fine_tunes(config, model)

    def step(name: str, total: int, k: int) -> None:
        if progress is not None:
            progress(f"preparing {name}", k + 1, total)

    def windows(root: str | tuple[str, ...], sequences: tuple[str, ...]) -> BatchData:
        data = load_windows(
            root,
            sequences,
            config.preprocess,
            config.batch,
            model.pca,
            backbone,
            frames=config.frames,
            cache_dir=run_dir / "cache" if cache_dir is None else cache_dir,
            progress=step,
        )
        if head:
            data.head = prepare_head(
                open_sequences(root, sequences), config.preprocess, backbone, model.pca,
                data.scans.mask.shape[1], frames=config.frames, progress=progress,
            )  # fmt: skip
        return data

    hard = dataclasses.replace(config.batch, association="hard")
    data = windows(config.training_roots, config.sequences)
    evaluate = Evaluator(data, hard)
    val_set = None
    if config.validation and validation:
        roots = config.validation_roots
        vals = [Evaluator(windows(root, config.validation), hard) for root in roots]
        refs = [
            _gicp_reference(config, model, val, root) for val, root in zip(vals, roots, strict=True)
        ]
        val_set = Validation(vals, refs)
    # Written last, so that a setup that fails does not bind the folder; rewritten when a
    # resumed run raises a count.
    path = run_dir / "config.yaml"
    if not resumed or config_dict(load_config(path, TrainConfig)) != config_dict(config):
        dump_config(config, path)
    reference = _gicp_reference(config, model, evaluate, ", ".join(config.training_roots))
    return Problem(config, run_dir, model, data, evaluate, reference, val_set)


def choose(
    problem: Problem, params: Learned, value: float, train_t_err: float
) -> tuple[Learned, dict[str, Any]]:
    """The weights to export and how they were chosen (provenance): ``params``, selected with
    ``value`` and training t_err ``train_t_err``; or, with validation windows, plain GICP
    (:meth:`Problem.plain_gicp`) unless ``value`` is below GICP's validation objective by
    ``min_gain`` (a fraction of it). So a model that validation finds worse than GICP, or
    cannot tell from it, ships as GICP itself, not as the nearest learned weights."""
    plain = None if problem.validation is None else problem.plain_gicp()
    if plain is None:
        return params, {"train_t_err": train_t_err, **selection(problem, value)}
    gicp = problem.validation_loss(plain).objective
    if value < (1.0 - problem.config.min_gain) * gicp:
        return params, {"train_t_err": train_t_err, **selection(problem, value),
                        "validation_gicp": gicp}  # fmt: skip
    fallback = {"validation_gicp": gicp, "fallback": {"from_value": value,
                "from_train_t_err": train_t_err, "min_gain": problem.config.min_gain}}  # fmt: skip
    return plain, {"train_t_err": problem.training_loss(plain).t_err,
                   **selection(problem, gicp), **fallback}  # fmt: skip


def selection(problem: Problem, value: float) -> dict[str, Any]:
    """The exported model's provenance of how it was chosen: the objective, on which windows,
    and its ``value`` there."""
    config = problem.config
    chosen = {"objective": config.objective, "selected_value": value}
    if problem.validation is None:
        return {**chosen, "selected_on": "training"}
    return {**chosen, "selected_on": "validation",
            "validation": {"data": list(config.validation_roots),
                           "sequences": list(config.validation)}}  # fmt: skip


def _gicp_reference(
    config: TrainConfig, model: GLOAMModel, evaluate: Evaluator, root: str
) -> np.ndarray | None:
    """Plain GICP's t_err on each window of ``evaluate`` (W,), for the ``gicp_ratio``
    objective; None for ``t_err``."""
    if config.objective != "gicp_ratio":
        return None
    t_err = evaluate(Learned(eps=jnp.asarray(model.eps, jnp.float32))).t_err
    bad = [w.name for w, t in zip(evaluate.data.windows, t_err, strict=True) if not t > 0]
    if bad:
        raise InputError(
            root,
            f"plain GICP's t_err is zero or not finite on {', '.join(bad)}: the gicp_ratio "
            "objective needs a positive reference on every window",
        )
    return np.asarray(t_err, np.float64)


def write_history(run_dir: Path, history: list[dict[str, Any]]) -> None:
    io.write_atomic(run_dir / "history.json", json.dumps(history, indent=1))


def plot_histories(
    curves: dict[str, tuple[list[float], list[float]]],
    path: str | Path,
    title: str,
    ylabel: str = "training t_err (%)",
    reference: tuple[str, float] | None = None,
) -> None:
    """A training value against wall time (s): one line per label ``(wall_s, values)``, and
    ``reference`` ``(label, value)`` as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for label, (wall, value) in curves.items():
        ax.plot(wall, value, marker="." if len(wall) < 60 else None, label=label)
    if reference is not None:
        ax.axhline(reference[1], color="0.4", linestyle="--", linewidth=1, label=reference[0])
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel(ylabel)
    # Bad trials (TPE explores) reach many times the start: keep the scale on the progress.
    start = min(v[0] for _, v in curves.values() if v)
    ax.set_ylim(0.0, 2.0 * start)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def plot_objective(
    problem: Problem,
    history: list[dict[str, Any]],
    t_err: dict[str, str],
    objective: dict[str, str],
    title: str,
) -> None:
    """A run's ``loss_curve.png``: the history's ``t_err`` keys (t_err, in %) against wall time,
    each under its label; with the ``gicp_ratio`` objective its ``objective`` keys instead
    (what selects and ships, plain GICP = 1), since a falling mean t_err can hide windows that
    got worse."""
    wall = [h["wall_s"] for h in history]
    if problem.config.objective == "gicp_ratio":
        curves = {label: (wall, [h[k] for h in history]) for k, label in objective.items()}
        extra = {"ylabel": "objective (plain GICP = 1)", "reference": ("plain GICP", 1.0)}
    else:
        curves = {label: (wall, [100 * h[k] for h in history]) for k, label in t_err.items()}
        extra = {}
    plot_histories(curves, problem.run_dir / "loss_curve.png", title, **extra)


class Clock:
    """Wall time of the training work itself, accumulated across resumed runs."""

    def __init__(self, elapsed: float = 0.0) -> None:
        self.elapsed = elapsed
        self._t0 = time.perf_counter()

    def lap(self) -> float:
        now = time.perf_counter()
        self.elapsed += now - self._t0
        self._t0 = now
        return self.elapsed
