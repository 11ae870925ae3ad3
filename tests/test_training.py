"""Training: gradients through GICP against finite differences (both adjoints), the TPE and
gradient drivers on tiny data, resume after interruption, the command line."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from gloam_jax.cli import app
from gloam_jax.cli.common import cache_dir
from gloam_jax.config import dump_config
from gloam_jax.errors import InputError
from gloam_jax.learned import Learned
from gloam_jax.models import load_model
from gloam_jax.preprocess import PreprocessConfig
from gloam_jax.training import batch
from gloam_jax.training.config import GradConfig, TPEConfig
from gloam_jax.training.data import load_windows
from gloam_jax.training.grad import train_grad
from gloam_jax.training.problem import setup
from gloam_jax.training.tpe import train_tpe


@pytest.mark.parametrize("adjoint", ["unrolled", "implicit"])
def test_gradient_matches_finite_differences(sim_sequence, tiny_training, adjoint):
    """d(loss)/d(weights) of the trajectory error through the LM solves, float64, along
    random directions in weight space, against central differences."""
    jax.config.update("jax_enable_x64", True)
    model, tiny = tiny_training.model, tiny_training.batch
    try:
        # Implicit differentiation assumes converged solves: give LM enough steps.
        inner = 3 if adjoint == "unrolled" else 12
        gicp = dataclasses.replace(tiny.gicp, adjoint=adjoint, inner_steps=inner)
        config = dataclasses.replace(tiny, gicp=gicp, temperature=0.2)
        data = load_windows(sim_sequence, ["00"], PreprocessConfig(), config, model.pca,
                            model.backbone(), frames=5)  # fmt: skip
        f64 = lambda tree: jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), tree)  # noqa: E731
        # The "gicp" start outputs the plane (eps, 1, 1) everywhere: a clamp and a sort tie,
        # where the loss has no derivative; move it off both.
        eigenvalue = model.eigenvalue._replace(
            b2=model.eigenvalue.b2 + jnp.array([0.02, -0.1, 0.1])
        )
        params = f64((model.conversion, eigenvalue))  # the weights; eps is fixed

        def loss(p):
            return batch.loss(Learned(*p, model.eps), data, config)

        flat_p, unravel = jax.flatten_util.ravel_pytree(params)
        # One program for the gradient and the differences' values: one compilation.
        value_and_grad = jax.jit(jax.value_and_grad(lambda x: loss(unravel(x))))
        value, flat_g = value_and_grad(flat_p)
        assert np.isfinite(float(value)) and float(value) > 0
        assert np.all(np.isfinite(flat_g)) and np.linalg.norm(flat_g) > 0
        fl = lambda x: float(value_and_grad(x)[0])  # noqa: E731
        rng = np.random.default_rng(0)
        h = 1e-5
        for _ in range(3):
            v = rng.normal(size=flat_p.shape)
            v /= np.linalg.norm(v)
            fd = (fl(flat_p + h * v) - fl(flat_p - h * v)) / (2 * h)
            ad = float(flat_g @ v)
            assert ad == pytest.approx(fd, rel=2e-3, abs=1e-7), (adjoint, ad, fd)
    finally:
        jax.config.update("jax_enable_x64", False)


class Interrupt(Exception):
    pass


def _interrupt_after(n):
    def progress(done, total, best):
        if done == n:
            raise Interrupt

    return progress


def test_tpe_runs_resumes_and_exports(tiny_training, tmp_path):
    cfg = tiny_training.config(mode="tpe", tpe=TPEConfig(n_trials=3))
    run = tmp_path / "tpe"
    cache = tmp_path / "cache"
    with pytest.raises(Interrupt):
        train_tpe(setup(cfg, run, cache_dir=cache), _interrupt_after(2))
    history = json.loads((run / "history.json").read_text())
    assert len(history) == 2
    trained = train_tpe(setup(cfg, run, cache_dir=cache))  # resumes: one more trial
    history = json.loads((run / "history.json").read_text())
    assert [h["trial"] for h in history] == [0, 1, 2]
    assert all(np.isfinite(h["t_err"]) for h in history)
    assert history[-1]["best_t_err"] == min(h["t_err"] for h in history)
    # Trial 0 is the start model itself.
    problem = setup(cfg, run, cache_dir=cache)
    assert history[0]["t_err"] == pytest.approx(problem.training_loss(problem.init_params).t_err)
    loaded = load_model(run / "model.npz")
    assert loaded.provenance["mode"] == "tpe"
    assert loaded.provenance["train_t_err"] == pytest.approx(history[-1]["best_t_err"])
    got = problem.training_loss(problem.init_params._replace(
        conversion=loaded.conversion, eigenvalue=loaded.eigenvalue)).t_err  # fmt: skip
    assert got == pytest.approx(history[-1]["best_t_err"], rel=1e-5)
    assert trained.provenance["trials"] == 3 and (run / "loss_curve.png").stat().st_size > 0


def test_grad_runs_and_resumes_to_the_same_weights(tiny_training, tmp_path):
    """With a random subset of source points per step: a resumed run repeats them, and the
    warm-up goes on from the step it stopped at. (Resuming inside a step: the Ctrl-C test of
    test_batch.py, with the same training step.)"""
    grad = GradConfig(steps=2, eval_every=1, learning_rate=0.01, source_points=64, warmup_steps=2)
    cfg = tiny_training.config(mode="grad", grad=grad)
    cache = tmp_path / "cache"
    straight = train_grad(setup(cfg, tmp_path / "a", cache_dir=cache))
    with pytest.raises(Interrupt):
        train_grad(setup(cfg, tmp_path / "b", cache_dir=cache), _interrupt_after(1))
    assert (tmp_path / "b" / "checkpoint.npz").is_file()
    resumed = train_grad(setup(cfg, tmp_path / "b", cache_dir=cache))
    for a, b in zip(jax.tree_util.tree_leaves((straight.conversion, straight.eigenvalue)),
                    jax.tree_util.tree_leaves((resumed.conversion, resumed.eigenvalue)),
                    strict=True):  # fmt: skip
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7)
    history = json.loads((tmp_path / "b" / "history.json").read_text())
    assert [h["step"] for h in history] == [0, 1, 2]
    assert all(np.isfinite(h["t_err"]) for h in history)
    assert np.isfinite(history[-1]["soft_loss"])
    assert load_model(tmp_path / "b" / "model.npz").provenance["steps"] == 2


def test_a_thickness_bound_holds_in_training_and_in_the_exported_model(tiny_training, tmp_path):
    """``max_thickness`` reaches the training registrations: there a plane ten times thicker
    than the bound registers as the plane at the bound. The exported model keeps it."""
    from gloam_jax.learned import plane_output

    cap = 0.004
    cfg = tiny_training.config(mode="grad", max_thickness=cap)
    problem = setup(cfg, tmp_path / "run", cache_dir=tmp_path / "cache")
    assert problem.model.max_thickness == cap
    assert float(problem.init_params.max_thickness) == pytest.approx(cap)
    mlp = problem.init_params.eigenvalue

    def plane(thickness: float) -> Learned:
        return problem.init_params._replace(eigenvalue=mlp.constant(plane_output(thickness)))

    thick, at_cap = problem.training_loss(plane(10 * cap)), problem.training_loss(plane(cap))
    free = problem.training_loss(plane(10 * cap)._replace(max_thickness=None))
    np.testing.assert_allclose(thick.t_err, at_cap.t_err, rtol=1e-6)
    assert abs(free.t_err - thick.t_err) > 1e-3 * thick.t_err  # the bound changed something
    exported = problem.export(plane(10 * cap), tmp_path / "model.npz", {})
    assert exported.max_thickness == cap and load_model(tmp_path / "model.npz").max_thickness == cap
    with pytest.raises(InputError, match=r"max_thickness must be in \(0, 1\], not 0"):
        tiny_training.config(max_thickness=0.0)


def test_backbone_options_reach_the_fitted_start_and_the_model_file(tiny_training, tmp_path):
    """Without init_model, the PCA is fitted on the backbone the config's options build, and
    the model file rebuilds that backbone."""
    options = {"max_height": 3.0, "drop": ["density"]}
    cfg = tiny_training.config(init_model=None, pca_every=10, backbone_options=options)
    problem = setup(cfg, tmp_path / "run", cache_dir=tmp_path / "cache")
    backbone = load_model(tmp_path / "run" / "init_model.npz").backbone()
    assert backbone.options()["max_height"] == 3.0 and backbone.options()["drop"] == ["density"]
    assert "density" not in backbone.feature_names
    assert problem.model.pca.mean.shape == (backbone.dim,) == (19,)
    with pytest.raises(InputError, match="backbone_options must be a mapping"):
        tiny_training.config(backbone_options=["density"])


def test_grad_source_points_must_be_positive():
    with pytest.raises(InputError, match="source_points must be >= 1"):
        GradConfig(source_points=0)
    with pytest.raises(InputError, match="warmup_steps must be >= 0"):
        GradConfig(warmup_steps=-1)


@pytest.mark.parametrize("warmup", [0, 4])
def test_warmup_scales_the_first_adam_steps(warmup):
    """Under a constant gradient Adam moves each weight by its rate, so step k moves it by
    rate * min(1, k / warmup_steps)."""
    from types import SimpleNamespace

    from gloam_jax.training.grad import _optimizer

    cfg = GradConfig(learning_rate=0.01, warmup_steps=warmup)
    optimizer = _optimizer(SimpleNamespace(config=SimpleNamespace(grad=cfg)))
    params, grads = {"w": jnp.zeros(3)}, {"w": jnp.array([0.5, -2.0, 1e-3])}
    state = optimizer.init(params)
    for k in range(1, 7):
        updates, state = optimizer.update(grads, state, params)
        expected = 0.01 * (min(1.0, k / warmup) if warmup else 1.0)
        np.testing.assert_allclose(np.abs(updates["w"]), expected, rtol=1e-4)


def test_the_command_line_sets_equinox_errors_to_nan_unless_told_otherwise():
    import os
    import subprocess
    import sys

    probe = "import gloam_jax.cli, equinox._config as c; print(c.EQX_ON_ERROR)"
    env = {k: v for k, v in os.environ.items() if k != "EQX_ON_ERROR"}
    for setting, expected in ((None, "nan"), ("raise", "raise")):
        run_env = env if setting is None else {**env, "EQX_ON_ERROR": setting}
        out = subprocess.run([sys.executable, "-c", probe], env=run_env, capture_output=True,
                             text=True, check=True)  # fmt: skip
        assert out.stdout.strip() == expected


def test_cli_train_and_a_changed_config(tiny_training, tmp_path):
    # A training step that no other test builds: a new entry in the compilation cache.
    cfg = tiny_training.config(mode="grad", grad=GradConfig(steps=1))
    dump_config(cfg, tmp_path / "train.yaml")
    runner = CliRunner()
    args = ["train", "--config", str(tmp_path / "train.yaml"), "--out", str(tmp_path / "run")]
    steps_before = set((cache_dir() / "jax").glob("jit_update-*"))
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert (tmp_path / "run" / "model.npz").is_file()
    # The compiled training step went into the compilation cache: a rerun loads it (no host
    # callback in it: EQX_ON_ERROR=nan, as the command line sets it).
    assert set((cache_dir() / "jax").glob("jit_update-*")) - steps_before
    result = runner.invoke(app, [*args, "--mode", "tpe"])
    assert result.exit_code == 2
    assert "other settings (mode)" in result.output
    # The overrides reach the settings that the run folder checks (counts may change).
    result = runner.invoke(app, [*args, "--seed", "3", "--n-trials", "7"])
    assert result.exit_code == 2
    assert "other settings (seed)" in result.output
    result = runner.invoke(app, ["train", "--config", str(tmp_path / "missing.yaml")])
    assert result.exit_code == 2 and "file not found" in result.output
