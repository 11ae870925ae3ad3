"""Feature novelty: the MLPs' inputs clamped to the region of the training features."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from gloam_jax.cli import app
from gloam_jax.config import dump_config
from gloam_jax.errors import InputError
from gloam_jax.features.novelty import fit_novelty
from gloam_jax.learned import EigenvalueEstimationMLP, FeatureConversionMLP, Learned, attributes
from gloam_jax.models import load_model, save_model


def test_fit_on_gaussian_features_gives_the_chi2_quantile_and_clamps_onto_it():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    x = rng.normal(size=(200_000, 6)) @ A + 3.0
    nov = fit_novelty(x, quantile=0.99)
    assert nov.radius2 == pytest.approx(16.81, rel=0.03)  # chi-square, 6 dof: 99 % quantile
    # d2 is the Mahalanobis distance under the fitted covariance
    L = np.linalg.cholesky(np.cov(x, rowvar=False))
    mean = x.mean(axis=0)
    z = np.array([[1.0, -2.0, 0.5, 0.0, 3.0, 1.0], [10.0, 0.0, -5.0, 2.0, 0.0, 4.0]])
    f = jnp.asarray(mean + z @ L.T)
    np.testing.assert_allclose(nov.squared_distance(f), np.sum(z**2, axis=1), rtol=1e-3)
    # inside: unchanged; beyond: on the boundary, along the same ray from the mean
    g = np.asarray(nov.clamp(f))
    np.testing.assert_allclose(g[0], f[0], rtol=1e-12)
    # g[1] is rounded to float32 (|g| ~ 13, 11 from the mean, covariance condition ~100): d2
    # may move by up to 2 * 6e-8 * (13 * sqrt(6) / 11) * sqrt(100) ~ 3.5e-6 relative (-9e-8 here).
    assert float(nov.squared_distance(jnp.asarray(g[1]))) == pytest.approx(nov.radius2, rel=1e-5)
    ray, moved = np.asarray(f[1]) - mean, g[1] - mean
    np.testing.assert_allclose(moved / np.linalg.norm(moved), ray / np.linalg.norm(ray), atol=1e-6)


def test_fit_rejects_too_few_rows_and_a_bad_quantile():
    with pytest.raises(InputError, match="more finite rows than columns"):
        fit_novelty(np.ones((3, 6)))
    with pytest.raises(InputError, match="quantile"):
        fit_novelty(np.random.default_rng(0).normal(size=(50, 6)), quantile=1.5)


def _parts(key=0):
    k1, k2 = jax.random.split(jax.random.PRNGKey(key))
    return Learned(FeatureConversionMLP.init(k1), EigenvalueEstimationMLP.init(k2))


def test_the_mlps_see_familiar_features_as_they_are_and_novel_ones_clamped():
    rng = np.random.default_rng(1)
    nov = fit_novelty(rng.normal(size=(5000, 6)))
    f = jnp.asarray(np.stack([np.zeros(6), np.full(6, 10.0)]), jnp.float32)  # d2 0 and ~600
    vectors = jnp.asarray(np.stack([np.eye(3), np.linalg.qr(rng.normal(size=(3, 3)))[0]]),
                          jnp.float32)  # fmt: skip
    values = jnp.asarray([[0.01, 0.5, 1.0], [0.02, 0.3, 0.9]], jnp.float32)
    parts = _parts()
    covs, feats = attributes(values, vectors, f, parts, "plane")
    gated_covs, gated_feats = attributes(values, vectors, f, parts._replace(novelty=nov), "plane")
    at_edge = attributes(values, vectors, nov.clamp(f), parts, "plane")
    # the clamp leaves a familiar point's features as they are, but the gated attributes are
    # another compiled program: float32 sums may round differently (a few ulps; 1e-5 is ~80)
    np.testing.assert_allclose(gated_covs[0], covs[0], rtol=1e-5)
    np.testing.assert_allclose(gated_feats[0], feats[0], rtol=1e-5)
    np.testing.assert_allclose(gated_covs[1], at_edge[0][1], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(gated_feats[1], at_edge[1][1], rtol=1e-5)
    assert np.abs(np.asarray(feats[1]) - np.asarray(gated_feats[1])).max() > 0.1


def test_gradients_reach_the_mlps_not_the_novelty():
    rng = np.random.default_rng(2)
    nov = fit_novelty(rng.normal(size=(5000, 6)))
    f = jnp.asarray(rng.normal(size=(8, 6)) * 2.0, jnp.float32)  # some beyond the radius
    vectors = jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (8, 3, 3))
    values = jnp.ones((8, 3), jnp.float32)

    def loss(parts):
        covs, feats = attributes(values, vectors, f, parts, "plane")
        return jnp.sum(covs**2) + jnp.sum(feats**2)

    g = jax.grad(loss)(_parts()._replace(novelty=nov))
    assert float(jnp.abs(g.eigenvalue.w2).sum()) > 0
    assert float(jnp.abs(g.conversion.w2).sum()) > 0
    assert float(jnp.abs(g.novelty.mean).sum()) == 0


def test_model_file_keeps_the_novelty_and_rejects_a_broken_one(tiny_training, tmp_path):
    nov = fit_novelty(np.random.default_rng(3).normal(size=(500, 6)))
    model = dataclasses.replace(tiny_training.model, novelty=nov)
    path = tmp_path / "m.npz"
    save_model(path, model)
    back = load_model(path)
    np.testing.assert_allclose(back.novelty.factor, nov.factor)
    assert back.novelty.radius2 == pytest.approx(nov.radius2)
    assert back.learned.novelty is back.novelty
    assert load_model(tiny_training.start).novelty is None
    with np.load(path) as z:
        arrays = dict(z)
    arrays["novelty_factor"] = arrays["novelty_factor"][:3]
    broken = tmp_path / "broken.npz"
    np.savez(broken, **arrays)
    with pytest.raises(InputError, match=r"'novelty_factor' has shape \(3, 6\), expected \(6, 6\)"):
        load_model(broken)


def test_gloam_novelty_fits_on_the_training_worlds(tiny_training, tmp_path):
    config = tmp_path / "train.yaml"
    dump_config(tiny_training.config(), config)
    out = tmp_path / "gated.npz"
    result = CliRunner().invoke(
        app,
        [
            "novelty",
            str(tiny_training.start),
            "--config",
            str(config),
            "--out",
            str(out),
            "--quantile",
            "0.9",
            "--cache",
            str(tmp_path / "cache"),
        ],  # fmt: skip
    )
    assert result.exit_code == 0, result.output
    model = load_model(out)
    record = model.provenance["novelty"]
    assert record["quantile"] == 0.9 and record["fitted_on"]["sequences"] == ["00"]
    assert record["points"] > 1000
    # about a tenth of the training points it was fitted on lie beyond the trusted region
    from gloam_jax.training.novelty import window_features

    cfg = tiny_training.config()
    features = window_features(model, cfg, cfg.training_roots, cfg.sequences,
                               cache_dir=tmp_path / "cache")  # fmt: skip
    f = np.concatenate([x for per in features.values() for x in per])
    d2 = np.asarray(model.novelty.squared_distance(jnp.asarray(f)))
    beyond = np.mean(d2 > model.novelty.radius2)
    assert beyond == pytest.approx(0.1, abs=0.01)
    info = CliRunner().invoke(app, ["model-info", str(out)])
    assert "novelty: MLP inputs clamped to d2" in info.output
    missing = CliRunner().invoke(app, ["novelty", str(tmp_path / "none.npz"), "--config",
                                       str(config), "--out", str(out)])  # fmt: skip
    assert missing.exit_code != 0 and "model file not found" in missing.output


def test_training_from_a_clamped_model_keeps_its_region_and_exports_it(tiny_training, tmp_path):
    from gloam_jax.training.config import GradConfig
    from gloam_jax.training.grad import train_grad
    from gloam_jax.training.novelty import fit_model_novelty
    from gloam_jax.training.problem import setup

    cache = tmp_path / "cache"
    clamped = fit_model_novelty(tiny_training.model, tiny_training.config(), quantile=0.5,
                                cache_dir=cache)  # fmt: skip
    start = tmp_path / "start.npz"
    save_model(start, clamped)
    grad = GradConfig(steps=1, eval_every=1, learning_rate=0.01, source_points=64)
    cfg = tiny_training.config(mode="grad", grad=grad, init_model=str(start))
    problem = setup(cfg, tmp_path / "run", cache_dir=cache)
    assert problem.init_params.novelty is not None  # the training registrations clamp too
    trained = train_grad(problem)
    np.testing.assert_array_equal(np.asarray(trained.novelty.factor), clamped.novelty.factor)
    exported = load_model(tmp_path / "run" / "model.npz")
    np.testing.assert_array_equal(exported.novelty.mean, clamped.novelty.mean)
    assert exported.novelty.radius2 == pytest.approx(clamped.novelty.radius2)
