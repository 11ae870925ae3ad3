"""Data association in [xyz, f] space: hard argmin and softmax weights."""

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax import association

hard = jax.jit(association.hard)
soft = jax.jit(association.soft)


def candidates(seed=0, n=400, k=5, f=3):
    """Source points a (n, 3), candidates b (n, k, 3), features and a validity mask."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-10, 10, (n, 3)).astype(np.float32)
    b = (a[:, None] + rng.normal(0, 0.5, (n, k, 3))).astype(np.float32)
    fa = rng.normal(size=(n, f)).astype(np.float32)
    fb = rng.normal(size=(n, k, f)).astype(np.float32)
    valid = rng.uniform(size=(n, k)) < 0.7
    valid[:10] = False  # rows without any candidate
    b[:20, 1] = b[:20, 0]  # exact ties: the first index wins, as in gicp
    return tuple(map(jnp.asarray, (a, b, fa, fb, valid)))


def test_zero_features_equal_plain_nearest_exactly():
    a, b, fa, fb, valid = candidates()
    j = hard(a, b, jnp.zeros_like(fa), jnp.zeros_like(fb), valid)
    # The xyz-only choice as gloam_jax.gicp makes it.
    d2 = jnp.where(valid, jnp.sum((b - a[:, None, :]) ** 2, axis=-1), jnp.inf)
    np.testing.assert_array_equal(j, jnp.argmin(d2, axis=1))
    # And the same as a brute-force search in NumPy on the valid rows.
    d2 = np.where(valid, np.sum((np.asarray(b) - np.asarray(a)[:, None]) ** 2, -1), np.inf)
    rows = np.asarray(valid).any(1)
    np.testing.assert_array_equal(np.asarray(j)[rows], np.argmin(d2, 1)[rows])


def test_hard_uses_features_and_never_picks_invalid():
    a, b, fa, fb, valid = candidates(1)
    j = np.asarray(hard(a, b, fa, fb, valid))
    rows = np.asarray(valid).any(1)
    assert np.all(np.asarray(valid)[rows, j[rows]])
    cost = np.sum((np.asarray(b) - np.asarray(a)[:, None]) ** 2, -1)
    cost += np.sum((np.asarray(fb) - np.asarray(fa)[:, None]) ** 2, -1)
    np.testing.assert_array_equal(j[rows], np.argmin(np.where(valid, cost, np.inf), 1)[rows])
    # Features move the choice away from the nearest point for some rows.
    nearest = np.asarray(hard(a, b, 0 * fa, 0 * fb, valid))
    assert np.any(nearest[rows] != j[rows])


def test_soft_weights():
    a, b, fa, fb, valid = candidates(2)
    w = np.asarray(soft(a, b, fa, fb, valid, 0.5))
    rows = np.asarray(valid).any(1)
    assert np.all(np.isfinite(w))
    np.testing.assert_allclose(w[rows].sum(1), 1.0, rtol=1e-5)
    assert np.all(w[~np.asarray(valid)] == 0) and np.all(w[~rows] == 0)
    # Cold: the weight concentrates on the hard choice.
    cold = np.asarray(soft(a, b, fa, fb, valid, 1e-4))
    j = np.asarray(hard(a, b, fa, fb, valid))
    np.testing.assert_allclose(cold[rows, j[rows]], 1.0, atol=1e-3)


def test_soft_gradients_finite():
    a, b, fa, fb, valid = candidates(3)
    target = jnp.asarray(np.random.default_rng(4).normal(size=valid.shape), jnp.float32)

    def loss(fa, fb, temperature):
        return jnp.sum(target * association.soft(a, b, fa, fb, valid, temperature))

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(fa, fb, 0.3)
    assert all(np.all(np.isfinite(g)) for g in grads)
    assert np.all(np.asarray(grads[0])[:10] == 0)  # rows without candidates
    assert np.any(np.asarray(grads[0]) != 0)
