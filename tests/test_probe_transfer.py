"""scripts/probe_transfer.py: the start, the trained update, its reverse, fractions of it and
random-sign updates of a gradient run, each scored as the run scores its weights."""

import json
import sys

import pytest
from repo_scripts import import_script

from gloam_jax.training.config import GradConfig
from gloam_jax.training.grad import train_grad
from gloam_jax.training.problem import setup

probe = import_script("probe_transfer")


def test_probe_rows_are_the_run_s_own_scores(tiny_training, tmp_path, monkeypatch):
    cfg = tiny_training.config(mode="grad", grad=GradConfig(steps=2, learning_rate=0.05))
    run, cache = tmp_path / "run", tmp_path / "cache"
    train_grad(setup(cfg, run, cache_dir=cache))
    history = json.loads((run / "history.json").read_text())
    out = tmp_path / "transfer.json"
    monkeypatch.setattr(sys, "argv", [
        "probe_transfer.py", "--run", str(run), "--cache", str(cache), "--directions", "2",
        "--scales", "0,1", "--out", str(out),
    ])  # fmt: skip
    probe.main()
    result = json.loads(out.read_text())
    rows = result["rows"]
    assert result["step"] == 2 and len(rows) == 3 + 2 + 2
    train = {label: row["train_objective"] for label, row in rows.items()}
    # The start and the last step are the objectives the run's history recorded for them.
    assert train["start"] == pytest.approx(history[0]["objective"], rel=1e-6)
    assert train["trained (start + D)"] == pytest.approx(history[-1]["objective"], rel=1e-6)
    assert train["scaled (start + 0 D)"] == pytest.approx(train["start"], rel=1e-6)
    assert train["scaled (start + 1 D)"] == pytest.approx(train["trained (start + D)"], rel=1e-6)
    assert train["reversed (start - D)"] != pytest.approx(train["trained (start + D)"], rel=1e-4)
    assert all(row["val_objective"] is None for row in rows.values())  # no validation windows


def test_probe_refuses_a_run_without_a_checkpoint(tiny_training, tmp_path, monkeypatch):
    from gloam_jax.config import dump_config

    run = tmp_path / "run"
    run.mkdir()
    dump_config(tiny_training.config(mode="grad"), run / "config.yaml")
    monkeypatch.setattr(sys, "argv", ["probe_transfer.py", "--run", str(run)])
    with pytest.raises(SystemExit, match="no checkpoint.npz"):
        probe.main()


def test_window_gradients_average_to_the_training_loss_gradient(tiny_training, tmp_path):
    """probe_gradients.py: the per-window gradients of the error ratios, averaged, are the
    gradient of the gicp_ratio loss without its penalty (the loss tested against finite
    differences in test_training.py)."""
    import jax
    import numpy as np

    from gloam_jax.training import batch

    gradients = import_script("probe_gradients")
    cfg = tiny_training.config(mode="grad", objective="gicp_ratio")
    problem = setup(cfg, tmp_path / "run", cache_dir=tmp_path / "cache")
    rows = gradients.window_gradients(problem, problem.data, problem.reference)
    assert rows.shape == (len(problem.data.windows), 86) and np.all(np.isfinite(rows))
    assert np.abs(rows).max() > 0
    mesh = batch.pair_mesh()
    scans, pairs = batch.place(problem.data.scans, problem.data.pairs, mesh)
    placed = batch.BatchData(scans, pairs, problem.data.windows, problem.data.regularizer)
    g = jax.grad(batch.loss)(problem.init_params, placed, cfg.batch, mesh, problem.reference, 0.0)
    mlps = jax.tree_util.tree_leaves([g.conversion, g.eigenvalue])
    whole = np.concatenate([np.ravel(x) for x in mlps])
    # float32 through the LM solves, summed in another order: to 1e-3 of the gradient's size.
    assert np.linalg.norm(rows.mean(axis=0) - whole) <= 1e-3 * np.linalg.norm(whole)
