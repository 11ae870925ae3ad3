"""Property tests of the SO(3)/SE(3) module, in float64."""

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from gloam_jax import geometry as geo


@pytest.fixture(autouse=True, scope="module")
def x64():
    """float64 for this module only; the rest of the suite runs the default float32 path."""
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", False)


finite = st.floats(-3.0, 3.0, allow_nan=False, allow_subnormal=False)
vec3 = arrays(np.float64, 3, elements=finite)
vec6 = arrays(np.float64, 6, elements=finite)
rot_vec = vec3.filter(lambda v: np.linalg.norm(v) < np.pi - 1e-3)
tangent = vec6.filter(lambda v: np.linalg.norm(v[3:]) < np.pi - 1e-3)
SETTINGS = settings(max_examples=40, deadline=None)

# Jitted once so that each hypothesis example runs compiled code instead of re-tracing.
so3_exp, so3_log = jax.jit(geo.so3_exp), jax.jit(geo.so3_log)
se3_exp, se3_log = jax.jit(geo.se3_exp), jax.jit(geo.se3_log)
se3_inverse, se3_apply = jax.jit(geo.se3_inverse), jax.jit(geo.se3_apply)


def _twisted(x):
    return geo.se3_log(geo.se3_exp(x) @ geo.se3_exp(0.3 * x))


JACOBIANS = [
    (jax.jit(f), jax.jit(jax.jacfwd(f)), jax.jit(jax.jacrev(f))) for f in (geo.se3_exp, _twisted)
]


def _is_rotation(R):
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


@SETTINGS
@given(rot_vec)
def test_so3_exp_log_round_trip(phi):
    R = np.asarray(so3_exp(phi))
    _is_rotation(R)
    np.testing.assert_allclose(so3_log(R), phi, atol=1e-9)


@SETTINGS
@given(tangent)
def test_se3_exp_log_round_trip(xi):
    np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-9)


@SETTINGS
@given(tangent, tangent, tangent)
def test_group_axioms(a, b, c):
    A, B, C = (np.asarray(se3_exp(x)) for x in (a, b, c))
    eye = np.eye(4)
    np.testing.assert_allclose(A @ se3_inverse(A), eye, atol=1e-12)
    np.testing.assert_allclose(se3_inverse(A) @ A, eye, atol=1e-12)
    np.testing.assert_allclose((A @ B) @ C, A @ (B @ C), atol=1e-10)
    np.testing.assert_allclose(geo.se3_compose(A, eye), A, atol=1e-15)


@SETTINGS
@given(tangent, arrays(np.float64, (5, 3), elements=finite))
def test_apply_matches_homogeneous_product(xi, points):
    T = np.asarray(se3_exp(xi))
    expected = (T[:3, :3] @ points.T).T + T[:3, 3]
    np.testing.assert_allclose(se3_apply(T, points), expected, atol=1e-12)


def test_batching_broadcasts():
    xi = np.random.default_rng(0).normal(size=(4, 7, 6)) * 0.5
    T = geo.se3_exp(xi)
    assert T.shape == (4, 7, 4, 4)
    assert geo.se3_log(T).shape == (4, 7, 6)
    np.testing.assert_allclose(geo.se3_exp(xi[2, 3]), T[2, 3], atol=1e-14)


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-5, 0.05, 0.2])
def test_small_angles_finite_and_accurate(scale):
    xi = np.array([0.3, -0.2, 0.1, 0.5, -0.4, 0.7]) * np.array([1, 1, 1, scale, scale, scale])
    T = geo.se3_exp(xi)
    np.testing.assert_allclose(geo.se3_log(T), xi, atol=1e-12)
    jac = jax.jacfwd(lambda x: geo.se3_log(geo.se3_exp(x)))(xi)
    np.testing.assert_allclose(jac, np.eye(6), atol=1e-8)


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [1, -2, 0.5]])
def test_log_at_pi(axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    R = np.asarray(geo.so3_exp(np.pi * axis))
    phi = np.asarray(geo.so3_log(R))
    assert np.linalg.norm(phi) == pytest.approx(np.pi, abs=1e-9)
    # At pi the axis sign is ambiguous; both give the same rotation.
    np.testing.assert_allclose(geo.so3_exp(phi), R, atol=1e-9)
    grad = jax.grad(lambda m: geo.rotation_angle(m))(R)
    assert np.all(np.isfinite(grad))


def test_gradients_finite_at_identity():
    for f in (geo.so3_exp, lambda p: geo.so3_log(geo.so3_exp(p)), geo.rotation_angle):
        arg = np.zeros(3) if f is not geo.rotation_angle else np.eye(3)
        jac = jax.jacrev(lambda a, f=f: f(a))(arg)
        assert np.all(np.isfinite(jac))


def _numeric_jacobian(f, x, eps=1e-6):
    cols = []
    for i in range(x.size):
        d = np.zeros_like(x)
        d[i] = eps
        cols.append((np.asarray(f(x + d)) - np.asarray(f(x - d))) / (2 * eps))
    return np.stack(cols, axis=-1)


@SETTINGS
@given(tangent.filter(lambda v: 0.05 < np.linalg.norm(v[3:]) < 3.0))
def test_autodiff_matches_finite_differences(xi):
    for f, jacfwd, jacrev in JACOBIANS:
        fwd = np.asarray(jacfwd(xi))
        rev = np.asarray(jacrev(xi))
        num = _numeric_jacobian(f, xi)
        np.testing.assert_allclose(fwd, rev, atol=1e-10)
        np.testing.assert_allclose(fwd, num, atol=1e-6)


def test_quaternion_round_trip_and_hemisphere():
    phi = np.random.default_rng(1).normal(size=(50, 3))
    R = geo.so3_exp(phi)
    q = np.asarray(geo.quat_from_rotation(R))
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(geo.rotation_from_quat(q), R, atol=1e-12)


def test_interpolate_endpoints_and_midpoint():
    A = geo.se3_exp(np.array([1.0, 2, 3, 0.1, 0.2, 0.3]))
    B = geo.se3_exp(np.array([2.0, 0, 1, -0.2, 0.4, 0.1]))
    np.testing.assert_allclose(geo.se3_interpolate(A, B, 0.0), A, atol=1e-12)
    np.testing.assert_allclose(geo.se3_interpolate(A, B, 1.0), B, atol=1e-12)
    M = geo.se3_interpolate(A, B, 0.5)
    # Half-way twice is the whole way.
    np.testing.assert_allclose(M @ geo.se3_inverse(A) @ M, B, atol=1e-12)


@pytest.mark.parametrize(
    "shape_a, shape_b",
    [
        ((3, 3), (7, 3, 3)),
        ((5, 2, 3, 3), (5, 1, 3, 2)),
        ((7, 1, 6), (6, 4)),
        ((4, 1, 0), (4, 0, 1)),
    ],
)
def test_small_matmul_and_its_gradients_match_matmul(shape_a, shape_b):
    """Broadcast batch axes (summed back in the gradients) and an empty inner axis."""
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=shape_a), rng.normal(size=shape_b)
    np.testing.assert_allclose(geo.matmul(A, B), A @ B, atol=1e-14)

    def loss(product):
        return lambda A, B: jax.numpy.sum(jax.numpy.sin(product(A, B)))

    ours = jax.grad(loss(geo.matmul), (0, 1))(A, B)
    for got, want in zip(ours, jax.grad(loss(jax.numpy.matmul), (0, 1))(A, B), strict=True):
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_allclose(geo.dot(A[..., 0, :], A[..., 0, :]),
                               np.sum(A[..., 0, :] ** 2, axis=-1), atol=1e-14)  # fmt: skip
    np.testing.assert_allclose(geo.rotate(A, B[..., 0]), (A @ B[..., :1])[..., 0], atol=1e-14)
