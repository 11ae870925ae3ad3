"""GICP registration: neighbour sets, covariances, recovered transforms, bad input."""

import jax
import numpy as np
import pytest
from shared_data import shared_path

from gloam_jax import covariance as cov
from gloam_jax import geometry as geo
from gloam_jax import io
from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError
from gloam_jax.gicp import GICPConfig
from gloam_jax.neighbors import KdTree
from gloam_jax.registration import align, prepare


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) of T_est against T_true."""
    D = np.linalg.inv(T_true) @ T_est
    angle = np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))
    return float(np.linalg.norm(D[:3, 3])), float(np.rad2deg(angle))


def structured_scene(seed: int = 0, n: int = 20000) -> np.ndarray:
    """Points on a floor, two perpendicular walls, a slanted roof and some poles: (n, 3)."""
    rng = np.random.default_rng(seed)
    k = n // 5
    floor = np.c_[rng.uniform(-20, 20, k), rng.uniform(-20, 20, k), np.zeros(k)]
    wall_x = np.c_[np.full(k, 12.0), rng.uniform(-20, 20, k), rng.uniform(0, 6, k)]
    wall_y = np.c_[rng.uniform(-20, 20, k), np.full(k, -9.0), rng.uniform(0, 6, k)]
    u, v = rng.uniform(-10, 10, k), rng.uniform(0, 5, k)
    roof = np.c_[u, 9.0 + 0.6 * v, 3.0 + 0.8 * v]
    angles, heights = rng.uniform(0, 2 * np.pi, n - 4 * k), rng.uniform(0, 5, n - 4 * k)
    centres = np.array([[5.0, 3.0], [-6.0, -4.0], [2.0, -7.0], [-3.0, 6.0]])
    c = centres[rng.integers(0, 4, n - 4 * k)]
    poles = np.c_[c + 0.15 * np.c_[np.cos(angles), np.sin(angles)], heights]
    return np.concatenate([floor, wall_x, wall_y, roof, poles]) + rng.normal(0, 0.005, (n, 3))


def test_knn_matches_brute_force():
    rng = np.random.default_rng(0)
    pts, queries = rng.uniform(-5, 5, (500, 3)), rng.uniform(-5, 5, (50, 3))
    idx, valid = KdTree(pts).query(queries, 7, max_distance=2.0)
    d = np.linalg.norm(queries[:, None] - pts[None], axis=-1)
    brute = np.argsort(d, axis=1)[:, :7]
    expected_valid = np.take_along_axis(d, brute, 1) <= 2.0
    np.testing.assert_array_equal(valid, expected_valid)
    np.testing.assert_array_equal(np.where(valid, idx, -1), np.where(expected_valid, brute, -1))


def test_covariances_and_regularisers():
    rng = np.random.default_rng(1)
    plane_pts = np.c_[rng.uniform(-1, 1, (400, 2)), 0.001 * rng.normal(size=400)]
    nb, _ = KdTree(plane_pts).query(plane_pts, 20)
    C = cov.knn_covariances(jax.numpy.asarray(plane_pts), jax.numpy.asarray(nb))
    # Brute-force check of one covariance.
    expected = np.cov(plane_pts[nb[0]].T, bias=True)
    np.testing.assert_allclose(C[0], expected, atol=1e-6)
    for name, expected_values in (("plane", [cov.PLANE_EPS, 1, 1]),):
        values, vectors = np.linalg.eigh(np.asarray(cov.REGULARIZERS[name](C)))
        np.testing.assert_allclose(
            values, np.broadcast_to(expected_values, values.shape), atol=1e-5
        )
        # The normal (z) keeps the small eigenvalue.
        assert np.all(np.abs(vectors[:, 2, 0]) > 0.99)
    clamped = np.linalg.eigvalsh(np.asarray(cov.raw_eps(C, eps=1e-3)))
    assert clamped.min() >= 1e-3 - 1e-7
    np.testing.assert_allclose(clamped[:, 2], np.linalg.eigvalsh(np.asarray(C))[:, 2], rtol=1e-4)


def test_closed_form_eigendecomposition_matches_numpy():
    rng = np.random.default_rng(5)
    R = np.linalg.qr(rng.normal(size=(300, 3, 3)))[0]
    spreads = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1e-3], [1.0, 1e-3, 1e-3], [1.0, 0.3, 0.05]])
    values = np.repeat(spreads, 75, axis=0) * rng.uniform(0.01, 4.0, (300, 1))
    C = np.einsum("nij,nj,nkj->nik", R, values, R)
    special = np.stack(
        [np.zeros((3, 3)), np.eye(3), np.diag([2.0, 2.0, 0.0]), np.diag([0, 0, 5.0])]
    )
    C = np.concatenate([C, special]).astype(np.float32)
    got_values, vectors = (np.asarray(x, np.float64) for x in jax.jit(cov.eigendecompose)(C))
    scale = np.abs(C).max(axis=(1, 2)) + 1e-30
    expected = np.linalg.eigvalsh(C.astype(np.float64))
    # float32: a repeated eigenvalue puts the trigonometric formula's arccos at +-1, where it
    # loses half the digits (~sqrt(eps) = 3e-4 relative); the eigenvectors stay orthonormal.
    assert np.all(np.abs(got_values - expected) <= 5e-4 * scale[:, None])
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", vectors, vectors), np.broadcast_to(np.eye(3), C.shape), atol=1e-5
    )
    residual = np.einsum("nij,njk->nik", C, vectors) - vectors * got_values[:, None, :]
    assert np.all(np.abs(residual).max(axis=(1, 2)) <= 5e-4 * scale)


@pytest.mark.parametrize(
    "xi",
    [
        [0.8, -0.3, 0.05, 0.0, 0.0, np.deg2rad(4.0)],
        [-0.5, 0.6, 0.1, np.deg2rad(1.0), np.deg2rad(-1.0), np.deg2rad(-6.0)],
    ],
)
def test_recovers_known_transform(xi):
    target = structured_scene(0)
    T_true = np.asarray(geo.se3_exp(np.asarray(xi, np.float32)), dtype=np.float64)
    # A different sampling of the same surfaces, seen from the transformed pose.
    source = structured_scene(1) @ T_true[:3, :3] - T_true[:3, :3].T @ T_true[:3, 3]
    result = align(target, source, downsampling_resolution=0.2)
    dt, dr = transform_error(result.T_target_source, T_true)
    assert result.converged
    assert dt < 0.01 and dr < 0.05
    assert result.num_inliers > 0.8 * len(prepare(source, downsampling_resolution=0.2).points)
    assert result.H.shape == (6, 6) and np.all(np.linalg.eigvalsh(result.H) > 0)


def test_candidate_choice_in_jax_matches_nearest_neighbour():
    target = structured_scene(0)
    source = structured_scene(2) + np.array([0.3, -0.2, 0.0])
    one = align(target, source, config=GICPConfig(num_candidates=1))
    five = align(target, source, config=GICPConfig(num_candidates=5))
    dt, dr = transform_error(one.T_target_source, five.T_target_source)
    assert dt < 0.005 and dr < 0.02


def test_kept_candidates_save_queries_and_reach_the_same_transform():
    """With requery_shift, rounds whose points moved less keep their candidates (and the
    conditioning reuses their nearest): fewer k-d tree queries, the same answer; 0 queries
    every round and once more for the conditioning."""
    target = structured_scene(0)
    T_true = np.asarray(geo.se3_exp(np.array([0.03, -0.02, 0.0, 0.0, 0.0, 0.002])), np.float64)
    source = structured_scene(4) @ T_true[:3, :3] - T_true[:3, :3].T @ T_true[:3, 3]
    every = align(target, source, config=GICPConfig(requery_shift=0.0))
    kept = align(target, source, config=GICPConfig(requery_shift=0.1))
    assert every.queries == every.iterations + 1
    assert kept.queries < every.queries and kept.queries >= 1 and kept.converged
    dt, dr = transform_error(kept.T_target_source, every.T_target_source)
    assert dt < 0.002 and dr < 0.01
    assert transform_error(kept.T_target_source, T_true)[0] < 0.01
    assert kept.condition == pytest.approx(every.condition, rel=0.05)
    for bad in (-0.1, 0.2):  # kept candidates must still count as fresh (0.1 x 1 m)
        with pytest.raises(InputError, match="gicp.requery_shift must be between 0 and 0.1 m"):
            GICPConfig(requery_shift=bad)


def test_real_pair_recovers_reference():
    PAIR = shared_path("real_pair")
    target = pc.crop_range(io.read_scan(PAIR / "251370668.pcd"), 0.5, 200.0)
    source = pc.crop_range(io.read_scan(PAIR / "251371071.pcd"), 0.5, 200.0)
    reference = np.loadtxt(PAIR / "relative.txt")
    result = align(target, source, downsampling_resolution=0.05, num_neighbors=20)
    dt, dr = transform_error(result.T_target_source, reference)
    assert dt < 0.05 and dr < 0.2


def test_agrees_with_small_gicp():
    import small_gicp

    target = structured_scene(0)
    T_true = np.asarray(geo.se3_exp(np.array([0.6, 0.2, 0.0, 0.0, 0.0, 0.05])), np.float64)
    source = structured_scene(3) @ T_true[:3, :3] - T_true[:3, :3].T @ T_true[:3, 3]
    ours = align(target, source, downsampling_resolution=0.25)
    peer = small_gicp.align(
        target, source, downsampling_resolution=0.25, max_correspondence_distance=1.0, num_threads=2
    )
    dt, dr = transform_error(ours.T_target_source, peer.T_target_source)
    assert dt < 0.01 and dr < 0.05


def test_bad_input():
    with pytest.raises(InputError, match="empty scan"):
        prepare(np.zeros((0, 3)), name="a.bin")
    with pytest.raises(InputError, match="a.bin: all 5 points are NaN"):
        prepare(np.full((5, 3), np.nan), name="a.bin")
    with pytest.raises(InputError, match="too few points for 20 neighbours"):
        prepare(np.random.default_rng(0).normal(size=(10, 3)), name="a.bin")
    pts = structured_scene(0, 4000)
    pts[::100] = np.nan
    cloud = prepare(pts, downsampling_resolution=0.0)
    assert cloud.num_dropped == 40 and len(cloud.points) == 3960
    with pytest.raises(InputError, match="unknown regularizer"):
        align(pts, pts, regularizer="sphere")


@pytest.mark.parametrize("num_partners", [1, 3])
def test_analytic_gauss_newton_matches_autodiff(num_partners):
    """Hard partners (one each) and soft ones (three, with weights)."""
    import jax.numpy as jnp

    from gloam_jax.gicp import Cloud, Partners, _whitened, gauss_newton_system, make_pairs, retract

    rng = np.random.default_rng(4)
    n = 64
    target_points = rng.normal(size=(n, 3)).astype(np.float32)
    A = rng.normal(size=(n, 3, 3))
    target_covs = (A @ A.transpose(0, 2, 1) + 0.1 * np.eye(3)).astype(np.float32)
    # Anisotropic source covariances: both hold the weights' rotation fixed, as GICP does.
    source_covs = np.tile(np.diag([0.05, 0.2, 0.4]), (n, 1, 1)).astype(np.float32)
    no_features = jnp.zeros((n, 0), jnp.float32)
    source = Cloud(
        jnp.asarray(target_points + 0.05), jnp.asarray(source_covs), jnp.ones(n, bool), no_features
    )
    target = Cloud(
        jnp.asarray(target_points), jnp.asarray(target_covs), jnp.ones(n, bool), no_features
    )
    index = (np.arange(n)[:, None] + np.arange(num_partners)) % n
    weights = rng.uniform(0.1, 1.0, size=index.shape) if num_partners > 1 else np.ones((n, 1))
    partners = Partners(
        target.points[index], target.covs[index], jnp.asarray(np.sqrt(weights), jnp.float32)
    )
    T = jnp.asarray(geo.se3_exp(np.array([0.01, -0.02, 0.03, 0.02, -0.01, 0.015])), jnp.float32)
    # Weights at a rotation other than T's: the system holds them fixed, whatever they are.
    R_weights = jnp.asarray(geo.so3_exp(np.array([0.1, 0.0, -0.05])), jnp.float32)
    args = (T, make_pairs(R_weights, source, partners), jnp.float32(100.0))
    H, b, error, inliers = gauss_newton_system(*args)

    def residuals(xi):
        return _whitened(retract(xi, T), *args[1:])[0].reshape(-1)

    J = jax.jacrev(residuals)(jnp.zeros(6))
    e = residuals(jnp.zeros(6))
    np.testing.assert_allclose(H, J.T @ J, rtol=2e-4, atol=1e-3)
    np.testing.assert_allclose(b, J.T @ e, rtol=2e-4, atol=1e-4)
    assert float(error) == pytest.approx(float(e @ e), rel=1e-5)
    assert int(inliers) == n * num_partners


def test_round_cost_is_the_sum_of_squared_whitened_residuals():
    """|L^T g(xi) - u|^2 differs from sum |W (b - T a)|^2 by a constant, for any increment."""
    import jax.numpy as jnp

    from gloam_jax.gicp import (
        Cloud,
        Partners,
        _residuals,
        _whitened,
        make_pairs,
        retract,
        round_cost,
    )

    rng = np.random.default_rng(5)
    n = 200
    jax.config.update("jax_enable_x64", True)
    try:
        a = rng.uniform(-40, 40, (n, 3))
        A = rng.normal(size=(n, 3, 3))
        covs = A @ A.transpose(0, 2, 1) + 0.05 * np.eye(3)
        none = jnp.zeros((n, 0))
        source = Cloud(jnp.asarray(a), jnp.asarray(covs), jnp.ones(n, bool), none)
        target = Cloud(jnp.asarray(a + rng.normal(0, 0.1, (n, 3))), jnp.asarray(covs[::-1]),
                       jnp.ones(n, bool), none)  # fmt: skip
        T0 = jnp.asarray(geo.se3_exp(np.array([500.0, -20.0, 3.0, 0.01, 0.02, -0.5])))
        target = target._replace(points=target.points @ T0[:3, :3].T + T0[:3, 3])
        partners = Partners(target.points[:, None], target.covs[:, None], jnp.ones((n, 1)))
        pairs = make_pairs(T0[:3, :3], source, partners)
        cost = round_cost(T0, pairs, 1e6)

        def both(xi):
            xi = jnp.asarray(xi)
            e = _whitened(retract(xi, T0), pairs, 1e6)[0]
            return float(jnp.sum(_residuals(xi, cost) ** 2)), float(jnp.sum(e * e))

        form0, exact0 = both(np.zeros(6))
        for xi in rng.normal(0, [0.3, 0.3, 0.3, 0.02, 0.02, 0.02], (5, 6)):
            form, exact = both(xi)
            assert form - form0 == pytest.approx(exact - exact0, rel=1e-9)
    finally:
        jax.config.update("jax_enable_x64", False)


def test_runs_in_float64_mode_too():
    target = structured_scene(0)
    T_true = np.asarray(geo.se3_exp(np.array([0.4, -0.2, 0.0, 0.0, 0.0, 0.03])), np.float64)
    source = structured_scene(5) @ T_true[:3, :3] - T_true[:3, :3].T @ T_true[:3, 3]
    jax.config.update("jax_enable_x64", True)
    try:
        result = align(target, source, downsampling_resolution=0.3)
    finally:
        jax.config.update("jax_enable_x64", False)
    dt, dr = transform_error(result.T_target_source, T_true)
    assert dt < 0.01 and dr < 0.05
