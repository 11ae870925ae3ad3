"""The paper's training: optuna's TPE over every weight of the MLPs, the objective being the
mean translational relative error of frame-to-frame registrations over the training windows.

The study lives in an optuna storage (default ``sqlite:///RUN/study.db``; a PostgreSQL URL lets
workers on several machines share one study). It is named after the run folder unless
``tpe.study_name`` says otherwise, and records the digest of the run's settings
(:func:`gloam_jax.training.problem.settings_hash`): a run with other settings is refused. Any
number of workers, here (``workers``) or on other machines with the same storage and study
name, run trials until the study holds ``n_trials`` finished (complete or pruned) ones; a rerun
resumes, and a larger ``n_trials`` extends the study. Each worker keeps a heartbeat on its running
trial: one silent for ``grace_period`` seconds (its worker was killed) is failed and its weights
queued again. Each weight is searched in ``[w0 - bound, w0 + bound]`` around the start model's
value, which is enqueued as trial 0.
"""

from __future__ import annotations

import bisect
import json
import os
import signal
import socket
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import optuna
from optuna.trial import TrialState

from gloam_jax import io
from gloam_jax.errors import InputError
from gloam_jax.interrupt import raise_if_stopped, stop_on
from gloam_jax.learned import MLP, Learned
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.problem import (
    Problem,
    choose,
    plot_objective,
    settings_hash,
    setup,
    write_history,
)

FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)  # what counts towards n_trials
HASH_ATTR = "settings_hash"
# Queues a failed stale trial's weights again (optuna >= 4.9 renamed it).
_Retry = getattr(optuna.storages, "RetryHeartbeatStaleTrialCallback", None) or (
    optuna.storages.RetryFailedTrialCallback
)


@contextmanager
def _quiet() -> Iterator[None]:
    """Optuna's heartbeats are 'experimental': no warning for each use of them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        warnings.simplefilter("ignore", FutureWarning)
        yield


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


# The study's storage ----------------------------------------------------------------------------


def study_name(config: TrainConfig, run_dir: str | Path) -> str:
    """``tpe.study_name``, or the run folder's name."""
    return config.tpe.study_name or Path(run_dir).resolve().name


def storage_url(config: TrainConfig, run_dir: str | Path) -> str:
    """The study's database URL, checked: ``tpe.storage`` or ``sqlite:///RUN/study.db``. A
    bare ``postgresql://`` gets the psycopg driver (the ``postgres`` extra)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    text = config.tpe.storage
    if text is None:
        return f"sqlite:///{(Path(run_dir) / 'study.db').resolve()}"
    try:
        url = make_url(text)
    except ArgumentError:
        raise InputError(
            None,
            f"storage {text!r} is not a database URL "
            "(e.g. sqlite:///runs/study.db or postgresql://user:password@host/database)",
        ) from None
    shown = url.render_as_string(hide_password=True)
    if url.drivername == "postgresql":
        url = url.set(drivername="postgresql+psycopg")
    try:
        url.get_dialect().import_dbapi()
    except ArgumentError:  # no such dialect
        raise InputError(None, f"storage {shown}: unknown database '{url.drivername}'") from None
    except ImportError as err:
        hint = (
            "pip install 'gloam-jax[postgres]'"
            if url.get_backend_name() == "postgresql"
            else f"install the Python driver for {url.drivername}"
        )
        raise InputError(
            None, f"storage {shown}: its database driver is missing ({err.name}); {hint}"
        ) from None
    if url.get_backend_name() == "sqlite":
        if not url.database or url.database == ":memory:":
            raise InputError(None, f"storage {shown}: name a file (a study in memory is lost)")
        folder = Path(url.database).expanduser().resolve().parent
        if not folder.is_dir():
            raise InputError(None, f"storage {shown}: folder {folder} does not exist")
    return url.render_as_string(hide_password=False)


def open_storage(config: TrainConfig, run_dir: str | Path) -> optuna.storages.RDBStorage:
    """Connect to the study's storage (creating its tables) with heartbeats on; a database
    that cannot be reached or read is a one-line :class:`InputError`."""
    import sqlalchemy.event
    import sqlalchemy.exc

    url = storage_url(config, run_dir)
    if config.tpe.storage is None:
        try:
            Path(run_dir).mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputError(run_dir, f"cannot create the run folder ({err.strerror})") from None
    shown = config.tpe.storage if config.tpe.storage is not None else url
    sqlite = url.startswith("sqlite")
    # Workers of one sqlite study wait for each other's writes instead of failing at once.
    engine = {"connect_args": {"timeout": 60}} if sqlite else {"pool_pre_ping": True}
    try:
        with _quiet():
            storage = optuna.storages.RDBStorage(
                url,
                engine_kwargs=engine,
                heartbeat_interval=config.tpe.heartbeat_interval,
                grace_period=config.tpe.grace_period,
                heartbeat_stale_trial_callback=_Retry(max_retry=3),
            )
        if sqlite:
            sqlalchemy.event.listen(storage.engine, "connect", _sqlite_pragmas)
            storage.engine.dispose()  # connections made from here on get the pragmas
        storage.get_all_studies()  # reads the tables: a damaged file fails here
    except (sqlalchemy.exc.SQLAlchemyError, RuntimeError) as err:
        cause = getattr(err, "orig", None) or err
        first = (str(cause).strip().splitlines() or [type(cause).__name__])[0]
        raise InputError(None, f"storage {shown}: cannot use this database ({first})") from None
    return storage


def _sqlite_pragmas(connection, record) -> None:
    """Write-ahead logging: readers do not wait for a writer, and a commit appends to the log
    instead of rewriting the file (optuna commits once per suggested weight; several workers
    on the default rollback journal spent their time waiting for each other's locks). Safe
    against a crashed process; a power cut may lose the last trials, which are retried."""
    cursor = connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def check_study(storage: optuna.storages.RDBStorage, name: str, config: TrainConfig) -> bool:
    """Refuse a study made with other settings; returns whether the study exists."""
    try:
        study_id = storage.get_study_id_from_name(name)
    except KeyError:
        return False
    theirs = storage.get_study_user_attrs(study_id).get(HASH_ATTR)
    ours = settings_hash(config)
    if theirs is None and not storage.get_all_trials(study_id, deepcopy=False):
        return True  # just created by another worker, who records the digest next
    if theirs != ours:
        made = "without a settings digest" if theirs is None else f"with settings {theirs}"
        raise InputError(
            None,
            f"study '{name}' in {storage.url.split('@')[-1]} was made {made}, this run has "
            f"{ours}: use another --study-name (or the settings it was made with)",
        )
    return True


def open_study(
    problem: Problem, storage: optuna.storages.RDBStorage, name: str, *, seeded: bool
) -> optuna.Study:
    """Create the study (recording the settings digest, enqueueing the start as trial 0) or
    join it. ``seeded``: the sampler uses the run's seed (one worker alone); workers sharing
    a study each draw their own (else their random start-up trials would all be alike)."""
    sampler = optuna.samplers.TPESampler(
        seed=problem.config.seed if seeded else None,
        n_startup_trials=problem.config.tpe.n_startup_trials,
        multivariate=True,
        constant_liar=True,  # workers avoid the weights that others are trying
    )
    try:
        storage.create_new_study([optuna.study.StudyDirection.MINIMIZE], name)
        created = True
    except optuna.exceptions.DuplicatedStudyError:
        created = False
    study = optuna.load_study(study_name=name, storage=storage, sampler=sampler)
    if created:
        study.set_user_attr(HASH_ATTR, settings_hash(problem.config))
        study.enqueue_trial(_start_values(problem))
    else:
        check_study(storage, name, problem.config)
    return study


def _start_values(problem: Problem) -> dict[str, float]:
    return {
        name: float(np.ravel(getattr(getattr(problem.init_params, part), field))[i])
        for name, (part, field, i) in _names(problem).items()
    }


def finished(study: optuna.Study) -> int:
    """Trials that count towards ``n_trials``, all workers together."""
    return len(study.get_trials(deepcopy=False, states=FINISHED))


# Running trials ---------------------------------------------------------------------------------


def _history(study: optuna.Study) -> list[dict]:
    """Completed trials in order of completion: trial number, t_err, the wall time so far (the
    time during which any trial of the study was running: the sum of the trials' durations for
    one worker, less with several; pauses between resumed runs do not count)."""
    trials = study.get_trials(deepcopy=False)
    now = max((t.datetime_complete for t in trials if t.datetime_complete), default=None)
    spans = sorted(
        (t.datetime_start.timestamp(), (t.datetime_complete or now or t.datetime_start).timestamp())
        for t in trials
        if t.datetime_start is not None
    )
    merged: list[list[float]] = []
    for start, end in spans:
        if merged and start <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([start, end])
    starts = [m[0] for m in merged]
    before = np.concatenate([[0.0], np.cumsum([e - s for s, e in merged])])

    def covered(t: float) -> float:
        k = bisect.bisect_right(starts, t) - 1
        return float(before[k] + min(t, merged[k][1]) - merged[k][0]) if k >= 0 else 0.0

    done = [t for t in trials if t.state == TrialState.COMPLETE]
    history, best, best_t_err = [], np.inf, np.inf
    for t in sorted(done, key=lambda t: (t.datetime_complete, t.number)):
        t_err = _t_err(t)
        if t.value < best:
            best, best_t_err = t.value, t_err
        history.append(
            {
                "trial": t.number,
                "wall_s": covered(t.datetime_complete.timestamp()),
                "objective": t.value,
                "t_err": t_err,
                "r_err": t.user_attrs.get("r_err"),
                "best": best,
                "best_t_err": best_t_err,
            }
        )
    return history


def _t_err(trial: optuna.trial.FrozenTrial) -> float:
    """A trial's training t_err (its value, the objective, in studies from before the
    objective setting, which were all t_err)."""
    return trial.user_attrs.get("t_err", trial.value)


def _objective(problem: Problem) -> Callable[[optuna.Trial], float]:
    bound, init = problem.config.tpe.bound, _start_values(problem)
    host, pid = socket.gethostname(), os.getpid()

    def objective(trial: optuna.Trial) -> float:
        values = {n: trial.suggest_float(n, v - bound, v + bound) for n, v in init.items()}
        trial.set_user_attr("worker", f"{host}:{pid}")  # which worker runs it, once it has weights
        train = problem.training_loss(params_from_values(problem, values))
        raise_if_stopped()  # an interrupt that the evaluation swallowed fails this trial
        trial.set_user_attr("t_err", train.t_err)
        trial.set_user_attr("r_err", train.r_err)
        if not np.isfinite(train.objective):
            raise optuna.TrialPruned(f"non-finite loss {train.objective}")
        return train.objective

    return objective


def _raise_if_stopped(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
    raise_if_stopped()  # between trials: an interrupt swallowed while optuna stored one


def run_trials(study: optuna.Study, problem: Problem, callbacks: list | None = None) -> None:
    """Run trials in this process until the study holds ``n_trials`` finished ones (counted
    over all workers: a few more finish when several were running at the end)."""
    n = problem.config.tpe.n_trials
    with _quiet():
        optuna.storages.fail_stale_trials(study)
        if finished(study) < n:
            budget = optuna.study.MaxTrialsCallback(n, states=FINISHED)
            callbacks = [budget, _raise_if_stopped, *(callbacks or [])]
            study.optimize(_objective(problem), callbacks=callbacks)


def _worker_main() -> None:
    """One worker process (``python -c``, argv: run folder, cache folder or '', study name):
    the prepared problem (from the cache) and trials until the study is done."""
    from gloam_jax.config import load_config

    optuna.logging.set_verbosity(optuna.logging.ERROR)
    run_dir, cache_dir, name = sys.argv[1:4]
    # The first SIGINT/SIGTERM ends the running trial as failed: optuna marks a trial that
    # raises KeyboardInterrupt FAIL.
    try:
        with stop_on(signal.SIGINT, signal.SIGTERM):
            config = load_config(Path(run_dir) / "config.yaml", TrainConfig)
            storage = open_storage(config, run_dir)
            problem = setup(config, run_dir, cache_dir=cache_dir or None, validation=False)
            run_trials(open_study(problem, storage, name, seeded=False), problem)
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    except InputError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def _fail_trials_of(study: optuna.Study, pids: set[int]) -> None:
    """Fail (and queue again) the running trials of this machine's workers that died."""
    host = socket.gethostname()
    mine = {f"{host}:{pid}" for pid in pids}
    storage = study._storage
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        if t.user_attrs.get("worker") in mine:
            try:
                storage.set_trial_state_values(t._trial_id, state=TrialState.FAIL)
            except optuna.exceptions.UpdateFinishedTrialError:
                continue
            with _quiet():
                _Retry(max_retry=3)(study, t)


FOLLOW_EVERY_S = 5.0  # how often the command reads the study while its workers run


def _worker_env() -> dict[str, str]:
    """The environment of a worker: this process's, with its JAX persistent compilation cache
    (``gloam train --compilation-cache``), so that workers load the evaluation that an earlier
    run compiled instead of each compiling it again at once."""
    import jax

    env = dict(os.environ)
    folder = jax.config.jax_compilation_cache_dir
    if folder:
        env["JAX_COMPILATION_CACHE_DIR"] = str(folder)
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(
            jax.config.jax_persistent_cache_min_compile_time_secs
        )
    return env


def _run_workers(
    problem: Problem,
    study: optuna.Study,
    workers: int,
    cache_dir: str | Path | None,
    progress: Callable[[int, int, float], None] | None,
) -> None:
    """Run trials here and in ``workers - 1`` more processes on the prepared run; follow the
    study until they all end."""
    # Fresh interpreters (JAX's threads do not survive a fork), reading the run's config.yaml
    # that setup() wrote; they load the windows that it prepared.
    command = [sys.executable, "-c", "from gloam_jax.training.tpe import _worker_main as m; m()"]
    args = [str(problem.run_dir), "" if cache_dir is None else str(cache_dir), study.study_name]
    procs = [subprocess.Popen([*command, *args], env=_worker_env()) for _ in range(workers - 1)]
    handled: set[int] = set()

    def follow() -> None:
        with _quiet():
            optuna.storages.fail_stale_trials(study)
        dead = {p.pid for p in procs if p.poll() not in (None, 0, 2, 130)}
        if dead - handled:
            _fail_trials_of(study, dead - handled)
            handled.update(dead)
        history = _history(study)
        write_history(problem.run_dir, history)
        if progress is not None and history:
            progress(finished(study), problem.config.tpe.n_trials, history[-1]["best_t_err"])

    followed = time.monotonic()

    def follow_sometimes(*_) -> None:
        # Reading the whole study costs CPU that the workers need: every few seconds.
        nonlocal followed
        if time.monotonic() - followed >= FOLLOW_EVERY_S:
            follow()
            followed = time.monotonic()

    try:
        # This process is the first worker (one interpreter start and one setup fewer); it
        # follows the others between its trials, then until they end.
        run_trials(study, problem, [follow_sometimes])
        while running := [p for p in procs if p.poll() is None]:
            try:
                running[0].wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                pass
            follow_sometimes()
        follow()
    except BaseException:
        # Interrupted (Ctrl-C reaches the workers too; a SIGTERM is passed on): the workers
        # fail their running trials and end.
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
        raise
    codes = [p.returncode for p in procs]
    if finished(study) < problem.config.tpe.n_trials:
        raise InputError(
            None,
            f"the TPE workers ended (exit codes {codes}) before the study held "
            f"{problem.config.tpe.n_trials} trials; rerun the command to resume",
        )


def train_tpe(
    problem: Problem,
    progress: Callable[[int, int, float], None] | None = None,
    *,
    workers: int = 1,
    cache_dir: str | Path | None = None,
    storage: optuna.storages.RDBStorage | None = None,
):
    """Run (or resume, or join) the study; export the best trial's weights to
    ``RUN/model.npz``.

    ``workers``: trials run in this process (1) or in that many worker processes, which load
    the prepared windows from ``cache_dir`` (as given to :func:`setup`). ``storage``: an open
    :func:`open_storage` (else opened here). ``progress(done, total, best)`` as trials finish.
    Returns the exported model.
    """
    cfg = problem.config.tpe
    if not _names(problem):
        raise InputError(None, f"method '{problem.config.method}' has no weights to train")
    if workers < 1:
        raise InputError(None, f"workers must be >= 1, not {workers}")
    optuna.logging.set_verbosity(optuna.logging.ERROR)  # an interrupted trial: no traceback
    storage = open_storage(problem.config, problem.run_dir) if storage is None else storage
    name = study_name(problem.config, problem.run_dir)
    alone = workers == 1 and problem.config.tpe.storage is None
    study = open_study(problem, storage, name, seeded=alone)

    if workers == 1:

        def done(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
            history = _history(study)
            write_history(problem.run_dir, history)
            if progress is not None and history:
                progress(finished(study), cfg.n_trials, history[-1]["best_t_err"])

        run_trials(study, problem, [done])
    else:
        _run_workers(problem, study, workers, cache_dir, progress)
    return _export(problem, study)


def _export(problem: Problem, study: optuna.Study) -> Any:
    history = _history(study)
    if not history:
        raise InputError(None, f"study '{study.study_name}' has no completed trial to export")
    write_history(problem.run_dir, history)
    labels = {"t_err": "trial", "best_t_err": "best so far"}
    plot_objective(problem, history, labels, {"objective": "trial", "best": "best so far"},
                   f"TPE, {problem.config.method}")  # fmt: skip
    best, value = _select(problem, study)
    params, chosen = choose(problem, params_from_values(problem, best.params), value, _t_err(best))
    return problem.export(
        params,
        problem.run_dir / "model.npz",
        {"trials": finished(study), "best_trial": best.number, "wall_s": history[-1]["wall_s"],
         "study": study.study_name, **chosen},
    )  # fmt: skip


def _select(problem: Problem, study: optuna.Study) -> tuple[optuna.trial.FrozenTrial, float]:
    """The trial to export and its selection value: the best on the training objective, or,
    with validation windows, the best on them among the ``tpe.validate_best`` best trials and
    the start (trial 0), each listed in ``RUN/validation.json``. The start is always a
    candidate, as step 0 is in gradient mode: from a ``gicp`` start validation can fall back
    to plain GICP."""
    if problem.validation is None:
        return study.best_trial, study.best_value
    done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    candidates = sorted(done, key=lambda t: t.value)[: problem.config.tpe.validate_best]
    if all(t.number != 0 for t in candidates):
        candidates += [t for t in done if t.number == 0]
    rows = []
    for t in candidates:
        val = problem.validation_loss(params_from_values(problem, t.params))
        rows.append({"trial": t.number, "objective": t.value, "t_err": _t_err(t),
                     "val_objective": val.objective, "val_t_err": val.t_err,
                     "val_r_err": val.r_err})  # fmt: skip
    io.write_atomic(problem.run_dir / "validation.json", json.dumps(rows, indent=1))
    k = int(np.argmin([r["val_objective"] for r in rows]))
    return candidates[k], rows[k]["val_objective"]
