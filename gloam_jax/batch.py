"""Many frame-to-frame registrations at once: ``jit`` + ``vmap`` over padded scan pairs.

Training and batch evaluation register every scan of a window to its predecessor, as the
paper trains (frame-to-frame). The host prepares each scan once (the odometry's preprocessing,
k-NN eigendecomposition, PCA features) and each pair's fixed candidate sets: the K nearest
target points of every (subsampled) source point at the initial guess, within a radius. All
that follows is one traced function of the learned parts: covariances (plane or Algorithm 1),
association features, a fixed number of GICP rounds (:func:`gloam_jax.gicp.gicp_round`, the
partners re-chosen among the candidates in JAX each round), the chained trajectory and its
relative error. It differentiates through the LM solves with either optimistix adjoint.

Pair ``b`` registers source scan ``i + 1`` to target scan ``i``: its estimate is
``T_prev_curr`` in the LiDAR frame, and :func:`trajectories` chains them per window.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from gloam_jax import covariance as cov
from gloam_jax import geometry as geo
from gloam_jax import io
from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError
from gloam_jax.features import Backbone
from gloam_jax.gicp import Cloud, attributes, gicp_round
from gloam_jax.models import GLOAMModel, Learned
from gloam_jax.neighbors import KdTree
from gloam_jax.odometry import OdometryConfig, preprocess_scan
from gloam_jax.training.losses import (
    TRAINING_FRACTIONS,
    SegmentPlan,
    chain,
    scaled_lengths,
    segment_errors,
    segment_plan,
)


@dataclass(frozen=True)
class BatchConfig:
    """Batch registration settings: fixed candidate sets, a fixed number of rounds."""

    rounds: int = 4  # GICP rounds, partners re-chosen among the candidates each round
    inner_steps: int = 2  # LM steps per round
    num_candidates: int = 5  # K target candidates per source point (found once)
    candidate_radius: float = 2.0  # m around the initial guess
    max_correspondence_distance: float = 1.0  # m, checked at each round's estimate
    max_source_points: int = 2048  # source points per pair (a fixed random subset)
    association: Literal["hard", "soft"] = "hard"  # soft: softmax weights (training DA)
    temperature: float = 0.05  # soft association's, in the cost's units (m^2)
    adjoint: Literal["unrolled", "implicit"] = "unrolled"  # differentiation through LM
    segment_fractions: tuple[float, ...] = TRAINING_FRACTIONS  # of each window's path
    segment_step: int = 10  # frames between segment starts (the devkit's)
    seed: int = 0  # source subsets

    def __post_init__(self) -> None:
        if self.inner_steps < 2:  # optimistix's LM spends its first step initialising
            raise InputError(None, f"inner_steps must be at least 2, not {self.inner_steps}")
        if self.rounds < 1 or self.num_candidates < 1 or self.max_source_points < 1:
            raise InputError(None, "rounds, num_candidates and max_source_points must be >= 1")
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


class PairSet(NamedTuple):
    """B registrations: scan indices ``target``, ``source`` (B,); source rows (B, P) with
    ``row_mask``; candidate target rows (B, P, K) with ``valid``; ``T_init`` (B, 4, 4)."""

    target: Array
    source: Array
    rows: Array
    row_mask: Array
    candidates: Array
    valid: Array
    T_init: Array


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
    pairs: PairSet
    windows: list[Window]

    @property
    def num_pairs(self) -> int:
        return int(self.pairs.target.shape[0])


# --------------------------------------------------------------------------------------------
# Host side: scans and candidate sets


@jax.jit
def _knn_eigen(points: Array, neighbours: Array) -> tuple[Array, Array]:
    return cov.eigendecompose(cov.knn_covariances(points, neighbours))


def _prepare_scan(seq, i, odometry, model, backbone, velocity, frame_dt):
    scan = seq.scan(i)
    path = str(seq.scan_path(i))
    features = None if model is None else backbone(scan, path=path, frame=i)
    points, pca, _ = preprocess_scan(
        scan,
        seq.point_times(i),
        odometry,
        velocity=velocity,
        frame_dt=frame_dt,
        model=model,
        features=features,
        source=path,
    )
    neighbours, _ = KdTree(points, path).query(points, odometry.num_neighbors)
    size = pc.bucket_size(len(points))
    values, vectors = _knn_eigen(
        jnp.asarray(pc.pad(points, size)[0], jnp.float32), jnp.asarray(pc.pad(neighbours, size)[0])
    )
    n = len(points)
    pca = np.zeros((n, 0), np.float32) if pca is None else pca.astype(np.float32)
    return points, np.asarray(values)[:n], np.asarray(vectors)[:n], pca


def _velocities(rel_gt: np.ndarray) -> np.ndarray:
    """se(3) motion per frame (n, 6) from the (n - 1, 4, 4) ground-truth frame-to-frame
    motions; frame 0 takes frame 1's."""
    xi = np.asarray(geo.se3_log_jit(rel_gt), np.float64)
    return np.concatenate([xi[:1], xi])


def prepare_window(
    seq: io.KittiSequence,
    frames: range,
    odometry: OdometryConfig,
    config: BatchConfig,
    model: GLOAMModel | None = None,
    backbone: Backbone | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Prepared scans and pairs of one window of ``seq`` as host arrays (see :func:`stack`).

    Scans are deskewed with the ground truth's velocity (so training sees clean sweeps, as an
    odometry with a good velocity estimate does); each pair's initial guess is the previous
    interval's ground-truth motion (constant velocity; the identity for the first pair), its
    candidates found at that guess.
    """
    gt_cam = seq.gt_poses_cam
    if gt_cam is None:
        raise InputError(seq.sequence_dir, "training and batch evaluation need ground truth")
    frames = range(frames.start, min(frames.stop, len(seq)), 1)
    if len(frames) < 2:
        raise InputError(seq.sequence_dir, f"need at least 2 scans, have {len(frames)}")
    if model is not None and backbone is None:
        raise InputError(None, "a model needs the backbone that makes its features")
    gt_lidar = seq.gt_poses_lidar[frames.start : frames.stop]
    rel_gt = np.linalg.inv(gt_lidar[:-1]) @ gt_lidar[1:]
    velocity = _velocities(rel_gt)
    times = seq.times
    scans = []
    for k, i in enumerate(frames):
        dt = float(times[i] - times[i - 1]) if i > 0 else odometry.sweep_duration
        scans.append(_prepare_scan(seq, i, odometry, model, backbone, velocity[k], dt))
        if progress is not None:
            progress(k)
    rng = np.random.default_rng(config.seed)
    rows, cands, valids, T_init = [], [], [], []
    for k in range(len(frames) - 1):
        target, source = scans[k][0], scans[k + 1][0]
        n = len(source)
        sub = np.arange(n)
        if n > config.max_source_points:
            sub = np.sort(rng.choice(n, config.max_source_points, replace=False))
        T0 = rel_gt[k - 1] if k > 0 else np.eye(4)
        moved = source[sub] @ T0[:3, :3].T + T0[:3, 3]
        c, v = KdTree(target, str(seq.scan_path(frames[k]))).query(
            moved, config.num_candidates, config.candidate_radius
        )
        rows.append(sub)
        cands.append(c)
        valids.append(v)
        T_init.append(T0)
    return {
        "name": seq.sequence,
        "scans": scans,
        "rows": rows,
        "candidates": cands,
        "valid": valids,
        "T_init": np.stack(T_init),
        "gt_cam": gt_cam[frames.start : frames.stop],
        "Tr_cam_velo": seq.Tr_cam_velo,
    }


# The BatchConfig fields that prepare_window uses; the others act on the device side only.
_PREPARATION_FIELDS = ("num_candidates", "candidate_radius", "max_source_points", "seed")


def _cache_key(seq, frames, odometry, config, model, backbone) -> str:
    parts = {
        "sequence": str(seq.sequence_dir.resolve()),
        "frames": [frames.start, frames.stop],
        "odometry": asdict(odometry),
        "batch": {k: getattr(config, k) for k in _PREPARATION_FIELDS},
        "backbone": None if backbone is None else [backbone.name, backbone.options()],
    }
    h = hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode())
    if model is not None:
        for a in model.pca:
            h.update(np.ascontiguousarray(a, np.float64).tobytes())
    return h.hexdigest()[:16]


def _save_window(path: Path, w: dict) -> None:
    arrays = {"T_init": w["T_init"], "gt_cam": w["gt_cam"], "Tr_cam_velo": w["Tr_cam_velo"]}
    for k, scan in enumerate(w["scans"]):
        for name, a in zip(("points", "values", "vectors", "pca"), scan, strict=True):
            arrays[f"scan{k}_{name}"] = a
    for k in range(len(w["rows"])):
        arrays[f"pair{k}_rows"] = w["rows"][k]
        arrays[f"pair{k}_candidates"] = w["candidates"][k]
        arrays[f"pair{k}_valid"] = w["valid"][k]
    io.write_npz(path, name=np.array(w["name"]), **arrays)


def _load_window(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        n = len(z["gt_cam"])
        return {
            "name": str(z["name"]),
            "scans": [tuple(z[f"scan{k}_{a}"] for a in ("points", "values", "vectors", "pca"))
                      for k in range(n)],
            "rows": [z[f"pair{k}_rows"] for k in range(n - 1)],
            "candidates": [z[f"pair{k}_candidates"] for k in range(n - 1)],
            "valid": [z[f"pair{k}_valid"] for k in range(n - 1)],
            "T_init": z["T_init"],
            "gt_cam": z["gt_cam"],
            "Tr_cam_velo": z["Tr_cam_velo"],
        }  # fmt: skip


def load_windows(
    root: str | Path,
    sequences: Sequence[str],
    odometry: OdometryConfig,
    config: BatchConfig,
    model: GLOAMModel | None = None,
    backbone: Backbone | None = None,
    *,
    frames: int | None = None,
    cache_dir: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> BatchData:
    """Prepare the first ``frames`` scans (all by default) of each sequence under ``root`` and
    stack them (:func:`stack`). With ``cache_dir``, prepared windows are saved there
    (atomically) and reused by later runs with the same settings and PCA."""
    windows = []
    for name in sequences:
        seq = io.KittiSequence(root, name)
        window = range(0, len(seq) if frames is None else min(frames, len(seq)))
        path = None
        if cache_dir is not None:
            key = _cache_key(seq, window, odometry, config, model, backbone)
            path = Path(cache_dir) / f"window_{name}_{key}.npz"
            if path.is_file():
                windows.append(_load_window(path))
                continue
        step = None if progress is None else partial(progress, name, len(window))
        w = prepare_window(seq, window, odometry, config, model, backbone, step)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            _save_window(path, w)
        windows.append(w)
    return stack(windows, config)


def stack(windows: list[dict], config: BatchConfig) -> BatchData:
    """Pad and concatenate prepared windows into device arrays (float32, or float64 under
    x64): scans padded to the largest one's bucket, pairs to ``max_source_points``."""
    real = jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32
    all_scans = [s for w in windows for s in w["scans"]]
    size = pc.bucket_size(max(len(s[0]) for s in all_scans))
    P = max(len(r) for w in windows for r in w["rows"])
    scan_cols = [[], [], [], [], []]
    pair_cols = [[], [], [], [], [], [], []]
    info, scan_offset, pair_offset = [], 0, 0
    for w in windows:
        for scan in w["scans"]:
            n_points = len(scan[0])
            for col, a in zip(scan_cols, scan, strict=False):
                col.append(pc.pad(np.asarray(a), size)[0])
            scan_cols[1][-1][n_points:] = 1.0  # padded rows: unit spheres, finite
            scan_cols[2][-1][n_points:] = np.eye(3)
            scan_cols[4].append(pc.pad(scan[0], size)[1])
        n = len(w["scans"])
        for k in range(n - 1):
            rows, row_mask = pc.pad(w["rows"][k].astype(np.int32), P)
            pair_cols[0].append(scan_offset + k)
            pair_cols[1].append(scan_offset + k + 1)
            pair_cols[2].append(rows)
            pair_cols[3].append(row_mask)
            pair_cols[4].append(pc.pad(w["candidates"][k], P)[0])
            pair_cols[5].append(pc.pad(w["valid"][k], P)[0])
            pair_cols[6].append(w["T_init"][k])
        gt = np.asarray(w["gt_cam"], np.float64)
        lengths = scaled_lengths(gt, config.segment_fractions, source=w["name"])
        plan = segment_plan(gt, lengths, step=config.segment_step, source=w["name"])
        info.append(Window(w["name"], pair_offset, pair_offset + n - 1, gt, w["Tr_cam_velo"], plan))
        scan_offset, pair_offset = scan_offset + n, pair_offset + n - 1
    scans = ScanSet(
        *(jnp.asarray(np.stack(c), real) for c in scan_cols[:4]),
        jnp.asarray(np.stack(scan_cols[4])),
    )
    pairs = PairSet(
        jnp.asarray(pair_cols[0], jnp.int32),
        jnp.asarray(pair_cols[1], jnp.int32),
        jnp.asarray(np.stack(pair_cols[2])),
        jnp.asarray(np.stack(pair_cols[3])),
        jnp.asarray(np.stack(pair_cols[4])),
        jnp.asarray(np.stack(pair_cols[5])),
        jnp.asarray(np.stack(pair_cols[6]), real),
    )
    return BatchData(scans, pairs, info)


# --------------------------------------------------------------------------------------------
# Device side: registrations, trajectories, errors


def register_pair(learned: Learned, scans: ScanSet, pair: PairSet, config: BatchConfig) -> Array:
    """One registration (``pair`` holds one row of each PairSet field): ``T_target_source``
    (4, 4) after ``config.rounds`` GICP rounds from ``pair.T_init``."""
    t, s = pair.target, pair.source
    P, K = pair.candidates.shape
    # The target as just the candidate rows (P * K), so nothing of size Q is gathered per pair.
    flat = pair.candidates.reshape(-1)
    t_covs, t_feats = attributes(
        scans.values[t, flat], scans.vectors[t, flat], scans.pca[t, flat], learned, "plane"
    )
    target = Cloud(scans.points[t, flat], t_covs, scans.mask[t, flat], t_feats)
    rows = pair.rows
    s_covs, s_feats = attributes(
        scans.values[s, rows], scans.vectors[s, rows], scans.pca[s, rows], learned, "plane"
    )
    source = Cloud(scans.points[s, rows], s_covs, pair.row_mask & scans.mask[s, rows], s_feats)
    local = jnp.arange(P * K, dtype=jnp.int32).reshape(P, K)
    max_d2 = jnp.asarray(config.max_correspondence_distance**2, scans.points.dtype)
    temperature = (
        jnp.asarray(config.temperature, scans.points.dtype)
        if config.association == "soft"
        else None
    )
    T = pair.T_init
    for _ in range(config.rounds):
        T, _, _ = gicp_round(
            T, source, target, local, pair.valid, max_d2, config.inner_steps, config.adjoint,
            temperature,
        )  # fmt: skip
    return T


def register_pairs(learned: Learned, scans: ScanSet, pairs: PairSet, config: BatchConfig) -> Array:
    """All registrations at once (vmap): ``T_prev_curr`` (B, 4, 4). Traceable; see
    :func:`evaluate` for the jitted whole."""
    return jax.vmap(lambda p: register_pair(learned, scans, p, config))(pairs)


def trajectories(T_rel: Array, windows: list[Window]) -> list[Array]:
    """Each window's estimated camera-0 trajectory (n, 4, 4), first pose identity, from the
    pairs' LiDAR-frame estimates (B, 4, 4): ``Tr @ T_world_lidar @ inv(Tr)``."""
    out = []
    for w in windows:
        T_lidar = chain(T_rel[w.start : w.stop])
        Tr = jnp.asarray(w.Tr_cam_velo, T_rel.dtype)
        out.append(Tr @ T_lidar @ jnp.asarray(np.linalg.inv(w.Tr_cam_velo), T_rel.dtype))
    return out


def window_errors(T_rel: Array, windows: list[Window]) -> tuple[Array, Array]:
    """Per-window relative errors (W,) each: translation (fraction) and rotation (rad/m),
    the devkit's rule over each window's scaled segments (the training loss's terms)."""
    t_err, r_err = [], []
    for w, T_est in zip(windows, trajectories(T_rel, windows), strict=True):
        t, r = segment_errors(T_est, jnp.asarray(w.gt_cam, T_est.dtype), w.plan)
        t_err.append(jnp.mean(t)), r_err.append(jnp.mean(r))
    return jnp.stack(t_err), jnp.stack(r_err)


def loss(learned: Learned, data: BatchData, config: BatchConfig) -> Array:
    """Mean translational relative error over the windows (a fraction): Eq. (8)'s loss."""
    T_rel = register_pairs(learned, data.scans, data.pairs, config)
    return jnp.mean(window_errors(T_rel, data.windows)[0])


class Evaluation(NamedTuple):
    """Batch evaluation: per-window ``t_err`` (fraction) and ``r_err`` (rad/m), (W,), and the
    registrations ``T_rel`` (B, 4, 4)."""

    t_err: np.ndarray
    r_err: np.ndarray
    T_rel: np.ndarray


class Evaluator:
    """Jitted batch evaluation of learned parts on fixed data: ``Evaluator(data, cfg)(learned)``.
    Compiles once per structure of ``learned`` (which parts are present)."""

    def __init__(self, data: BatchData, config: BatchConfig) -> None:
        self.data, self.config = data, config
        windows = data.windows

        def run(learned, scans, pairs):
            T_rel = register_pairs(learned, scans, pairs, config)
            return (*window_errors(T_rel, windows), T_rel)

        self._run = jax.jit(run)

    def __call__(self, learned: Learned) -> Evaluation:
        t, r, T = self._run(learned, self.data.scans, self.data.pairs)
        return Evaluation(np.asarray(t), np.asarray(r), np.asarray(T))
