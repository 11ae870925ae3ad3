"""The paper's training: optuna's TPE over every weight of the MLPs, the objective being the
mean translational relative error of frame-to-frame registrations over the training windows.

The study lives in an optuna storage (default ``sqlite:///RUN/study.db``; any RDB URL, e.g.
PostgreSQL, lets several workers share one study). A rerun with the same folder resumes: it
runs only the trials still missing to ``n_trials``. Each weight is searched in
``[w0 - bound, w0 + bound]`` around the start model's value, which is enqueued as trial 0.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import optuna

from gloam_jax.errors import InputError
from gloam_jax.learned import MLP, Learned
from gloam_jax.training.problem import Problem, plot_histories, write_history


def _mlps(params: Learned) -> dict[str, MLP]:
    """The MLPs among the parameters (those the method uses), by part name."""
    return {k: v for k, v in params._asdict().items() if isinstance(v, MLP)}


def _names(problem: Problem) -> dict[str, tuple[str, str, int]]:
    """Search-space names -> (part, field, flat index), for the MLPs the method uses."""
    names = {}
    for part, mlp in _mlps(problem.init_params).items():
        for field, array in mlp._asdict().items():
            for i in range(np.size(array)):
                names[f"{part}.{field}[{i}]"] = (part, field, i)
    return names


def params_from_values(problem: Problem, values: dict[str, float]) -> Learned:
    """The start's parameters with the searched weights set from ``values``."""
    start = _mlps(problem.init_params)
    flat = {
        part: {k: np.array(v, np.float32).ravel() for k, v in mlp._asdict().items()}
        for part, mlp in start.items()
    }
    for name, (part, field, i) in _names(problem).items():
        flat[part][field][i] = values[name]
    mlps = {
        part: type(mlp)(*(flat[part][k].reshape(np.shape(v)) for k, v in mlp._asdict().items()))
        for part, mlp in start.items()
    }
    return problem.init_params._replace(**mlps)


def _storage(problem: Problem) -> str:
    url = problem.config.tpe.storage
    return f"sqlite:///{(problem.run_dir / 'study.db').resolve()}" if url is None else url


def _history(study: optuna.Study) -> list[dict]:
    """Completed trials in order: trial number, t_err, wall time so far (sum of durations)."""
    history, wall, best = [], 0.0, np.inf
    for t in study.get_trials(deepcopy=False):
        if t.state != optuna.trial.TrialState.COMPLETE:
            continue
        wall += (t.datetime_complete - t.datetime_start).total_seconds()
        best = min(best, t.value)
        history.append(
            {
                "trial": t.number,
                "wall_s": wall,
                "t_err": t.value,
                "r_err": t.user_attrs.get("r_err"),
                "best_t_err": best,
            }
        )
    return history


def train_tpe(problem: Problem, progress: Callable[[int, int, float], None] | None = None):
    """Run (or resume) the study; export the best trial's weights to ``RUN/model.npz``.

    ``progress(done, total, best)`` after each trial. Returns the exported model.
    """
    cfg = problem.config.tpe
    names = _names(problem)
    if not names:
        raise InputError(None, f"method '{problem.config.method}' has no weights to train")
    init = {
        name: float(np.ravel(getattr(getattr(problem.init_params, part), field))[i])
        for name, (part, field, i) in names.items()
    }
    sampler = optuna.samplers.TPESampler(
        seed=problem.config.seed, n_startup_trials=cfg.n_startup_trials, multivariate=True
    )
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(
        study_name=cfg.study_name,
        storage=_storage(problem),
        sampler=sampler,
        direction="minimize",
        load_if_exists=True,
    )
    if not study.trials:
        study.enqueue_trial(init)

    def objective(trial: optuna.Trial) -> float:
        values = {n: trial.suggest_float(n, v - cfg.bound, v + cfg.bound) for n, v in init.items()}
        t_err, r_err = problem.training_loss(params_from_values(problem, values))
        trial.set_user_attr("r_err", r_err)
        if not np.isfinite(t_err):
            raise optuna.TrialPruned(f"non-finite loss {t_err}")
        return t_err

    def done(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        history = _history(study)
        write_history(problem.run_dir, history)
        if progress is not None and history:
            progress(len(history), cfg.n_trials, history[-1]["best_t_err"])

    complete = len(_history(study))
    if complete < cfg.n_trials:
        study.optimize(objective, n_trials=cfg.n_trials - complete, callbacks=[done])
    history = _history(study)
    write_history(problem.run_dir, history)
    wall = [h["wall_s"] for h in history]
    plot_histories(
        {
            "trial": (wall, [100 * h["t_err"] for h in history]),
            "best so far": (wall, [100 * h["best_t_err"] for h in history]),
        },
        problem.run_dir / "loss_curve.png",
        f"TPE, {problem.config.method}",
    )
    best = study.best_trial
    return problem.export(
        params_from_values(problem, best.params),
        problem.run_dir / "model.npz",
        {"train_t_err": best.value, "trials": len(history), "best_trial": best.number,
         "wall_s": wall[-1]},
    )  # fmt: skip
