"""Algorithm 1 (learned covariances), the two MLPs, and model files."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gloam_jax import covariance as cov
from gloam_jax.errors import InputError
from gloam_jax.features import fit_pca
from gloam_jax.learned import EigenvalueEstimationMLP, FeatureConversionMLP
from gloam_jax.models import GLOAMModel, init_model, load_model, save_model

# Jitted once: op-by-op dispatch compiles every primitive separately, which is slower.
learned = jax.jit(cov.learned)


def random_covariances(rng, n):
    A = rng.normal(size=(n, 3, 3))
    return A @ A.transpose(0, 2, 1) / 3


def test_algorithm1_properties():
    rng = np.random.default_rng(0)
    C = random_covariances(rng, 200)
    e = rng.normal(size=(200, 3)).astype(np.float32)
    e[:20] = [0.5, -1.0, 2.0]  # a negative value: clamped
    eps = 1e-2
    out = np.asarray(learned(jnp.asarray(C, jnp.float32), jnp.asarray(e), eps), np.float64)
    values, vectors = np.linalg.eigh(C)
    expected = np.maximum(np.sort(e, axis=1), eps)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    # Eigenvectors of the k-NN covariance kept, each with its new eigenvalue, in ascending
    # order: the smallest MLP value goes along the normal (C's smallest eigenvector).
    for i in range(3):
        v = vectors[:, :, i]
        np.testing.assert_allclose(
            np.einsum("nij,nj->ni", out, v), expected[:, i, None] * v, atol=2e-5
        )
    got = np.linalg.eigvalsh(out)
    np.testing.assert_allclose(got, expected, atol=2e-5)
    assert np.all(np.diff(got, axis=1) >= -1e-6)  # ascending
    # Positive definite: the floor is eps / ||e'|| after the scaling (clamp first).
    assert got.min() >= 0.99 * eps / np.linalg.norm(np.maximum(np.sort(e, 1), eps), axis=1).max()
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(got[:20], np.tile(expected[0], (20, 1)), atol=2e-5)
    np.testing.assert_allclose(expected[0], np.array([eps, 0.5, 2.0]) / np.sqrt(eps**2 + 4.25))
    np.testing.assert_allclose(out, out.transpose(0, 2, 1), atol=1e-6)


def test_algorithm1_zero_outputs_and_padding_are_finite():
    C = jnp.concatenate([jnp.eye(3)[None] * 0.1, jnp.zeros((1, 3, 3))])  # a padded zero row
    e = jnp.zeros((2, 3))
    out, grad = jax.jit(jax.value_and_grad(lambda e: cov.learned(C, e, 1e-3).sum()))(e)
    assert np.isfinite(out) and np.all(np.isfinite(grad))
    np.testing.assert_allclose(np.linalg.eigvalsh(learned(C, e, 1e-3)), 1 / np.sqrt(3), rtol=1e-5)


def test_algorithm1_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    with jax.enable_x64(True):
        C = jnp.asarray(random_covariances(rng, 8))
        # Distinct values away from eps, so sort and clamp are locally smooth.
        e0 = jnp.asarray(rng.uniform(0.1, 2.0, (8, 3)))
        W = jnp.asarray(rng.normal(size=(8, 3, 3)))

        @jax.jit
        def loss(e):
            return jnp.sum(W * cov.learned(C, e, 1e-3))

        grad_fn = jax.jit(jax.grad(loss))
        grad = np.asarray(grad_fn(e0))
        h = 1e-6
        numeric = np.zeros((8, 3))
        for idx in np.ndindex(8, 3):
            step = jnp.zeros((8, 3)).at[idx].set(h)
            numeric[idx] = (loss(e0 + step) - loss(e0 - step)) / (2 * h)
        np.testing.assert_allclose(grad, numeric, rtol=1e-6, atol=1e-8)
        # Below eps an output is clamped: no gradient flows to it.
        clamped = e0.at[0, 0].set(-1.0)
        assert grad_fn(clamped)[0, 0] == 0.0


def test_max_thickness_bounds_the_planes_and_keeps_the_gradient():
    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        e = jnp.asarray(rng.uniform(0.05, 2.0, (64, 3)))
        cap = 0.1
        free = np.asarray(cov.learned_values(e, 1e-3))
        bounded = np.asarray(cov.learned_values(e, 1e-3, cap))
        thin = free[:, 0] / free[:, 1] <= cap
        assert 0 < thin.sum() < len(thin)  # both cases occur
        # Thin planes are untouched; thick ones are brought to the bound, in-plane shape kept.
        np.testing.assert_allclose(bounded[thin], free[thin], rtol=1e-12)
        np.testing.assert_allclose(bounded[~thin, 0] / bounded[~thin, 1], cap, rtol=1e-12)
        np.testing.assert_allclose(
            bounded[~thin, 1] / bounded[~thin, 2], free[~thin, 1] / free[~thin, 2], rtol=1e-12
        )
        np.testing.assert_allclose(np.linalg.norm(bounded, axis=1), 1.0, rtol=1e-12)
        # GICP's plane (eps, 1, 1) fits under a bound of eps.
        plane = cov.learned_values(jnp.array([1e-3, 1.0, 1.0]), 1e-3, 1e-3)
        np.testing.assert_allclose(plane, np.array([1e-3, 1, 1]) / np.sqrt(2 + 1e-6), rtol=1e-12)

        # A bounded plane's gradient reaches its middle eigenvalue, which sets its thickness.
        W = jnp.asarray(rng.normal(size=(64, 3)))

        @jax.jit
        def loss(e):
            return jnp.sum(W * cov.learned_values(e, 1e-3, cap))

        grad = np.asarray(jax.grad(loss)(e))
        h = 1e-6
        numeric = np.zeros(e.shape)
        for idx in np.ndindex(*e.shape):
            step = jnp.zeros(e.shape).at[idx].set(h)
            numeric[idx] = (loss(e + step) - loss(e - step)) / (2 * h)
        np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-8)


def test_mlps_per_point_and_batched():
    key = jax.random.PRNGKey(0)
    conv, eig = FeatureConversionMLP.init(key), EigenvalueEstimationMLP.init(key)
    assert sum(x.size for x in jax.tree_util.tree_leaves(conv)) == 43
    f = jnp.asarray(np.random.default_rng(1).normal(size=(50, 6)), jnp.float32)
    batched = eig(f)
    assert batched.shape == (50, 3) and conv(f[0]).shape == (3,)
    # float32 through other compiled programs (a vmapped dot against a matmul): the 6- and
    # 4-term sums may round in another order, a few ulps; 1e-5 is about 80 ulps
    np.testing.assert_allclose(jax.vmap(eig)(f), batched, rtol=1e-5)
    np.testing.assert_allclose(eig(f[3]), batched[3], rtol=1e-5)
    # A pytree: gradients have the MLP's type and shapes.
    g = jax.jit(jax.grad(lambda m: jnp.sum(m(f) ** 2)))(eig)
    assert isinstance(g, EigenvalueEstimationMLP) and g.w1.shape == (6, 4)
    assert not np.allclose(FeatureConversionMLP.init(jax.random.PRNGKey(2)).w1, conv.w1)


@pytest.fixture
def model():
    rng = np.random.default_rng(3)
    raw = rng.normal(size=(500, 20)) @ rng.normal(size=(20, 20))
    pca = fit_pca(raw)
    return raw.astype(np.float32), init_model(
        jax.random.PRNGKey(4), pca, eps=2e-3, backbone_options={"voxel_size": 0.25}
    )


def test_model_round_trip(tmp_path, model):
    raw, m = model
    path = tmp_path / "sub" / "model.npz"
    save_model(path, m)
    loaded = load_model(path)
    assert isinstance(loaded, GLOAMModel)
    assert (loaded.eps, loaded.backbone_name, loaded.backbone_options) == (
        2e-3,
        "geometric",
        {"voxel_size": 0.25},
    )
    for a, b in zip(
        jax.tree_util.tree_leaves((m.pca, m.conversion, m.eigenvalue)),
        jax.tree_util.tree_leaves((loaded.pca, loaded.conversion, loaded.eigenvalue)),
        strict=True,
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # The frozen PCA and both MLPs apply identically after loading.
    f, f2 = m.pca_features(raw), loaded.pca_features(raw)
    np.testing.assert_array_equal(f, f2)
    np.testing.assert_array_equal(m.eigenvalue(f), loaded.eigenvalue(f2))
    np.testing.assert_array_equal(m.conversion(f), loaded.conversion(f2))
    assert f.shape == (500, 6)
    assert 0 < loaded.pca.explained_variance_ratio.sum() <= 1
    with pytest.raises(InputError, match="20 .*expects|expects 20"):
        loaded.pca_features(raw[:, :5])


def test_bad_model_files(tmp_path, model):
    _, m = model
    with pytest.raises(InputError, match="model file not found"):
        load_model(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"\x00\x01 not a zip")
    with pytest.raises(InputError, match="garbage.npz: not a gloam-jax model file"):
        load_model(garbage)
    bare = tmp_path / "bare.npz"
    np.save(tmp_path / "bare.npy", np.zeros(3))
    (tmp_path / "bare.npy").rename(bare)
    with pytest.raises(InputError, match="an .npy array"):
        load_model(bare)
    plain = tmp_path / "plain.npz"
    np.savez(plain, x=np.zeros(3))
    with pytest.raises(InputError, match="no JSON metadata"):
        load_model(plain)
    future = tmp_path / "future.npz"
    save_model(future, dataclasses.replace(m, version=99))
    with pytest.raises(InputError, match="version 99 is not supported") as e:
        load_model(future)
    assert "\n" not in str(e.value)
    broken = tmp_path / "broken.npz"
    save_model(
        broken, dataclasses.replace(m, conversion=m.conversion._replace(w1=jnp.zeros((5, 4))))
    )
    with pytest.raises(InputError, match=r"'conversion_w1' has shape \(5, 4\), expected \(6, 4\)"):
        load_model(broken)


def test_gicp_init_starts_at_the_plane_regulariser(model):
    raw, m = model
    g = init_model(jax.random.PRNGKey(4), m.pca, init="gicp")
    f = g.pca_features(raw)
    values = np.asarray(cov.learned_values(g.eigenvalue(f), g.eps))
    plane = np.array([g.eps, 1.0, 1.0]) / np.sqrt(2 + g.eps**2)
    np.testing.assert_allclose(values, np.broadcast_to(plane, values.shape), rtol=1e-6)
    # Yet the eigenvalue MLP has a gradient there: its output weights see the hidden layer.
    grad = jax.grad(lambda w2: cov.learned_values(g.eigenvalue._replace(w2=w2)(f), g.eps).sum())
    assert np.abs(np.asarray(grad(g.eigenvalue.w2))).max() > 1e-3
    # Association features vary (they need a gradient) but by centimetres against metres.
    converted = np.asarray(g.conversion(f))
    assert 0 < converted.std(axis=0).max() < 0.03
    with pytest.raises(InputError, match="unknown init 'plane'"):
        init_model(jax.random.PRNGKey(4), m.pca, init="plane")


def test_max_thickness_round_trip_and_bad_values(tmp_path, model):
    _, m = model
    assert m.max_thickness is None and m.learned.max_thickness is None
    save_model(tmp_path / "free.npz", m)
    assert load_model(tmp_path / "free.npz").max_thickness is None
    with np.load(tmp_path / "free.npz") as z:  # a file without the bound reads as before it
        assert "max_thickness" not in str(z["metadata"])
    save_model(tmp_path / "thin.npz", dataclasses.replace(m, max_thickness=0.005))
    loaded = load_model(tmp_path / "thin.npz")
    assert loaded.max_thickness == 0.005 and loaded.learned.max_thickness == 0.005
    with pytest.raises(InputError, match=r"max_thickness must be in \[eps = 0.002, 1\], got 0.001"):
        dataclasses.replace(m, max_thickness=0.001)  # m.eps is 0.002: its plane would not fit
    # A file edited by hand: the error names it.
    with np.load(tmp_path / "thin.npz") as z:
        arrays = dict(z)
    arrays["metadata"] = np.array(str(arrays["metadata"]).replace("0.005", '"thin"'))
    np.savez(tmp_path / "edited.npz", **arrays)
    with pytest.raises(InputError, match="edited.npz: max_thickness must be a number or null"):
        load_model(tmp_path / "edited.npz")


def test_provenance_round_trip(tmp_path, model):
    _, m = model
    info = {"mode": "grad", "train_t_err": 0.0071, "config": {"seed": 3}}
    save_model(tmp_path / "m.npz", dataclasses.replace(m, provenance=info))
    assert load_model(tmp_path / "m.npz").provenance == info


def test_shipped_model_loads_and_says_how_it_was_trained():
    shipped = load_model("default")
    assert shipped.backbone_name == "geometric"
    prov = shipped.provenance
    assert prov["mode"] in ("tpe", "grad") and np.isfinite(prov["train_t_err"])
    # Under the protocol (docs/protocol.md): fitted on train worlds only, chosen on the val
    # worlds against plain GICP, and scored on the test worlds afterwards.
    from gloam_jax.training.protocol import SPLITS

    ids = {split: {w.sequence for w in SPLITS[split]} for split in SPLITS}
    assert set(prov["config"]["sequences"]) <= ids["train"]
    assert prov["selected_on"] == "validation"
    assert set(prov["validation"]["sequences"]) <= ids["val"]
    assert prov["selected_value"] < prov["validation_gicp"]
    scores = [s for s in prov["test_scores"] if s["method"] == "gloam"]
    assert scores and set(scores[0]["worlds"]) == ids["test"]


def test_shipped_hdl64_model_was_chosen_on_long_validation_among_three_seeds():
    model = load_model("hdl64")
    prov = model.provenance
    assert prov["selected_on"] == "val_long" and prov["objective"] == "mean t_err / GICP"
    selection = prov["selection"]
    assert len(selection["files"]) == 3 and selection["worlds"] == ["401", "403", "404"]
    assert prov["selected_value"] == min(selection["files"].values()) < 1.0
    assert [s.name for s in model.sensors] == ["hdl64"] and model.sensors[0].rings == 64
