"""Jitted ray casting of one LiDAR sweep against a :class:`~gloam_jax.simulate.world.Scene`.

Rays are grouped in azimuth sectors; each sector is tested only against the primitives that
can lie in it. The host lists those (sector, primitive) pairs, padded to a power-of-two count
so shapes, and compiled code, repeat from frame to frame; the work is then proportional to the
pairs, not to the busiest sector times the number of sectors. Coordinates are relative to the
frame's sensor position (float32 stays precise far from the world origin).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax.simulate.world import (
    GRID_RES,
    PATTERN_SLATS,
    PATTERN_WINDOWS,
    Primitives,
    Scene,
)

MARCH_STEPS = 32  # ground samples per ray, geometrically spaced
BISECT_STEPS = 10
_FAR = 1e9


class Prims(NamedTuple):
    """Device-side primitive arrays, one entry per (sector, primitive) pair: leading axes (Q,)."""

    center: jax.Array
    size: jax.Array
    yaw: jax.Array
    velocity: jax.Array
    t_start: jax.Array
    t_end: jax.Array
    label: jax.Array
    reflectivity: jax.Array
    porosity: jax.Array
    pattern: jax.Array
    uid: jax.Array
    valid: jax.Array
    sector: jax.Array  # int32 sector whose rays meet this primitive; pairs sorted by it


class GroundGrid(NamedTuple):
    origin: jax.Array  # (2,)
    cells: jax.Array  # (NX - 1, NY - 1, 8): per cell, (base height, path distance) at its
    # corners (i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1): one gather per lookup, not four
    params: jax.Array  # (3,) road half width, sidewalk width, curb height
    labels: jax.Array  # (3,) int32 class of the road, the band beside it, the ground beyond
    z_range: jax.Array  # (2,) lowest and highest ground in the crop


class Hits(NamedTuple):
    """Per-ray results: range (inf where nothing), class id, reflectivity, |cos incidence|."""

    t: jax.Array
    label: jax.Array
    reflectivity: jax.Array
    cos_incidence: jax.Array


def _hash_uniforms(a: jax.Array, b: jax.Array, salt: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Two deterministic uniforms in [0, 1) (12 bits each) from two uint32 ids: an integer hash."""
    x = a * jnp.uint32(0x9E3779B1) ^ (b * jnp.uint32(0x85EBCA77)) ^ salt
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x2C1B3C6D)
    x = x ^ (x >> 12)
    x = x * jnp.uint32(0x297A2D39)
    x = x ^ (x >> 15)
    scale = 1.0 / 4096.0
    return (x >> 20).astype(jnp.float32) * scale, ((x >> 4) & 0xFFF).astype(jnp.float32) * scale


def _dot3(a, b):
    """Dot product over the last axis of 3, written out: (..., 3) -> (...). A reduction over
    that axis is a scalar loop on XLA's CPU backend (3x slower in the ray tests)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _to_local(o, d, tr, p: Prims):
    """Ray origin/direction in each primitive's frame: (R, 3) x (P,) -> (R, P, 3) twice."""
    centre = p.center + p.velocity * tr[:, None, None]
    dx = o[:, None, :] - centre
    c, s = jnp.cos(p.yaw), jnp.sin(p.yaw)

    def rot(v):
        return jnp.stack(
            [c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], -1
        )

    return rot(dx), rot(jnp.broadcast_to(d[:, None, :], dx.shape))


def _world_normal(n_local, p: Prims):
    c, s = jnp.cos(p.yaw), jnp.sin(p.yaw)
    return jnp.stack(
        [
            c * n_local[..., 0] - s * n_local[..., 1],
            s * n_local[..., 0] + c * n_local[..., 1],
            n_local[..., 2],
        ],
        -1,
    )


def _active(tr, p: Prims):
    return p.valid & (tr[:, None] >= p.t_start) & (tr[:, None] <= p.t_end)


def _porous(t_in, t_out, ray_id, p: Prims, salt, depth):
    """Foliage: a ray passes with the primitive's porosity, else returns inside the volume."""
    u1, u2 = _hash_uniforms(ray_id[:, None], p.uid, salt)
    passes = u1 < p.porosity
    t = jnp.where(p.porosity > 0, t_in + depth * (t_out - t_in) * u2 * u2, t_in)
    return t, passes


def box_hits(o, d, tr, ray_id, salt, p: Prims):
    """Entry distance (inf if missed) and world normal: (R, P) and (R, P, 3)."""
    lo, ld = _to_local(o, d, tr, p)
    safe = jnp.where(jnp.abs(ld) < 1e-12, 1e-12, ld)
    ta, tb = (-p.size - lo) / safe, (p.size - lo) / safe
    near, far = jnp.minimum(ta, tb), jnp.maximum(ta, tb)
    # Per component, not max/argmax over the last axis: XLA's CPU reductions over a minor
    # axis of 3 are scalar loops, and this is the simulator's innermost test.
    n0, n1, n2 = near[..., 0], near[..., 1], near[..., 2]
    t_in = jnp.maximum(jnp.maximum(n0, n1), n2)
    t_out = jnp.minimum(jnp.minimum(far[..., 0], far[..., 1]), far[..., 2])
    on_x = (n0 >= n1) & (n0 >= n2)  # the face entered; ties go to the first axis, as argmax
    on_y = ~on_x & (n1 >= n2)
    on_z = ~on_x & ~on_y
    hit = _active(tr, p) & (t_out >= t_in) & (t_in > 1e-3)
    local = lo + t_in[..., None] * ld
    u = jnp.where(on_x, local[..., 1], local[..., 0])  # along the face that was hit
    z_up = local[..., 2] + p.size[..., 2]  # height above the primitive's base
    kind, period_u, period_z, depth = (p.pattern[..., k] for k in range(4))
    side_face = ~on_z
    fu = jnp.mod(u / jnp.maximum(period_u, 1e-3), 1.0)
    fz = jnp.mod(z_up / jnp.maximum(period_z, 1e-3), 1.0)
    window = (
        (kind == PATTERN_WINDOWS) & side_face & (fu > 0.2) & (fu < 0.8) & (fz > 0.3) & (fz < 0.85)
    )
    window = window & (z_up > 1.0) & (z_up < 2 * p.size[..., 2] - 0.8)
    ld_face = jnp.where(on_x, ld[..., 0], jnp.where(on_y, ld[..., 1], ld[..., 2]))
    t_hit = jnp.where(window, t_in + depth / jnp.maximum(jnp.abs(ld_face), 0.05), t_in)
    slat_gap = (kind == PATTERN_SLATS) & side_face & (fu > period_z)  # period_z holds the fill
    t_hit, passes = _porous(t_hit, jnp.minimum(t_out, t_in + 0.6), ray_id, p, salt, 1.0)
    hit = hit & ~slat_gap & ~passes
    sign = -jnp.sign(ld_face)
    n_local = jnp.stack([on_x * sign, on_y * sign, on_z * sign], -1).astype(ld.dtype)
    return jnp.where(hit, t_hit, jnp.inf), _world_normal(n_local, p)


def cylinder_hits(o, d, tr, ray_id, salt, p: Prims):
    """Vertical cylinders (side surface only)."""
    lo, ld = _to_local(o, d, tr, p)
    r = p.size[..., 0]
    a = ld[..., 0] ** 2 + ld[..., 1] ** 2
    b = 2 * (lo[..., 0] * ld[..., 0] + lo[..., 1] * ld[..., 1])
    c = lo[..., 0] ** 2 + lo[..., 1] ** 2 - r * r
    disc = b * b - 4 * a * c
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.maximum(2 * a, 1e-12)
    z = lo[..., 2] + t * ld[..., 2]
    hit = _active(tr, p) & (disc > 0) & (t > 1e-3) & (jnp.abs(z) <= p.size[..., 2])
    local = lo + t[..., None] * ld
    n_local = local * jnp.array([1.0, 1.0, 0.0]) / jnp.maximum(r, 1e-6)[..., None]
    return jnp.where(hit, t, jnp.inf), _world_normal(n_local, p)


def ellipsoid_hits(o, d, tr, ray_id, salt, p: Prims):
    lo, ld = _to_local(o, d, tr, p)
    q, e = lo / p.size, ld / p.size
    a = _dot3(e, e)
    b = 2 * _dot3(q, e)
    c = _dot3(q, q) - 1.0
    disc = b * b - 4 * a * c
    root = jnp.sqrt(jnp.maximum(disc, 0.0))
    t_in = (-b - root) / jnp.maximum(2 * a, 1e-12)
    t_out = (-b + root) / jnp.maximum(2 * a, 1e-12)
    t, passes = _porous(t_in, t_out, ray_id, p, salt, 0.7)
    hit = _active(tr, p) & (disc > 0) & (t_in > 1e-3) & ~passes
    local = lo + t_in[..., None] * ld
    n_local = local / (p.size * p.size)
    n_local = n_local / jnp.maximum(jnp.sqrt(_dot3(n_local, n_local)), 1e-9)[..., None]
    return jnp.where(hit, t, jnp.inf), _world_normal(n_local, p)


def _ground_fields(xy, g: GroundGrid):
    """Bilinear (base height, path distance) at xy: (..., 2) -> (..., 2)."""
    f = (xy - g.origin) / GRID_RES
    # float32(NX) - 1.001, as with the grid of points: the same clamp at the crop's edge.
    f = jnp.clip(f, 0.0, (jnp.array(g.cells.shape[:2], f.dtype) + 1) - 1.001)
    i0 = jnp.floor(f).astype(jnp.int32)
    w = (f - i0)[..., None, :]
    c = g.cells[i0[..., 0], i0[..., 1]]
    a00, a01, a10, a11 = c[..., 0:2], c[..., 2:4], c[..., 4:6], c[..., 6:8]
    return (1 - w[..., 0]) * ((1 - w[..., 1]) * a00 + w[..., 1] * a01) + w[..., 0] * (
        (1 - w[..., 1]) * a10 + w[..., 1] * a11
    )


def ground_height(xy, g: GroundGrid):
    fields = _ground_fields(xy, g)
    road_half, curb = g.params[0], g.params[2]
    x = jnp.clip((fields[..., 1] - road_half) / 0.08, 0.0, 1.0)
    return fields[..., 0] + curb * x * x * (3 - 2 * x)


def ground_hits(o, d, g: GroundGrid, t_max: float):
    """March along each ray to the first point below the ground, then bisect: (R,) distances.

    Each ray is marched only over the stretch where its height lies within the ground's
    height range, so the samples are dense where a hit is possible. The march is a loop that
    keeps each ray's bracket, not all its samples at once: a few (R,) arrays stay in cache,
    where (MARCH_STEPS, R) samples made it 3x slower.
    """
    oz, dz = o[:, 2], d[:, 2]
    safe = jnp.where(jnp.abs(dz) < 1e-6, -1e-6, dz)
    z_lo, z_hi = g.z_range[0], g.z_range[1]
    t_lo = jnp.where(dz < -1e-6, (z_hi - oz) / safe, 0.0)
    t_hi = jnp.where(
        dz < -1e-6, (z_lo - oz) / safe, jnp.where(dz > 1e-6, (z_hi - oz) / safe, t_max)
    )
    t_lo = jnp.maximum(t_lo, 0.3)
    t_hi = jnp.clip(t_hi, t_lo * 1.001, t_max)
    # Quadratic spacing: dense near the start, where steep rays meet the ground.
    frac = jnp.linspace(0.0, 1.0, MARCH_STEPS, dtype=o.dtype) ** 2

    def below(t):
        p = o + t[..., None] * d
        return p[..., 2] < ground_height(p[..., :2], g)

    def march(k, state):
        lo, hi, found, starts_below = state
        t = t_lo + (t_hi - t_lo) * frac[k]
        crossed = below(t) & ~found
        starts_below = starts_below | (crossed & (k == 0))
        return (
            jnp.where(found | crossed, lo, t),
            jnp.where(crossed, t, hi),
            found | crossed,
            starts_below,
        )

    no = jnp.zeros(o.shape[0], bool)
    lo, hi, found, starts_below = jax.lax.fori_loop(0, MARCH_STEPS, march, (t_lo, t_hi, no, no))
    found = found & ~starts_below  # a ray that starts under the ground sees none of it

    def bisect(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        b = below(mid)
        return jnp.where(b, lo, mid), jnp.where(b, mid, hi)

    lo, hi = jax.lax.fori_loop(0, BISECT_STEPS, bisect, (lo, hi))
    return jnp.where(found, 0.5 * (lo + hi), jnp.inf)


def _ground_normal_and_label(p, g: GroundGrid):
    e = 0.2
    dx = ground_height(p[..., :2] + jnp.array([e, 0.0]), g) - ground_height(
        p[..., :2] - jnp.array([e, 0.0]), g
    )
    dy = ground_height(p[..., :2] + jnp.array([0.0, e]), g) - ground_height(
        p[..., :2] - jnp.array([0.0, e]), g
    )
    n = jnp.stack([-dx / (2 * e), -dy / (2 * e), jnp.ones_like(dx)], -1)
    n = n / jnp.sqrt(_dot3(n, n))[..., None]
    dist = _ground_fields(p[..., :2], g)[..., 1]
    road_half, sidewalk = g.params[0], g.params[1]
    label = jnp.where(
        dist < road_half,
        g.labels[0],
        jnp.where(dist < road_half + sidewalk, g.labels[1], g.labels[2]),
    )
    return n, label


_HIT_FNS = (box_hits, cylinder_hits, ellipsoid_hits)


def _nearest(t, sector, num_sectors: int):
    """Per sector and ray, the nearest pair and its distance: (Q, Rs) -> (S, Rs) twice.

    Ties go to the lowest pair, as argmin over a sector's primitives in index order would.
    """
    t_min = jax.ops.segment_min(t, sector, num_segments=num_sectors, indices_are_sorted=True)
    pair = jnp.arange(t.shape[0], dtype=jnp.int32)[:, None]
    cand = jnp.where(t == t_min[sector], pair, t.shape[0] - 1)
    k = jax.ops.segment_min(cand, sector, num_segments=num_sectors, indices_are_sorted=True)
    return t_min, jnp.minimum(k, t.shape[0] - 1)  # a sector without pairs: any index, t is inf


def _cast_pairs(o, d, tr, ray_id, salt, prims: tuple[Prims, Prims, Prims]):
    """Nearest primitive hit per ray, (S, Rs, ...) rays: (t, label, reflectivity, normal)."""
    S = o.shape[0]
    best = (
        jnp.full(o.shape[:2], jnp.inf, o.dtype),
        jnp.zeros(o.shape[:2], jnp.int32),
        jnp.zeros(o.shape[:2], o.dtype),
        jnp.zeros_like(o),
    )
    for fn, p in zip(_HIT_FNS, prims, strict=True):

        def pair_t(s, p_q, fn=fn):
            one = jax.tree.map(lambda a: a[None], p_q)
            return fn(o[s], d[s], tr[s], ray_id[s], salt, one)[0][:, 0]

        t_k, k = _nearest(jax.vmap(pair_t)(p.sector, p), p.sector, S)
        # Normal of the winner only: re-run the test against that one primitive.
        winner = jax.tree.map(lambda a, k=k: a[k][:, :, None], p)
        n = jax.vmap(lambda *a, fn=fn: fn(*a[:4], salt, a[4])[1])(o, d, tr, ray_id, winner)
        closer = t_k < best[0]
        best = (
            jnp.where(closer, t_k, best[0]),
            jnp.where(closer, p.label[k], best[1]),
            jnp.where(closer, p.reflectivity[k], best[2]),
            jnp.where(closer[..., None], n[:, :, 0], best[3]),
        )
    return best


@partial(jax.jit, static_argnames=("t_max",))
def cast_sweep(
    origins, dirs, times, ray_ids, salt, prims, ground: GroundGrid, reflectivity_lut, t_max: float
):
    """Cast a sweep grouped in S sectors of Rs rays each.

    origins, dirs: (S, Rs, 3); times: (S, Rs) s from mid-sweep; ray_ids: (S, Rs) uint32;
    prims: three :class:`Prims` (boxes, cylinders, ellipsoids), (sector, primitive) pairs
    with leading axis (Q_kind,). Returns :class:`Hits` with (S, Rs) fields.
    """
    t, label, refl, normal = _cast_pairs(origins, dirs, times, ray_ids, salt, prims)
    flat = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    t_g = ground_hits(*flat, ground, t_max).reshape(t.shape)
    p_g = origins + t_g[..., None] * dirs
    n_g, label_g = _ground_normal_and_label(p_g, ground)
    use_ground = t_g < t
    t = jnp.where(use_ground, t_g, t)
    label = jnp.where(use_ground, label_g, label)
    refl = jnp.where(use_ground, reflectivity_lut[label_g], refl)
    normal = jnp.where(use_ground[..., None], n_g, normal)
    cos_inc = jnp.abs(_dot3(normal, dirs))
    return Hits(t, label, refl, cos_inc)


def _pad_count(n: int) -> int:
    """n rounded up to a quarter of its power of two: few sizes (compilations), little waste."""
    step = max(2, (1 << (max(n, 1).bit_length() - 1)) >> 2)
    return max(8, -(-n // step) * step)


def sector_primitives(
    prims: Primitives,
    origin: np.ndarray,
    t_frame: float,
    sector_origins: np.ndarray,
    sector_azimuths: np.ndarray,
    max_range: float,
    min_pad: int = 8,
) -> Prims:
    """The (sector, primitive) pairs where a primitive may be seen in an azimuth sector,
    sorted by sector, then primitive; padded with invalid pairs: leading axis (Q,).

    origin: (3,) sensor position at mid-sweep, time t_frame: coordinates and times become
    relative to these. sector_origins: (S, 2) world xy of the sensor during each sector;
    sector_azimuths: (S, 2) world azimuths (radians) of each sector's first and last ray.
    min_pad: pad to at least this many pairs (keep it sticky to avoid recompiling).
    """
    S = len(sector_origins)
    centre_now = prims.center + prims.velocity * t_frame
    # Moving objects: allow for their motion during the sweep.
    radius = prims.bounding_radius() + 0.1 * np.linalg.norm(prims.velocity, axis=1) + 0.05
    alive = (prims.t_end >= t_frame - 0.1) & (prims.t_start <= t_frame + 0.1)
    dist0 = np.linalg.norm(centre_now[:, :2] - origin[:2], axis=1)
    near_idx = np.flatnonzero((dist0 - radius < max_range + 2.0) & alive)
    rel = centre_now[None, near_idx, :2] - sector_origins[:, None, :]  # (S, P_near, 2)
    dist = np.linalg.norm(rel, axis=-1)
    az = np.arctan2(rel[..., 1], rel[..., 0])
    r = radius[near_idx][None, :]
    half = np.where(dist <= r, np.pi, np.arcsin(np.clip(r / np.maximum(dist, 1e-6), 0, 1)) + 1e-3)
    a0, a1 = sector_azimuths[:, :1], sector_azimuths[:, 1:]
    span = np.abs((a1 - a0 + np.pi) % (2 * np.pi) - np.pi)
    centre = a0 + 0.5 * ((a1 - a0 + np.pi) % (2 * np.pi) - np.pi)
    diff = np.abs((az - centre + np.pi) % (2 * np.pi) - np.pi)
    sector, member = np.nonzero(diff <= 0.5 * span + half)  # row-major: sorted by sector
    Q = max(min_pad, _pad_count(len(sector)))
    if len(prims) == 0:
        return _empty_prims(S, Q)
    idx = np.zeros(Q, dtype=np.int64)
    idx[: len(sector)] = near_idx[member]
    valid = np.arange(Q) < len(sector)
    sub = prims.take(idx)
    return Prims(
        center=(sub.center + sub.velocity * t_frame - origin).astype(np.float32),
        size=np.maximum(sub.size, 1e-3).astype(np.float32),
        yaw=sub.yaw.astype(np.float32),
        velocity=sub.velocity.astype(np.float32),
        t_start=np.clip(sub.t_start - t_frame, -1e6, 1e6).astype(np.float32),
        t_end=np.clip(sub.t_end - t_frame, -1e6, 1e6).astype(np.float32),
        label=sub.label.astype(np.int32),
        reflectivity=sub.reflectivity.astype(np.float32),
        porosity=sub.porosity.astype(np.float32),
        pattern=sub.pattern.astype(np.float32),
        uid=sub.uid.astype(np.uint32),
        valid=valid,
        # Padding joins the last sector, keeping the pairs sorted; being invalid, it never hits.
        sector=np.concatenate([sector, np.full(Q - len(sector), S - 1)]).astype(np.int32),
    )


def _empty_prims(S: int, Q: int) -> Prims:
    f = np.zeros(Q, np.float32)
    f3 = np.zeros((Q, 3), np.float32)
    return Prims(
        f3,
        f3 + 1e-3,
        f,
        f3,
        f,
        f,
        f.astype(np.int32),
        f,
        f,
        np.zeros((Q, 4), np.float32),
        f.astype(np.uint32),
        np.zeros(Q, bool),
        np.full(Q, S - 1, np.int32),
    )


def ground_window(scene: Scene, origin: np.ndarray, half_extent: float) -> GroundGrid:
    """A fixed-size crop of the ground grid around ``origin``, in coordinates relative to it."""
    g = scene.ground
    n = int(np.ceil(2 * half_extent / GRID_RES)) + 2
    start = np.floor((origin[:2] - half_extent - g.origin) / GRID_RES).astype(int)
    start = np.clip(start, 0, np.maximum(np.array(g.base_height.shape) - n, 0))
    sl = (slice(start[0], start[0] + n), slice(start[1], start[1] + n))
    base = np.full((n, n), -1e3, np.float32)
    dist = np.full((n, n), 1e3, np.float32)
    crop_b, crop_d = g.base_height[sl], g.path_distance[sl]
    z_range = [crop_b.min() - origin[2] - 0.05, crop_b.max() - origin[2] + g.curb_height + 0.05]
    base[: crop_b.shape[0], : crop_b.shape[1]] = crop_b - origin[2]
    dist[: crop_d.shape[0], : crop_d.shape[1]] = crop_d
    fields = np.stack([base, dist], axis=-1)
    return GroundGrid(
        origin=(g.origin + start * GRID_RES - origin[:2]).astype(np.float32),
        cells=np.concatenate(
            [fields[:-1, :-1], fields[:-1, 1:], fields[1:, :-1], fields[1:, 1:]], axis=-1
        ),
        params=np.array([g.road_half_width, g.sidewalk_width, g.curb_height], np.float32),
        z_range=np.array(z_range, np.float32),
        labels=np.array(g.labels, np.int32),
    )
