"""Many registrations at once: ``jit`` + ``vmap`` over padded scan pairs.

Training and batch evaluation register every scan of a window to its predecessor (or to a
local map of earlier scans), as the paper trains. :mod:`gloam_jax.training.data` prepares the
scans and each pair's fixed candidate sets on the host; all that follows here is one traced
function of the learned parts: covariances (the regulariser or Algorithm 1), association
features, a fixed number of GICP rounds (:func:`gloam_jax.gicp.gicp_round`, the partners
re-chosen among the candidates in JAX each round), the chained trajectory and its relative
error. It differentiates through the LM solves with either optimistix adjoint.

Pair ``b`` registers source scan ``i + 1`` to target scan ``i``: its estimate is
``T_prev_curr`` in the LiDAR frame, and :func:`trajectories` chains them per window.

The pairs are independent, so they shard over a device mesh (:func:`pair_mesh`, by default
every local device): each device registers its slice of the pairs against a copy of the
scans, the pair count padded to a multiple of the device count with copies of
the last pair, whose estimates no window reads. See docs/scaling.md, "Sharding".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jax.typing import ArrayLike

from gloam_jax import geometry as geo
from gloam_jax.errors import InputError
from gloam_jax.gicp import Cloud, GICPConfig, gicp_round
from gloam_jax.io import cam_to_lidar_poses, frame_motions, lidar_to_cam_poses
from gloam_jax.learned import Learned, attributes
from gloam_jax.training.head import HeadData, head_features
from gloam_jax.training.losses import (
    TRAINING_FRACTIONS,
    SegmentPlan,
    chain,
    safe_norm,
    segment_errors,
)
from gloam_jax.training.objective import objective


def _batch_gicp() -> GICPConfig:
    return GICPConfig(num_candidates=5)


@dataclass(frozen=True)
class BatchConfig:
    """Batch registration settings: fixed candidate sets, a fixed number of rounds.

    ``gicp`` holds each round's settings (``num_candidates``: K found once per pair within
    ``candidate_radius``; ``max_iterations`` and the convergence thresholds are the
    odometry's, since the batch runs ``rounds`` rounds)."""

    rounds: int = 4  # GICP rounds, partners re-chosen among the candidates each round
    candidate_radius: float = 2.0  # m around the initial guess
    max_source_points: int = 2048  # source points per pair (a fixed random subset)
    association: Literal["hard", "soft"] = "hard"  # soft: softmax weights (training DA)
    temperature: float = 0.05  # soft association's, in the cost's units (m^2)
    segment_fractions: tuple[float, ...] = TRAINING_FRACTIONS  # of each window's path
    segment_step: int = 10  # frames between segment starts (the devkit's)
    seed: int = 0  # source subsets
    # The target of pair k: scan k alone (map_scans 1, frame-to-frame, as the paper trains),
    # or a local map of scans k, k - map_stride, ... (map_scans of them) merged with the
    # ground-truth poses, as the odometry registers to its last keyframes.
    map_scans: int = 1
    map_stride: int = 2
    # With N > 0 each window's t_err also counts the drift its pairs' mean rotation error about
    # the LiDAR's y and z axes (pitch, yaw) would add over a path of N frames (window_errors):
    # long segments see a per-pair bias that short windows hardly do. 0: the segments alone.
    drift_frames: int = 0
    # True: each window's mean per-pair rotation error is taken out of its estimates before
    # they are scored, so the loss gives no credit for moving it, only for cutting the
    # spread around it (a bias the training windows share need not be the drives':
    # experiments/hdl32_map20). Excludes drift_frames, which scores that mean.
    unbias_rotation: bool = False
    gicp: GICPConfig = field(default_factory=_batch_gicp)

    MOVED: ClassVar[dict[str, str]] = {
        k: f"gicp.{k}"
        for k in ("inner_steps", "num_candidates", "max_correspondence_distance", "adjoint")
    }

    def __post_init__(self) -> None:
        if min(self.rounds, self.gicp.num_candidates, self.max_source_points, self.map_scans,
               self.map_stride) < 1:  # fmt: skip
            raise InputError(
                None,
                "rounds, gicp.num_candidates, max_source_points, map_scans and map_stride "
                "must be >= 1",
            )
        if self.drift_frames < 0:
            raise InputError(None, f"drift_frames must be >= 0, got {self.drift_frames}")
        if self.drift_frames and self.unbias_rotation:
            raise InputError(None, "drift_frames scores the mean rotation error that "
                             "unbias_rotation takes out: set one of them")  # fmt: skip
        object.__setattr__(self, "segment_fractions", tuple(self.segment_fractions))


class ScanSet(NamedTuple):
    """Prepared scans padded to Q rows: points (S, Q, 3), ascending eigenvalues (S, Q, 3)
    and eigenvectors (S, Q, 3, 3) of the k-NN covariances, PCA features (S, Q, 6) (width 0
    without a model), mask (S, Q)."""

    points: Array
    values: Array
    vectors: Array
    pca: Array
    mask: Array


class PairBatch(NamedTuple):
    """B registrations: scan indices ``target``, ``source`` (B,); source rows (B, P) with
    ``row_mask``; candidates (B, P, K) with ``valid``, as rows of the flattened scans (S * Q)
    and the slot of the local map each comes from; the map's poses in the target's frame
    ``T_target_map`` (B, M, 4, 4) (M = 1, the identity, frame-to-frame); ``T_init`` (B, 4, 4)."""

    target: Array
    source: Array
    rows: Array
    row_mask: Array
    candidates: Array
    slots: Array
    valid: Array
    T_target_map: Array
    T_init: Array


def with_head(learned: Learned, scans: ScanSet, data: HeadData | None) -> ScanSet:
    """``scans`` with their PCA features recomputed from ``learned.head`` when it is set."""
    if learned.head is None:
        return scans
    if data is None:
        raise InputError(None, "fine-tuning the backbone's last layer needs its HeadData")
    features = head_features(learned.head, data, scans.mask.shape)
    return scans._replace(pca=features.astype(scans.pca.dtype))


def select_rows(pairs: PairBatch, index: Array) -> PairBatch:
    """The same source-row slots (R,) of every pair: a PairBatch with P = R."""
    fields = ("rows", "row_mask", "candidates", "slots", "valid")  # those with a row axis
    return pairs._replace(**{k: getattr(pairs, k)[:, index] for k in fields})


@dataclass(frozen=True)
class Window:
    """One window's bookkeeping: its pairs are ``pairs[start:stop]``; ground truth in the
    camera-0 convention (n, 4, 4) with ``Tr_cam_velo`` (4, 4); the segment plan of its loss."""

    name: str
    start: int
    stop: int
    gt_cam: np.ndarray
    Tr_cam_velo: np.ndarray
    plan: SegmentPlan


@dataclass
class BatchData:
    """Scans, pairs and windows, ready for :func:`register_pairs` and :func:`window_errors`."""

    scans: ScanSet
    pairs: PairBatch
    windows: list[Window]
    regularizer: str = "plane"  # plain GICP's covariances (the preprocessing's)
    head: HeadData | None = None  # fine-tuning the backbone's last layer (training.head)

    @property
    def num_pairs(self) -> int:
        return int(self.pairs.target.shape[0])


# --------------------------------------------------------------------------------------------
# Device side: registrations, trajectories, errors


def register_pair(
    learned: Learned, scans: ScanSet, pair: PairBatch, config: BatchConfig, regularizer: str
) -> Array:
    """One registration (``pair`` holds one row of each PairBatch field): ``T_target_source``
    (4, 4) after ``config.rounds`` GICP rounds from ``pair.T_init``; covariances without a
    learned eigenvalue MLP by ``regularizer``."""
    # The target as just the candidate rows, so nothing of size Q is gathered per pair; each
    # placed in the target's frame by its map slot's pose (k-NN eigenvectors rotate too), the
    # slot's pose selected elementwise (M is small) rather than gathered per row.
    T_map = sum(
        jnp.where((pair.slots == m)[..., None, None], T_m, 0.0)
        for m, T_m in enumerate(pair.T_target_map)
    )
    R, t = T_map[..., :3, :3], T_map[..., :3, 3]
    S, Q = scans.mask.shape

    def gather(a: Array) -> Array:  # (S, Q, ...) -> (P, K, ...)
        return a.reshape(S * Q, *a.shape[2:])[pair.candidates]

    t_covs, t_feats = attributes(
        gather(scans.values), geo.matmul(R, gather(scans.vectors)), gather(scans.pca), learned,
        regularizer,
    )  # fmt: skip
    candidates = Cloud(geo.rotate(R, gather(scans.points)) + t, t_covs, pair.valid, t_feats)
    s, rows = pair.source, pair.rows
    s_covs, s_feats = attributes(
        scans.values[s, rows], scans.vectors[s, rows], scans.pca[s, rows], learned, regularizer
    )
    source = Cloud(scans.points[s, rows], s_covs, pair.row_mask & scans.mask[s, rows], s_feats)
    max_d2 = jnp.asarray(config.gicp.max_correspondence_distance**2, scans.points.dtype)
    temperature = (
        jnp.asarray(config.temperature, scans.points.dtype)
        if config.association == "soft"
        else None
    )

    def round_(T: Array, _) -> tuple[Array, None]:
        T, _, _ = gicp_round(
            T, source, candidates, max_d2, config.gicp.inner_steps, config.gicp.adjoint, temperature
        )
        return T, None

    # A scan, so that XLA compiles one round, not config.rounds copies of it; each round
    # rematerialised in the backward pass, so that the gradient keeps only the rounds' poses,
    # not every round's per-candidate intermediates (half the memory, a quicker first step).
    return jax.lax.scan(jax.checkpoint(round_), pair.T_init, length=config.rounds)[0]


def register_pairs(
    learned: Learned, scans: ScanSet, pairs: PairBatch, config: BatchConfig, regularizer: str
) -> Array:
    """All registrations at once (vmap): ``T_prev_curr`` (B, 4, 4). Traceable; see
    :class:`Evaluator` for the jitted whole."""
    return jax.vmap(lambda p: register_pair(learned, scans, p, config, regularizer))(pairs)


PAIRS = "pairs"  # the mesh axis that the pairs shard over


def pair_mesh(devices=None) -> Mesh:
    """A one-axis mesh (``"pairs"``) over ``devices``, by default every local device (one on
    a plain CPU: then nothing is sharded)."""
    devices = jax.local_devices() if devices is None else list(devices)
    if not devices:
        raise InputError(None, "a device mesh needs at least one device")
    return Mesh(np.array(devices), (PAIRS,))


def pad_pairs(pairs: PairBatch, multiple: int) -> PairBatch:
    """The pairs padded to a multiple of ``multiple`` with copies of the last pair: valid
    registrations whose estimates, after the real ones, no window reads (so they change
    neither the errors nor the gradient). Traceable; unchanged when B already is one."""
    extra = -pairs.target.shape[0] % multiple
    if extra == 0:
        return pairs
    return jax.tree_util.tree_map(
        lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)]), pairs
    )


def place(scans: ScanSet, pairs: PairBatch, mesh: Mesh) -> tuple[ScanSet, PairBatch]:
    """The scans copied to every device of ``mesh`` and the pairs, padded
    (:func:`pad_pairs`), split along their leading axis: the layout the sharded functions
    read without moving data."""
    pairs = pad_pairs(pairs, mesh.size)
    scans = jax.device_put(scans, NamedSharding(mesh, P()))
    return scans, jax.device_put(pairs, NamedSharding(mesh, P(PAIRS)))


def register_sharded(
    learned: Learned,
    scans: ScanSet,
    pairs: PairBatch,
    config: BatchConfig,
    regularizer: str,
    mesh: Mesh | None,
) -> Array:
    """:func:`register_pairs` with the pairs split over ``mesh`` (None or one device: not
    split). Returns the estimates of the pairs padded to a multiple of the device count
    (:func:`pad_pairs`): the first B are the pairs'. Traceable and differentiable."""
    if mesh is None or mesh.size == 1:
        return register_pairs(learned, scans, pairs, config, regularizer)
    # Sharding annotations for XLA's partitioner (GSPMD), not shard_map: lineax's operators
    # fail inside shard_map (patrick-kidger/lineax#185). Each device registers its pairs; the
    # vmapped LM loops agree on their stopping step across devices (one small all-reduce).
    split = NamedSharding(mesh, P(PAIRS))
    scans = jax.lax.with_sharding_constraint(scans, NamedSharding(mesh, P()))
    pairs = jax.lax.with_sharding_constraint(pad_pairs(pairs, mesh.size), split)
    T_rel = register_pairs(learned, scans, pairs, config, regularizer)
    return jax.lax.with_sharding_constraint(T_rel, split)


def trajectories(T_rel: Array, windows: list[Window]) -> list[Array]:
    """Each window's estimated camera-0 trajectory (n, 4, 4), first pose identity, from the
    pairs' LiDAR-frame estimates (B, 4, 4): ``Tr @ T_world_lidar @ inv(Tr)``."""
    return [lidar_to_cam_poses(chain(T_rel[w.start : w.stop]), w.Tr_cam_velo) for w in windows]


def window_errors(
    T_rel: Array, windows: list[Window], drift_frames: int = 0, unbias_rotation: bool = False
) -> tuple[Array, Array]:
    """Per-window relative errors (W,) each: translation (fraction) and rotation (rad/m),
    the devkit's rule over each window's scaled segments (the training loss's terms). With
    ``drift_frames`` N > 0 the translation error adds :func:`window_drift` over N frames;
    with ``unbias_rotation`` the windows are scored :func:`without_rotation_bias`."""
    if unbias_rotation:
        T_rel = without_rotation_bias(T_rel, windows)
    t_err, r_err = [], []
    for w, T_est in zip(windows, trajectories(T_rel, windows), strict=True):
        t, r = segment_errors(T_est, jnp.asarray(w.gt_cam, T_est.dtype), w.plan)
        t_err.append(jnp.mean(t)), r_err.append(jnp.mean(r))
    t_err = jnp.stack(t_err)
    if drift_frames:
        t_err = t_err + window_drift(T_rel, windows, drift_frames)
    return t_err, jnp.stack(r_err)


def window_drift(T_rel: Array, windows: list[Window], frames: int) -> Array:
    """Per window (W,): the translational error (a fraction) that its pairs' mean rotation
    error b (rad a pair, about the LiDAR's y and z axes) would add over ``frames`` N frames.
    A constant heading error growing by b a frame moves the end of an N-frame path sideways
    by about b N^2 / 2 frame lengths, N / 2 * |b| of its length. Roll (about x, the direction
    of travel) moves it little, so it is left out."""
    return jnp.stack([0.5 * frames * safe_norm(rotation_bias(T_rel, w)[1:]) for w in windows])


def rotation_bias(T_rel: Array, w: Window) -> Array:
    """Window ``w``'s mean per-pair rotation error (3,), rad: the mean rotation vector of
    ``R_gt^T R_est`` over its pairs, about the LiDAR's x, y, z axes."""
    T_est = T_rel[w.start : w.stop]
    # The ground truth's motions in the LiDAR frame, as T_rel's (host-side constants).
    T_gt = frame_motions(cam_to_lidar_poses(w.gt_cam, w.Tr_cam_velo))
    R_gt_T = jnp.asarray(np.swapaxes(T_gt[:, :3, :3], -1, -2), T_est.dtype)
    return jnp.mean(geo.so3_log(geo.matmul(R_gt_T, T_est[:, :3, :3])), axis=0)


def without_rotation_bias(T_rel: Array, windows: list[Window]) -> Array:
    """``T_rel`` (B, 4, 4) with each window's pairs turned, in their own frame, by minus its
    :func:`rotation_bias`: to first order, each window's rotation errors less their mean."""
    for w in windows:
        T = T_rel[w.start : w.stop]
        turned = geo.matmul(T[:, :3, :3], geo.so3_exp(-rotation_bias(T_rel, w)))
        T_rel = T_rel.at[w.start : w.stop, :3, :3].set(turned)
    return T_rel


def window_t_err(
    learned: Learned, data: BatchData, config: BatchConfig, mesh: Mesh | None = None
) -> Array:
    """Each window's translational relative error (W,) (a fraction) with ``learned``: the
    terms of :func:`loss`. The pairs split over ``mesh`` (see :func:`register_sharded`)."""
    scans = with_head(learned, data.scans, data.head)
    T_rel = register_sharded(learned, scans, data.pairs, config, data.regularizer, mesh)
    return window_errors(T_rel, data.windows, config.drift_frames, config.unbias_rotation)[0]


def loss(
    learned: Learned,
    data: BatchData,
    config: BatchConfig,
    mesh: Mesh | None = None,
    reference: ArrayLike | None = None,
    worse_penalty: float = 0.0,
) -> Array:
    """The training objective of the windows' translational relative errors: their mean (a
    fraction, Eq. (8)'s loss), or with plain GICP's per-window errors ``reference`` (W,) the
    ``gicp_ratio`` of :mod:`gloam_jax.training.objective`. The pairs split over ``mesh`` (see
    :func:`register_sharded`), the same loss to float rounding."""
    return objective(window_t_err(learned, data, config, mesh), reference, worse_penalty)


class Evaluation(NamedTuple):
    """Batch evaluation: per-window ``t_err`` (fraction) and ``r_err`` (rad/m), (W,), and the
    registrations ``T_rel`` (B, 4, 4)."""

    t_err: np.ndarray
    r_err: np.ndarray
    T_rel: np.ndarray


class Evaluator:
    """Jitted batch evaluation of learned parts on fixed data: ``Evaluator(data, cfg)(learned)``.
    Compiles once per structure of ``learned`` (which parts are present). The pairs are split
    over ``mesh`` (default :func:`pair_mesh`: every local device); the scans and padded pairs
    are placed on its devices once, here. ``learned.head`` recomputes the scans' PCA
    features from ``data.head``, as in :func:`loss`."""

    def __init__(self, data: BatchData, config: BatchConfig, mesh: Mesh | None = None) -> None:
        self.data, self.config = data, config
        self.mesh = pair_mesh() if mesh is None else mesh
        windows, regularizer, mesh = data.windows, data.regularizer, self.mesh
        self._scans, self._pairs = place(data.scans, data.pairs, mesh)
        self._head = jax.device_put(data.head, NamedSharding(mesh, P()))

        def run(learned, scans, pairs, head):
            scans = with_head(learned, scans, head)
            T_rel = register_sharded(learned, scans, pairs, config, regularizer, mesh)
            errors = window_errors(T_rel, windows, config.drift_frames, config.unbias_rotation)
            return (*errors, T_rel[: data.num_pairs])

        self._run = jax.jit(run)

    def __call__(self, learned: Learned) -> Evaluation:
        t, r, T = self._run(learned, self._scans, self._pairs, self._head)
        return Evaluation(np.asarray(t), np.asarray(r), np.asarray(T))
