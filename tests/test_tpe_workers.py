"""TPE with several workers: a real PostgreSQL server shared by worker processes, a worker killed
mid-trial, SIGTERM, the storage checked before any data is prepared, the settings digest of a
study, counts raised on resume, and a failed setup that does not bind its run folder.

The server is Debian's PostgreSQL (``apt-get install postgresql``; ``.ci/run`` installs it), run
as the ``postgres`` user when the tests run as root (the server refuses root).
"""

import dataclasses
import glob
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState
from typer.testing import CliRunner

from gloam_jax.cli import app
from gloam_jax.config import dump_config
from gloam_jax.errors import InputError
from gloam_jax.models import load_model
from gloam_jax.training.config import TPEConfig, TrainConfig
from gloam_jax.training.problem import setup
from gloam_jax.training.tpe import train_tpe

# One worker runs this module (pytest-xdist --dist loadgroup): its PostgreSQL server and its
# scan cache are made once.
pytestmark = pytest.mark.xdist_group("tpe_workers")


def _pg_bin(name: str) -> str:
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}")) or [shutil.which(name)]
    if not found[-1]:
        pytest.fail(f"PostgreSQL's {name} not found: apt-get install postgresql (see .ci/run)")
    return found[-1]


@pytest.fixture(scope="module")
def postgres_url():
    """A PostgreSQL server for this module, on a free local port, trusting local users."""
    as_user = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
    folder = Path(tempfile.mkdtemp(prefix="gloam-pg-"))
    if as_user:
        shutil.chown(folder, "postgres")
    data = folder / "data"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    run = lambda *a: subprocess.run([*as_user, *a], check=True, capture_output=True)  # noqa: E731
    run(_pg_bin("initdb"), "-D", str(data), "-A", "trust", "-U", "postgres", "--no-sync")
    options = f"-p {port} -k {folder} -c listen_addresses=127.0.0.1 -c fsync=off"
    run(_pg_bin("pg_ctl"), "-D", str(data), "-o", options, "-l", str(folder / "log"), "-w",
        "-t", "60", "start")  # fmt: skip
    try:
        yield f"postgresql://postgres@127.0.0.1:{port}/postgres"
    finally:
        run(_pg_bin("pg_ctl"), "-D", str(data), "-m", "immediate", "stop")
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """Prepared windows shared by this module's runs (their preprocessing is the same)."""
    return tmp_path_factory.mktemp("cache")


def _config(tiny_training, **tpe) -> TrainConfig:
    return tiny_training.config(mode="tpe", tpe=TPEConfig(**{"n_trials": 4, **tpe}))


def _trials(url: str, name: str) -> list[optuna.trial.FrozenTrial]:
    return optuna.load_study(study_name=name, storage=url).get_trials(deepcopy=False)


def test_postgres_two_workers_share_one_study(tiny_training, cache, tmp_path,
                                              postgres_url):  # fmt: skip
    cfg = _config(tiny_training, n_trials=6, storage=postgres_url, study_name="two")
    problem = setup(cfg, tmp_path / "run", cache_dir=cache)
    # The command runs trials itself from the start; on a busy machine it could finish all
    # six before the worker process it started has imported JAX. Its trials wait until that
    # worker has begun one, so that the study shows both at work however slowly it starts.
    here, evaluate = f"{socket.gethostname()}:{os.getpid()}", problem.evaluate_hard

    def after_the_other_began(params):
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not any(
            t.user_attrs.get("worker") not in (None, here) for t in _trials(postgres_url, "two")
        ):
            time.sleep(0.2)
        return evaluate(params)

    problem.evaluate_hard = after_the_other_began
    trained = train_tpe(problem, workers=2, cache_dir=cache)
    trials = _trials(postgres_url, "two")
    finished = [t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
    # The budget is global; a worker's trial running when the other reached it also ends.
    assert 6 <= len(finished) <= 7
    assert not [t for t in trials if t.state == TrialState.RUNNING]
    assert sorted(t.number for t in trials) == list(range(len(trials)))  # no duplicates
    assert len({t.user_attrs["worker"] for t in finished}) == 2  # both workers ran trials
    best = min(t.value for t in trials if t.state == TrialState.COMPLETE)
    # Stored numbers, not recomputed: the trial's value (objective t_err, a float32 jnp mean)
    # and its t_err attribute (a NumPy mean) of the same evaluation's per-window errors; 1e-6
    # covers the two means' float32 rounding.
    assert trained.provenance["train_t_err"] == pytest.approx(best, rel=1e-6)
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert history[-1]["best_t_err"] == pytest.approx(best, rel=1e-6)
    assert load_model(tmp_path / "run" / "model.npz").provenance["study"] == "two"


def test_postgres_killed_worker_trial_fails_and_is_retried(tiny_training, cache,
                                                           tmp_path, postgres_url):  # fmt: skip
    """A worker on 'another machine' (a process of its own) is SIGKILLed mid-trial; after the
    grace period the next worker fails that trial and runs its weights again."""
    cfg = _config(tiny_training, n_trials=3, storage=postgres_url,
                  study_name="killed", heartbeat_interval=1, grace_period=3)  # fmt: skip
    run = tmp_path / "run"
    setup(cfg, run, cache_dir=cache)  # prepares the folder; the lone worker loads it
    command = [sys.executable, "-c", "from gloam_jax.training.tpe import _worker_main as m; m()"]
    worker = subprocess.Popen([*command, str(run), str(cache), "killed"])
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and worker.poll() is None:
            running = [t for t in _safe_trials(postgres_url, "killed")
                       if t.state == TrialState.RUNNING and "worker" in t.user_attrs]  # fmt: skip
            if running:
                break
            time.sleep(0.5)
        assert running, "the worker never started a trial"
        worker.send_signal(signal.SIGKILL)
        worker.wait()
    finally:
        if worker.poll() is None:
            worker.kill()
    killed = running[0]
    time.sleep(3.5)  # the grace period passes without a heartbeat
    train_tpe(setup(cfg, run, cache_dir=cache))  # resumes: fails the stale trial first
    trials = _trials(postgres_url, "killed")
    assert not [t for t in trials if t.state == TrialState.RUNNING]
    assert trials[killed.number].state == TrialState.FAIL
    retried = [t for t in trials if t.system_attrs.get("failed_trial") == killed.number]
    assert retried and retried[0].state == TrialState.COMPLETE
    assert retried[0].params == trials[killed.number].params
    assert len([t for t in trials if t.state == TrialState.COMPLETE]) == 3


def _safe_trials(url, name):
    try:
        return _trials(url, name)
    except KeyError:  # the worker has not made the study yet
        return []


def _cli_config(tiny_training, tmp_path, **tpe) -> Path:
    path = tmp_path / "train.yaml"
    dump_config(_config(tiny_training, **tpe), path)
    return path


@pytest.mark.parametrize(
    ("storage", "message"),
    [
        ("notaurl", "is not a database URL"),
        ("sqlite:////nonexistent-gloam/study.db", "folder /nonexistent-gloam does not exist"),
        ("mysql+pymysql://user@localhost/db", "database driver is missing (pymysql)"),
        ("truncated", "cannot use this database ("),  # not a database, or malformed
    ],
)
def test_cli_bad_storage_is_one_line_before_any_data(tiny_training, tmp_path,
                                                     storage, message):  # fmt: skip
    if storage == "truncated":  # a study.db cut short (the first bytes of a real one)
        db = tmp_path / "old.db"
        optuna.create_study(storage=f"sqlite:///{db}", study_name="x")
        (tmp_path / "study.db").write_bytes(db.read_bytes()[:100])
        storage = f"sqlite:///{tmp_path / 'study.db'}"
    config = _cli_config(tiny_training, tmp_path)
    out = tmp_path / "run"
    result = CliRunner().invoke(
        app, ["train", "--config", str(config), "--out", str(out), "--storage", storage]
    )
    assert result.exit_code == 2, result.output
    assert message in result.output and len(result.output.strip().splitlines()) == 1
    assert not (out / "cache").exists() and not (out / "config.yaml").exists()


def test_cli_counts_raised_on_resume_and_a_study_of_other_settings(tiny_training, cache,
                                                                   tmp_path):  # fmt: skip
    config = _cli_config(tiny_training, tmp_path, n_trials=2)
    args = ["train", "--config", str(config), "--cache", str(cache)]
    runner = CliRunner()
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "a")])
    assert result.exit_code == 0, result.output
    # The study is named after the run folder; a rerun may raise the trial count.
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "a"), "--trials", "3"])
    assert result.exit_code == 0, result.output
    trials = _trials(f"sqlite:///{tmp_path / 'a' / 'study.db'}", "a")
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 3
    assert load_model(tmp_path / "a" / "model.npz").provenance["trials"] == 3
    # Another run (other seed) pointed at that study is refused before preparing anything.
    storage = ["--storage", f"sqlite:///{tmp_path / 'a' / 'study.db'}", "--study-name", "a"]
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "b"), "--seed", "5", *storage])
    assert result.exit_code == 2
    assert "study 'a'" in result.output and "use another --study-name" in result.output
    assert not (tmp_path / "b" / "config.yaml").exists()


def test_a_failed_setup_does_not_bind_its_folder(tiny_training, cache, tmp_path):
    bad = dataclasses.replace(_config(tiny_training), init_model=str(tmp_path / "x"))
    with pytest.raises(InputError):
        setup(bad, tmp_path / "run", cache_dir=cache)
    assert not (tmp_path / "run" / "config.yaml").exists()
    good = dataclasses.replace(_config(tiny_training), seed=4)
    setup(good, tmp_path / "run", cache_dir=cache)  # other settings: accepted
    assert "seed: 4" in (tmp_path / "run" / "config.yaml").read_text()


def test_sigterm_fails_the_running_trial_and_exits_143(tiny_training, cache, tmp_path):
    config = _cli_config(tiny_training, tmp_path, n_trials=50)
    run = tmp_path / "run"
    command = [sys.executable, "-m", "gloam_jax", "train", "--config", str(config), "--out",
               str(run), "--cache", str(cache)]  # fmt: skip
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = f"sqlite:///{run / 'study.db'}"
    try:
        deadline = time.monotonic() + 300
        running = []
        while time.monotonic() < deadline and proc.poll() is None and not running:
            time.sleep(0.5)
            if (run / "config.yaml").exists():
                trials = _safe_trials(url, "run")
                running = [
                    t for t in trials if t.state == TrialState.RUNNING and "worker" in t.user_attrs
                ]
        assert running, "no trial started"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "SIGTERM" in err.strip().splitlines()[-1]
    trials = _trials(url, "run")
    assert trials[running[0].number].state == TrialState.FAIL
    assert not [t for t in trials if t.state == TrialState.RUNNING]


def test_a_swallowed_sigterm_fails_its_trial_and_stops(tiny_training, cache, tmp_path,
                                                       monkeypatch):  # fmt: skip
    """Extension code may clear the interrupt without a trace: the trial it ran in still ends
    failed, and no further trial starts."""
    from gloam_jax.interrupt import Terminated, stop_on
    from gloam_jax.training.tpe import open_storage, open_study, run_trials

    problem = setup(_config(tiny_training), tmp_path / "run", cache_dir=cache)
    loss, calls = problem.training_loss, []

    def swallowing(params):
        calls.append(params)
        if len(calls) == 2:
            try:
                signal.raise_signal(signal.SIGTERM)
                time.sleep(5)
            except KeyboardInterrupt:
                pass
        return loss(params)

    monkeypatch.setattr(problem, "training_loss", swallowing)
    study = open_study(problem, open_storage(problem.config, problem.run_dir), "run", seeded=True)
    with pytest.raises(Terminated):
        with stop_on(signal.SIGTERM):
            run_trials(study, problem)
    states = [t.state for t in study.get_trials(deepcopy=False)]
    assert states == [TrialState.COMPLETE, TrialState.FAIL]
