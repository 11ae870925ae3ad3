"""SO(3) and SE(3) on matrices, in JAX.

Conventions (owned here, used everywhere else):

* A rigid transform is a ``(..., 4, 4)`` homogeneous matrix. ``T_a_b`` maps points expressed
  in frame ``b`` into frame ``a``: ``p_a = T_a_b @ p_b``. Composition is matrix product,
  ``T_a_c = T_a_b @ T_b_c``.
* The se(3) tangent vector is ``xi = (rho, phi)``, shape ``(..., 6)``: translation part first,
  rotation part (axis * angle, radians) second, as in jaxlie. ``exp(xi)`` has rotation
  ``so3_exp(phi)`` and translation ``V(phi) @ rho``.
* Every function broadcasts over leading batch axes. Values and gradients are finite at
  angle 0 (Taylor branches) and at angle pi (the logarithm goes through a quaternion).

The exponentials, logarithms and quaternion maps are jitted: called on concrete arrays (the
simulator, set-up code) they compile one program per shape, not each of their primitives.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

# Below this squared angle the closed forms lose precision (float32 cancellation), so the
# Taylor series in theta^2 below are used instead; at 1e-2 their first omitted terms are below
# 1e-15.
_SMALL_ANGLE_SQ = 1e-2
_SIN_OVER_T = (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880)  # sin(t) / t
_ONE_MINUS_COS = (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800)  # (1 - cos t) / t^2
_T_MINUS_SIN = (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800)  # (t - sin t) / t^3
_V_INVERSE = (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160)  # (1 - (t/2)cot(t/2)) / t^2


def real_dtype():
    """float64 when JAX runs in x64 mode (gradient checks, tests), else float32 (fast path)."""
    return jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32


def _series(x: Array, coefficients: tuple[float, ...]) -> Array:
    """sum_k c_k x^k by Horner's rule."""
    out = jnp.full_like(x, coefficients[-1])
    for c in coefficients[-2::-1]:
        out = out * x + c
    return out


def matmul(A: ArrayLike, B: ArrayLike) -> Array:
    """``A @ B`` for small matrices, (..., n, k) @ (..., k, m), broadcasting: k multiply-adds
    of broadcast columns and rows, which XLA fuses with their neighbours into one elementwise
    loop. On the CPU, batched products of 3x3 blocks or 6-wide rows as ``dot`` ops are slow
    library calls that stream each operand from memory (the batch's hot path is made of them).
    Reverse mode only: its gradients are products of the same kind (the transposes of the
    multiply-adds would be reductions over 3-wide rows, slower still)."""
    return _matmul(jnp.asarray(A), jnp.asarray(B))


def _products(A: Array, B: Array) -> Array:
    out = jnp.zeros(jnp.broadcast_shapes(A.shape[:-1] + (1,), B.shape[:-2] + (1, B.shape[-1])),
                    jnp.result_type(A, B))  # fmt: skip
    for i in range(A.shape[-1]):
        out = out + A[..., :, i, None] * B[..., None, i, :]
    return out


def _unbroadcast(g: Array, shape: tuple[int, ...]) -> Array:
    """Sum a gradient (..., shape broadcast) back to ``shape``."""
    g = jnp.sum(g, axis=tuple(range(g.ndim - len(shape))))
    ones = tuple(i for i, (a, b) in enumerate(zip(g.shape, shape, strict=True)) if b == 1 < a)
    return jnp.sum(g, axis=ones, keepdims=True)


@jax.custom_vjp
def _matmul(A: Array, B: Array) -> Array:
    return _products(A, B)


def _matmul_fwd(A: Array, B: Array) -> tuple[Array, tuple[Array, Array]]:
    return _products(A, B), (A, B)


def _matmul_bwd(res: tuple[Array, Array], g: Array) -> tuple[Array, Array]:
    A, B = res
    dA = _unbroadcast(_products(g, jnp.swapaxes(B, -1, -2)), A.shape)
    dB = _unbroadcast(_products(jnp.swapaxes(A, -1, -2), g), B.shape)
    return dA.astype(A.dtype), dB.astype(B.dtype)


_matmul.defvjp(_matmul_fwd, _matmul_bwd)


def dot(a: ArrayLike, b: ArrayLike) -> Array:
    """Inner products over the last (short) axis, (..., k) . (..., k) -> (...), broadcasting
    (see matmul)."""
    return matmul(jnp.asarray(a)[..., None, :], jnp.asarray(b)[..., :, None])[..., 0, 0]


def rotate(R: ArrayLike, p: ArrayLike) -> Array:
    """``R p`` of vectors p (..., 3) by matrices R (..., 3, 3), broadcasting (see matmul)."""
    return matmul(R, jnp.asarray(p)[..., None])[..., 0]


def hat(phi: ArrayLike) -> Array:
    """Skew-symmetric matrix of ``phi``: (..., 3) -> (..., 3, 3), ``hat(a) @ b == cross(a, b)``."""
    phi = jnp.asarray(phi)
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def vee(K: ArrayLike) -> Array:
    """Inverse of :func:`hat`: (..., 3, 3) -> (..., 3)."""
    K = jnp.asarray(K)
    return jnp.stack([K[..., 2, 1], K[..., 0, 2], K[..., 1, 0]], axis=-1)


def _angle_coefficients(phi: Array) -> tuple[Array, Array, Array, Array]:
    """Return (theta^2, sin(t)/t, (1-cos t)/t^2, (t - sin t)/t^3), NaN-free at t = 0."""
    theta_sq = jnp.sum(phi * phi, axis=-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    # Double-where: the closed-form branch never sees a near-zero angle, so its gradient is finite.
    t2 = jnp.where(small, 1.0, theta_sq)
    t = jnp.sqrt(t2)
    half_sinc = jnp.sin(0.5 * t) / (0.5 * t)
    a = jnp.where(small, _series(theta_sq, _SIN_OVER_T), jnp.sin(t) / t)
    b = jnp.where(small, _series(theta_sq, _ONE_MINUS_COS), 0.5 * half_sinc * half_sinc)
    c = jnp.where(small, _series(theta_sq, _T_MINUS_SIN), (t - jnp.sin(t)) / (t2 * t))
    return theta_sq, a, b, c


@jax.jit
def so3_exp(phi: ArrayLike) -> Array:
    """Rotation matrix of the rotation vector ``phi``: (..., 3) -> (..., 3, 3)."""
    phi = jnp.asarray(phi)
    _, a, b, _ = _angle_coefficients(phi)
    K = hat(phi)
    eye = jnp.eye(3, dtype=K.dtype)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


@jax.jit
def quat_from_rotation(R: ArrayLike) -> Array:
    """Unit quaternion ``(qx, qy, qz, qw)`` with ``qw >= 0`` of a rotation matrix (Shepperd)."""
    R = jnp.asarray(R)
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = r00 + r11 + r22

    # Each candidate is well conditioned where it is chosen; the others are clamped so that
    # their (discarded) gradients stay finite.
    def root(x: Array) -> Array:
        return 0.5 * jnp.sqrt(jnp.maximum(x, 1e-12))

    def pair(i: int, j: int, sign: float) -> Array:
        return R[..., i, j] + sign * R[..., j, i]

    d21, d02, d10 = pair(2, 1, -1.0), pair(0, 2, -1.0), pair(1, 0, -1.0)
    s01, s02, s12 = pair(0, 1, 1.0), pair(0, 2, 1.0), pair(1, 2, 1.0)
    w0 = root(1.0 + trace)
    q0 = jnp.stack([d21 / (4 * w0), d02 / (4 * w0), d10 / (4 * w0), w0], axis=-1)
    x1 = root(1.0 + r00 - r11 - r22)
    q1 = jnp.stack([x1, s01 / (4 * x1), s02 / (4 * x1), d21 / (4 * x1)], axis=-1)
    y2 = root(1.0 - r00 + r11 - r22)
    q2 = jnp.stack([s01 / (4 * y2), y2, s12 / (4 * y2), d02 / (4 * y2)], axis=-1)
    z3 = root(1.0 - r00 - r11 + r22)
    q3 = jnp.stack([s02 / (4 * z3), s12 / (4 * z3), z3, d10 / (4 * z3)], axis=-1)
    diag_max = jnp.argmax(jnp.stack([r00, r11, r22], axis=-1), axis=-1)
    use0 = (trace > 0.0)[..., None]
    q = jnp.where(
        use0,
        q0,
        jnp.where((diag_max == 0)[..., None], q1, jnp.where((diag_max == 1)[..., None], q2, q3)),
    )
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., 3:4] < 0.0, -q, q)


@jax.jit
def rotation_from_quat(q: ArrayLike) -> Array:
    """Rotation matrix of a quaternion ``(qx, qy, qz, qw)`` (normalised first)."""
    q = jnp.asarray(q)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


@jax.jit
def so3_log(R: ArrayLike) -> Array:
    """Rotation vector of a rotation matrix, angle in [0, pi]: (..., 3, 3) -> (..., 3)."""
    q = quat_from_rotation(R)
    v, w = q[..., :3], q[..., 3]
    n_sq = jnp.sum(v * v, axis=-1)
    small = n_sq < 1e-8
    n = jnp.sqrt(jnp.where(small, 1.0, n_sq))
    # angle = 2 atan2(|v|, w); near |v| = 0 (so w ~ 1) use its series in |v|.
    scale = jnp.where(
        small,
        2.0 / w - 2.0 * n_sq / (3.0 * w**3),
        2.0 * jnp.arctan2(n, w) / n,
    )
    return v * scale[..., None]


def _v_matrix(phi: Array) -> Array:
    _, _, b, c = _angle_coefficients(phi)
    K = hat(phi)
    eye = jnp.eye(3, dtype=K.dtype)
    return eye + b[..., None, None] * K + c[..., None, None] * (K @ K)


def _v_inverse(phi: Array) -> Array:
    theta_sq = jnp.sum(phi * phi, axis=-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    t2 = jnp.where(small, 1.0, theta_sq)
    half = 0.5 * jnp.sqrt(t2)
    d = jnp.where(
        small,
        _series(theta_sq, _V_INVERSE),
        (1.0 - half * jnp.cos(half) / jnp.sin(half)) / t2,
    )
    K = hat(phi)
    eye = jnp.eye(3, dtype=K.dtype)
    return eye - 0.5 * K + d[..., None, None] * (K @ K)


def make_transform(R: ArrayLike, t: ArrayLike) -> Array:
    """Homogeneous matrix from rotation (..., 3, 3) and translation (..., 3)."""
    R, t = jnp.asarray(R), jnp.asarray(t)
    batch = jnp.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    dtype = jnp.result_type(R, t)
    T = jnp.zeros((*batch, 4, 4), dtype=dtype)
    T = T.at[..., :3, :3].set(jnp.broadcast_to(R, (*batch, 3, 3)))
    T = T.at[..., :3, 3].set(jnp.broadcast_to(t, (*batch, 3)))
    return T.at[..., 3, 3].set(1.0)


@jax.jit
def se3_exp(xi: ArrayLike) -> Array:
    """Transform of the tangent vector ``xi = (rho, phi)``: (..., 6) -> (..., 4, 4)."""
    xi = jnp.asarray(xi)
    rho, phi = xi[..., :3], xi[..., 3:]
    R = so3_exp(phi)
    t = (_v_matrix(phi) @ rho[..., None])[..., 0]
    return make_transform(R, t)


@jax.jit
def se3_log(T: ArrayLike) -> Array:
    """Tangent vector ``(rho, phi)`` of a transform: (..., 4, 4) -> (..., 6)."""
    T = jnp.asarray(T)
    phi = so3_log(T[..., :3, :3])
    rho = (_v_inverse(phi) @ T[..., :3, 3:4])[..., 0]
    return jnp.concatenate([rho, phi], axis=-1)


def se3_inverse(T: ArrayLike) -> Array:
    """Inverse transform, using the rotation's transpose: (..., 4, 4) -> (..., 4, 4)."""
    T = jnp.asarray(T)
    Rt = jnp.swapaxes(T[..., :3, :3], -1, -2)
    return make_transform(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def se3_compose(T_a_b: ArrayLike, T_b_c: ArrayLike) -> Array:
    """``T_a_c = T_a_b @ T_b_c`` with broadcasting."""
    return jnp.asarray(T_a_b) @ jnp.asarray(T_b_c)


def se3_apply(T_a_b: ArrayLike, p_b: ArrayLike) -> Array:
    """Map points (..., N, 3) from frame b to frame a; T broadcasts as (..., 4, 4)."""
    T_a_b, p_b = jnp.asarray(T_a_b), jnp.asarray(p_b)
    R = T_a_b[..., None, :3, :3]
    return (R @ p_b[..., None])[..., 0] + T_a_b[..., None, :3, 3]


@jax.jit
def se3_interpolate(T_w_a: ArrayLike, T_w_b: ArrayLike, alpha: ArrayLike) -> Array:
    """Geodesic ``T_w_a @ exp(alpha * log(T_a_b))``; alpha = 0 gives a, 1 gives b (extrapolates)."""
    alpha = jnp.asarray(alpha)
    xi = se3_log(se3_compose(se3_inverse(T_w_a), T_w_b))
    return se3_compose(T_w_a, se3_exp(alpha[..., None] * xi))


@jax.jit
def rotation_angle(R: ArrayLike) -> Array:
    """Rotation angle in radians, in [0, pi], NaN-free: (..., 3, 3) -> (...)."""
    phi = so3_log(R)
    sq = jnp.sum(phi * phi, axis=-1)
    positive = sq > 0.0
    # |phi| has no derivative at 0; the where keeps its gradient finite (zero) there.
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


# Host-side loops (registration rounds, odometry bookkeeping) handle a few 4x4 matrices at a
# time; eager JAX would dispatch dozens of tiny ops for each, so they call these compiled ones.
se3_exp_jit = jax.jit(se3_exp)
se3_log_jit = jax.jit(se3_log)
