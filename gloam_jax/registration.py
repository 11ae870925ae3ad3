"""Registration on the host: prepared clouds, the outer rounds, and the three-line API.

:func:`prepare` turns a raw cloud into a :class:`PreparedCloud` (voxel grid, k-d tree,
covariances, association features); :func:`align_prepared` runs GICP's outer rounds: each
queries the target's tree for the candidates of the moved source points and hands them to the
jitted round (:func:`gloam_jax.gicp.solve_round`). :func:`align` does both, as small_gicp's
``align(target, source)`` does, and returns its fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from gloam_jax import covariance as cov
from gloam_jax import geometry as geo
from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError
from gloam_jax.gicp import FRESH, Cloud, GICPConfig, retract_host, solve_round
from gloam_jax.learned import Learned, cloud_attributes
from gloam_jax.neighbors import KdTree
from gloam_jax.timing import StageTimer


@dataclass
class PreparedCloud:
    """A cloud ready for registration: downsampled points, k-d tree, regularised covariances."""

    points: np.ndarray  # (N, 3)
    covs: np.ndarray  # (N, 3, 3)
    tree: KdTree
    features: np.ndarray | None = None  # (N, F) for data association; None: none (F = 0)
    num_dropped: int = 0  # NaN / inf points removed
    # The k-NN neighbourhoods' normals (N, 3) and planarity (N,), for conditioning(); None:
    # taken from the covariances' smallest axes, every point counted as planar.
    normals: np.ndarray | None = None
    planarity: np.ndarray | None = None

    @cached_property
    def radius(self) -> float:
        """Distance of the farthest point from the cloud's origin (m)."""
        return float(np.sqrt(np.max(np.sum(self.points**2, axis=1))))

    # Each point's row in the padded device arrays (N,); None: its index. The local map lays
    # its keyframes out in fixed slots, so that a new keyframe rewrites only its own rows.
    rows: np.ndarray | None = None

    _padded: dict[tuple, Cloud] = field(default_factory=dict, repr=False)

    def padded(self, size: int | None = None) -> Cloud:
        """Device arrays padded to ``size`` rows (default: the bucket size), cached."""
        if size is None:
            end = len(self.points) if self.rows is None else int(self.rows.max()) + 1
            size = pc.bucket_size(end)
        key = (size, geo.real_dtype())
        if key not in self._padded:
            self._padded[key] = device_cloud(self.points, self.covs, self.features, size,
                                             self.rows)  # fmt: skip
        return self._padded[key]

    def place(self, size: int, device: Cloud) -> None:
        """Take ``device`` as the padded arrays at ``size`` rows (laid out by ``rows``)."""
        self._padded[(size, geo.real_dtype())] = device


def device_cloud(
    points: np.ndarray,
    covs: np.ndarray,
    features: np.ndarray | None,
    size: int,
    rows: np.ndarray | None = None,
) -> Cloud:
    """The device arrays of a cloud's columns (N, ...), padded to ``size`` rows (row i at
    ``rows[i]``, default i), in the device's precision."""
    # Padded in the device's precision on the host: half the bytes to copy in float32, and
    # no conversion compiled per shape on the device.
    real = geo.real_dtype()
    features = np.zeros((len(points), 0)) if features is None else features
    features = pc.pad(features, size, dtype=real, rows=rows)[0]
    points, mask = pc.pad(points, size, dtype=real, rows=rows)
    covs = pc.pad(covs, size, dtype=real, rows=rows)[0]
    covs[~mask] = np.eye(3)  # keeps padded rows finite
    return Cloud(*(jnp.asarray(x) for x in (points, covs, mask, features)))


class RegistrationResult(NamedTuple):
    """Outcome of :func:`align`; ``H``, ``b`` and ``error`` are the Gauss-Newton system over
    the increment of :func:`gloam_jax.gicp.retract` and the sum of squared whitened
    residuals at the final estimate.

    ``converged`` says the iterations settled; ``degenerate`` says the scene leaves the answer
    undetermined along ``weak_directions`` (6, m) (a tunnel's or a corridor's axis), in
    coordinates ``(rho, lever_arm * phi)``; ``condition`` is the weakest constraint over the
    strongest and ``support`` the points facing the weakest direction (see
    :func:`conditioning`)."""

    T_target_source: np.ndarray
    converged: bool
    iterations: int
    num_inliers: int
    H: np.ndarray
    b: np.ndarray
    error: float
    condition: float
    weak_directions: np.ndarray
    support: float
    queries: int = 0  # the target's k-d tree queried (rounds that refreshed candidates, rows)

    @property
    def degenerate(self) -> bool:
        return self.weak_directions.shape[1] > 0


def constraint_rows(
    target: PreparedCloud,
    source: PreparedCloud,
    T: np.ndarray,
    max_distance: float,
    nearest: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """How the scene's surfaces constrain ``T_target_source``: point-to-plane rows (N, 6) over
    the increment of :func:`gloam_jax.gicp.retract`, each source point paired with its nearest
    target point within ``max_distance`` (or ``nearest``: indices (N,) and found (N,) from a
    query near ``T``), and their weights (N,), that point's planarity.

    Unlike GICP's own H they carry none of the plane regulariser's in-plane weight, which
    gives a tunnel's axis as much information as a healthy drive's weakest direction, and the
    planarity weight leaves out the normals of line-like neighbourhoods (sparse scan rings),
    which move with the sensor and would pin it in place.
    """
    moved = source.points @ T[:3, :3].T + T[:3, 3]
    if nearest is None:
        index, found = target.tree.query(moved, 1, max_distance)
        nearest = index[:, 0], found[:, 0]
    index, found = nearest
    if target.normals is None:
        normals = np.linalg.eigh(target.covs[index])[1][..., 0]
        weight = found.astype(np.float64)
    else:
        normals = target.normals[index]
        weight = np.where(found, np.clip(target.planarity[index], 0.0, 1.0), 0.0)
    rows = np.concatenate([normals, np.cross(moved - T[:3, 3], normals)], axis=1)
    return rows, weight


def conditioning(
    rows: np.ndarray, weight: np.ndarray, lever_arm: float, threshold: float, support: float
) -> tuple[float, np.ndarray, float]:
    """Which directions the constraint ``rows`` (N, 6) with ``weight`` (N,) (see
    :func:`constraint_rows`) leave undetermined, in coordinates ``z = (rho, lever_arm * phi)``,
    both in metres. Returns the condition (the weakest eigenvalue of their system over the
    strongest), the weak directions (orthonormal columns (6, m)) and the weakest direction's
    support.

    A direction is weak when its eigenvalue is below ``threshold`` times the strongest and
    fewer than ``support`` (planarity-weighted) points face it: a row within 60 degrees of it.
    The eigenvalue alone has a floor from normal noise, each wall point of a tunnel tilting a
    little towards the axis, at the level of a healthy highway's weakest direction, which
    real structure (a car's back, a sign, a post) constrains (experiments/highway_degeneracy).
    """
    scaled = rows / np.array([1.0, 1.0, 1.0, lever_arm, lever_arm, lever_arm])
    values, vectors = np.linalg.eigh((scaled * weight[:, None]).T @ scaled)
    strongest = max(values[-1], 1e-300)
    norms = np.maximum(np.linalg.norm(scaled, axis=1, keepdims=True), 1e-300)
    facing = np.abs(scaled @ vectors) > 0.5 * norms  # (N, 6): cos > 0.5
    supports = weight @ facing
    weak = (values < threshold * strongest) & (supports < support)
    return float(max(values[0], 0.0) / strongest), vectors[:, weak], float(supports[0])


def prepare(
    points: np.ndarray,
    *,
    downsampling_resolution: float = 0.25,
    num_neighbors: int = 20,
    regularizer: str = "plane",
    name: str | None = None,
) -> PreparedCloud:
    """Drop invalid points, voxel-downsample, build the tree and the covariances: (N, 3+).
    ``name``: the cloud's name (a file) in error messages."""
    points, dropped = pc.drop_invalid(np.asarray(points), name)
    points = pc.voxel_downsample(points[:, :3].astype(np.float64), downsampling_resolution)
    cloud = build_cloud(points, num_neighbors, regularizer, name)
    cloud.num_dropped = dropped
    return cloud


def build_cloud(
    points: np.ndarray,
    num_neighbors: int,
    regularizer: str = "plane",
    source: str | None = None,
    size: int | None = None,
    pca_features: np.ndarray | None = None,
    learned: Learned | None = None,
    timer: StageTimer | None = None,
    neighbours: np.ndarray | None = None,
) -> PreparedCloud:
    """Tree, covariances and association features of clean, downsampled points (N, 3)
    float64; ``pca_features`` (N, 6) feed the ``learned`` parts (see cloud_attributes).
    ``size``: rows the jitted covariance code sees (default: the bucket size); ``timer``
    counts the stages ``neighbours`` and ``covariances``; ``neighbours``: each point's
    ``num_neighbors`` nearest (N, k) int32 where already found (:class:`VoxelCentres`),
    else queried here."""
    learned = Learned() if learned is None else learned
    timer = StageTimer() if timer is None else timer
    with timer("neighbours"):
        tree = KdTree(points, source)
        if neighbours is None:
            neighbours, _ = tree.query(points, num_neighbors)
        elif neighbours.shape != (len(points), num_neighbors):
            raise ValueError(f"neighbours {neighbours.shape} for {len(points)} points, "
                             f"k = {num_neighbors}")  # fmt: skip
    if pca_features is None:
        if learned.eigenvalue is not None or learned.conversion is not None:
            raise InputError(source, "learned covariances or association need point features")
        pca_features = np.zeros((len(points), 0))
    # Padded to a bucket size so that the jitted covariance code compiles once per bucket.
    size = pc.bucket_size(len(points)) if size is None else size
    with timer("covariances"):
        covs, features, normals, planarity = cloud_attributes(
            jnp.asarray(pc.pad(points, size)[0]),
            jnp.asarray(pc.pad(neighbours, size)[0]),
            jnp.asarray(pc.pad(np.asarray(pca_features), size)[0]),
            learned,
            regularizer,
        )
        n = len(points)
        covs = np.asarray(covs, dtype=np.float64)[:n]
        features = None if learned.conversion is None else np.asarray(features)[:n]
        normals, planarity = np.asarray(normals, np.float64)[:n], np.asarray(planarity)[:n]
    return PreparedCloud(points, covs, tree, features, normals=normals, planarity=planarity)


def align_prepared(
    target: PreparedCloud,
    source: PreparedCloud,
    init_T_target_source: np.ndarray | None = None,
    config: GICPConfig = GICPConfig(),
    sizes: tuple[int, int] | None = None,
    timer: StageTimer | None = None,
) -> RegistrationResult:
    """Register prepared clouds; see :func:`align`. ``sizes``: the rows (source, target) the
    solver sees (default: their bucket sizes); the odometry holds them fixed across frames,
    so the solver compiles once. ``timer`` counts the stages ``neighbours`` (the candidate
    queries) and ``solve`` (the rest)."""
    timer = StageTimer() if timer is None else timer
    T = np.eye(4) if init_T_target_source is None else np.asarray(init_T_target_source, float)
    with timer("solve"):  # the device arrays, made on first use
        if sizes is None:
            src, tgt = source.padded(), target.padded()
        else:
            src, tgt = source.padded(sizes[0]), target.padded(sizes[1])
    size = src.points.shape[0]
    max_d2 = jnp.asarray(config.max_correspondence_distance**2, dtype=geo.real_dtype())
    converged, iterations, queries = False, 0, 0
    # Where the candidates were found, and how far a source point may have moved since: a
    # round queries again from requery_shift on (always where it is 0).
    T_query, shift = T, np.inf
    for iterations in range(1, config.max_iterations + 1):  # noqa: B007
        with timer("neighbours"):
            if shift >= config.requery_shift:
                moved = source.points @ T[:3, :3].T + T[:3, 3]
                hits = target.tree.query(
                    moved, config.num_candidates, config.max_correspondence_distance
                )
                rows = hits[0] if target.rows is None else target.rows[hits[0]]
                cand, valid = (jnp.asarray(pc.pad(x, size)[0]) for x in (rows, hits[1]))
                T_query, queries = T, queries + 1
        with timer("solve"):  # dispatch, then the wait for the results np.asarray reads
            _, xi, system = solve_round(
                jnp.asarray(T, dtype=geo.real_dtype()),
                src,
                tgt,
                cand,
                valid,
                max_d2,
                config.inner_steps,
                config.adjoint,
            )
            # Compose in float64 on the host so that many rounds do not accumulate float32
            # error.
            T = retract_host(np.asarray(xi, np.float64), T)
            H, b, error, inliers = (np.asarray(x, np.float64) for x in system)
            # Converged when the next Gauss-Newton step would be below the thresholds
            # (small_gicp's criterion), provided the candidates are still fresh: no point moved
            # farther than a tenth of the correspondence distance since they were found.
            step = _gauss_newton_step(H, b)
            shift = _largest_shift(T_query, T, source.radius)
            fresh = shift < FRESH * config.max_correspondence_distance
            small = np.linalg.norm(step[3:]) < config.rotation_eps
        if inliers > 0 and fresh and small and np.linalg.norm(step[:3]) < config.translation_eps:
            converged = True
            break
    with timer("neighbours"):
        # The last candidates' nearest (the query sorts them) serve while they are kept.
        kept = shift < config.requery_shift
        nearest = (hits[0][:, 0], hits[1][:, 0]) if kept else None
        rows, weight = constraint_rows(
            target, source, T, config.max_correspondence_distance, nearest
        )
        queries += not kept
    with timer("solve"):
        condition, weak, support = conditioning(
            rows, weight, config.lever_arm, config.degeneracy_threshold, config.degeneracy_support
        )
    return RegistrationResult(
        T,
        converged,
        iterations,
        int(inliers),
        H,
        b,
        float(error),
        condition,
        weak,
        support,
        queries,
    )


def _largest_shift(T_from: np.ndarray, T_to: np.ndarray, radius: float) -> float:
    """Upper bound on how far any source point within ``radius`` of the source origin moves
    from ``T_from a`` to ``T_to a`` (m): the origin's shift plus the rotation's sweep."""
    D = T_to @ np.linalg.inv(T_from)
    angle = np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1.0, 1.0))
    return float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3]) + angle * radius)


def _gauss_newton_step(H: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``-H^-1 b`` (6,), zero along directions H does not constrain."""
    return -np.linalg.lstsq(H, b, rcond=1e-12)[0]


def align(
    target: np.ndarray,
    source: np.ndarray,
    init_T_target_source: np.ndarray | None = None,
    *,
    downsampling_resolution: float = 0.25,
    num_neighbors: int = 20,
    regularizer: str = "plane",
    config: GICPConfig = GICPConfig(),
) -> RegistrationResult:
    """Estimate ``T_target_source`` mapping ``source`` (N, 3+) points onto ``target`` (M, 3+).

    Both clouds are voxel-downsampled (``downsampling_resolution`` m), get k-NN covariances
    (``num_neighbors``) regularised by ``regularizer`` ("plane" or "raw_eps") and are
    registered by GICP from ``init_T_target_source`` (identity by default).
    """
    if regularizer not in cov.REGULARIZERS:
        raise InputError(
            None,
            f"unknown regularizer {regularizer!r}; choose one of {', '.join(cov.REGULARIZERS)}",
        )
    kw = dict(
        downsampling_resolution=downsampling_resolution,
        num_neighbors=num_neighbors,
        regularizer=regularizer,
    )
    tgt = prepare(target, name="target", **kw)
    src = prepare(source, name="source", **kw)
    return align_prepared(tgt, src, init_T_target_source, config)
