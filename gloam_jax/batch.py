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
    # The target of pair k: scan k alone (map_scans 1, frame-to-frame, as the paper trains),
    # or a local map of scans k, k - map_stride, ... (map_scans of them) merged with the
    # ground-truth poses, as the odometry registers to its last keyframes.
    map_scans: int = 1
    map_stride: int = 2

    def __post_init__(self) -> None:
        if self.inner_steps < 2:  # optimistix's LM spends its first step initialising
            raise InputError(None, f"inner_steps must be at least 2, not {self.inner_steps}")
        if min(self.rounds, self.num_candidates, self.max_source_points, self.map_scans,
               self.map_stride) < 1:  # fmt: skip
            raise InputError(
                None,
                "rounds, num_candidates, max_source_points, map_scans and map_stride must be >= 1",
            )
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


def select_rows(pairs: PairSet, index: Array) -> PairSet:
    """The same source-row slots (R,) of every pair: a PairSet with P = R."""
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
    points, pca, _, _ = preprocess_scan(
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


def prepare_scans(
    seq: io.KittiSequence,
    frames: range,
    odometry: OdometryConfig,
    model: GLOAMModel | None = None,
    backbone: Backbone | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Prepared scans of one window of ``seq`` and its ground truth, as host arrays.

    Scans are deskewed with the ground truth's velocity, so training sees clean sweeps, as an
    odometry with a good velocity estimate does.
    """
    gt_cam = seq.gt_poses_cam
    if gt_cam is None:
        raise InputError(seq.sequence_dir, "training and batch evaluation need ground truth")
    frames = range(frames.start, min(frames.stop, len(seq)), 1)
    if len(frames) < 2:
        raise InputError(seq.sequence_dir, f"need at least 2 scans, have {len(frames)}")
    if model is not None and backbone is None:
        raise InputError(None, "a model needs the backbone that makes its features")
    gt_lidar = _lidar_poses(gt_cam[frames.start : frames.stop], seq.Tr_cam_velo)
    velocity = _velocities(_relative_motions(gt_lidar))
    times = seq.times
    scans = []
    for k, i in enumerate(frames):
        dt = float(times[i] - times[i - 1]) if i > 0 else odometry.sweep_duration
        scans.append(_prepare_scan(seq, i, odometry, model, backbone, velocity[k], dt))
        if progress is not None:
            progress(k)
    return {
        "name": seq.sequence,
        "scans": scans,
        "gt_cam": gt_cam[frames.start : frames.stop],
        "Tr_cam_velo": seq.Tr_cam_velo,
    }


def _lidar_poses(gt_cam: np.ndarray, Tr_cam_velo: np.ndarray) -> np.ndarray:
    return np.linalg.inv(Tr_cam_velo) @ gt_cam @ Tr_cam_velo


def _relative_motions(gt_lidar: np.ndarray) -> np.ndarray:
    """Ground-truth LiDAR motions from each scan to the next (n - 1, 4, 4)."""
    return np.linalg.inv(gt_lidar[:-1]) @ gt_lidar[1:]


def prepare_pairs(window: dict, config: BatchConfig) -> dict[str, np.ndarray]:
    """Each pair of a :func:`prepare_scans` window: source rows (a fixed random subset),
    its local map and the candidates in it, and the initial guess, as host arrays.

    The initial guess is the previous interval's ground-truth motion (constant velocity; the
    identity for the first pair); the candidates are found at that guess. The map of pair k
    holds up to ``map_scans`` scans, k, k - map_stride, ..., placed by the ground truth.
    """
    scans, name = window["scans"], window["name"]
    gt_lidar = _lidar_poses(window["gt_cam"], window["Tr_cam_velo"])
    rel_gt = _relative_motions(gt_lidar)
    M = config.map_scans
    rng = np.random.default_rng(config.seed)
    out = {key: [] for key in ("rows", "candidates", "slots", "valid", "map_scans", "T_map")}
    T_init = []
    for k in range(len(scans) - 1):
        source = scans[k + 1][0]
        n = len(source)
        sub = np.arange(n)
        if n > config.max_source_points:
            sub = np.sort(rng.choice(n, config.max_source_points, replace=False))
        members = [k - j * config.map_stride for j in range(M) if k - j * config.map_stride >= 0]
        T_map = np.linalg.inv(gt_lidar[k]) @ gt_lidar[members]
        merged = np.concatenate(
            [scans[m][0] @ T[:3, :3].T + T[:3, 3] for m, T in zip(members, T_map, strict=True)]
        )
        slot_of = np.concatenate([np.full(len(scans[m][0]), j) for j, m in enumerate(members)])
        row_of = np.concatenate([np.arange(len(scans[m][0])) for m in members])
        T0 = rel_gt[k - 1] if k > 0 else np.eye(4)
        moved = source[sub] @ T0[:3, :3].T + T0[:3, 3]
        c, v = KdTree(merged, f"{name}: map of pair {k}").query(
            moved, config.num_candidates, config.candidate_radius
        )
        unused = M - len(members)  # early pairs: fewer scans; the spare slots go unused
        out["rows"].append(sub)
        out["candidates"].append(row_of[c].astype(np.int32))
        out["slots"].append(slot_of[c].astype(np.int8))
        out["valid"].append(v)
        out["map_scans"].append(np.asarray(members + [k] * unused, np.int32))
        out["T_map"].append(np.concatenate([T_map, np.tile(np.eye(4), (unused, 1, 1))]))
        T_init.append(T0)
    return out | {"T_init": np.stack(T_init)}


def prepare_window(
    seq: io.KittiSequence,
    frames: range,
    odometry: OdometryConfig,
    config: BatchConfig,
    model: GLOAMModel | None = None,
    backbone: Backbone | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Prepared scans and pairs of one window of ``seq`` as host arrays (see :func:`stack`)."""
    window = prepare_scans(seq, frames, odometry, model, backbone, progress)
    return window | prepare_pairs(window, config)


# The BatchConfig fields that prepare_pairs uses; the others act on the device side only.
_PAIR_FIELDS = (
    "num_candidates", "candidate_radius", "max_source_points", "seed", "map_scans", "map_stride"
)  # fmt: skip
_SCAN_ARRAYS = ("points", "values", "vectors", "pca")
_PAIR_ARRAYS = ("rows", "candidates", "slots", "valid", "map_scans", "T_map")


def _cache_keys(seq, frames, odometry, config, model, backbone) -> tuple[str, str]:
    """Keys of a window's prepared scans and of its pairs (which also depend on the scans)."""
    parts = {
        "sequence": str(seq.sequence_dir.resolve()),
        "frames": [frames.start, frames.stop],
        "odometry": asdict(odometry),
        "backbone": None if backbone is None else [backbone.name, backbone.options()],
    }
    h = hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode())
    if model is not None:
        for a in model.pca:
            h.update(np.ascontiguousarray(a, np.float64).tobytes())
    scan_key = h.hexdigest()[:16]
    pair_parts = {k: getattr(config, k) for k in _PAIR_FIELDS}
    pair_key = hashlib.sha1(json.dumps([scan_key, pair_parts]).encode()).hexdigest()[:16]
    return scan_key, pair_key


def _save_scans(path: Path, w: dict) -> None:
    arrays = {"gt_cam": w["gt_cam"], "Tr_cam_velo": w["Tr_cam_velo"]}
    for k, scan in enumerate(w["scans"]):
        for name, a in zip(_SCAN_ARRAYS, scan, strict=True):
            arrays[f"scan{k}_{name}"] = a
    io.write_npz(path, name=np.array(w["name"]), **arrays)


def _load_scans(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        n = len(z["gt_cam"])
        return {
            "name": str(z["name"]),
            "scans": [tuple(z[f"scan{k}_{a}"] for a in _SCAN_ARRAYS) for k in range(n)],
            "gt_cam": z["gt_cam"],
            "Tr_cam_velo": z["Tr_cam_velo"],
        }


def _save_pairs(path: Path, p: dict) -> None:
    arrays = {f"pair{k}_{a}": p[a][k] for a in _PAIR_ARRAYS for k in range(len(p["rows"]))}
    io.write_npz(path, T_init=p["T_init"], **arrays)


def _load_pairs(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        n = len(z["T_init"])
        return {a: [z[f"pair{k}_{a}"] for k in range(n)] for a in _PAIR_ARRAYS} | {
            "T_init": z["T_init"]
        }


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
    stack them (:func:`stack`). With ``cache_dir``, prepared scans and pairs are saved there
    (atomically, apart, since pairs are cheap to redo) and reused by later runs with the same
    settings and PCA."""
    windows = []
    for name in sequences:
        seq = io.KittiSequence(root, name)
        window = range(0, len(seq) if frames is None else min(frames, len(seq)))
        scan_path = pair_path = None
        if cache_dir is not None:
            scan_key, pair_key = _cache_keys(seq, window, odometry, config, model, backbone)
            scan_path = Path(cache_dir) / f"scans_{name}_{scan_key}.npz"
            pair_path = Path(cache_dir) / f"pairs_{name}_{pair_key}.npz"
            scan_path.parent.mkdir(parents=True, exist_ok=True)
        if scan_path is not None and scan_path.is_file():
            w = _load_scans(scan_path)
        else:
            step = None if progress is None else partial(progress, name, len(window))
            w = prepare_scans(seq, window, odometry, model, backbone, step)
            if scan_path is not None:
                _save_scans(scan_path, w)
        if pair_path is not None and pair_path.is_file():
            pairs = _load_pairs(pair_path)
        else:
            pairs = prepare_pairs(w, config)
            if pair_path is not None:
                _save_pairs(pair_path, pairs)
        windows.append(w | pairs)
    return stack(windows, config)


def stack(windows: list[dict], config: BatchConfig) -> BatchData:
    """Pad and concatenate prepared windows into device arrays (float32, or float64 under
    x64): scans padded to the largest one's bucket, pairs to ``max_source_points``."""
    real = jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32
    all_scans = [s for w in windows for s in w["scans"]]
    size = pc.bucket_size(max(len(s[0]) for s in all_scans))
    P = max(len(r) for w in windows for r in w["rows"])
    scan_cols = [[], [], [], [], []]
    pair_cols = {key: [] for key in PairSet._fields}
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
            # Candidates as rows of the flattened scans: the map slot's scan, then the row.
            scan_of = scan_offset + w["map_scans"][k][w["slots"][k].astype(np.int64)]
            flat = (scan_of * size + w["candidates"][k]).astype(np.int32)
            pair_cols["target"].append(scan_offset + k)
            pair_cols["source"].append(scan_offset + k + 1)
            pair_cols["rows"].append(rows)
            pair_cols["row_mask"].append(row_mask)
            pair_cols["candidates"].append(pc.pad(flat, P)[0])
            pair_cols["slots"].append(pc.pad(w["slots"][k].astype(np.int32), P)[0])
            pair_cols["valid"].append(pc.pad(w["valid"][k], P)[0])
            pair_cols["T_target_map"].append(w["T_map"][k])
            pair_cols["T_init"].append(w["T_init"][k])
        gt = np.asarray(w["gt_cam"], np.float64)
        lengths = scaled_lengths(gt, config.segment_fractions, source=w["name"])
        plan = segment_plan(gt, lengths, step=config.segment_step, source=w["name"])
        info.append(Window(w["name"], pair_offset, pair_offset + n - 1, gt, w["Tr_cam_velo"], plan))
        scan_offset, pair_offset = scan_offset + n, pair_offset + n - 1
    if scan_offset * size >= 1 << 31:
        raise InputError(None, f"{scan_offset} scans of {size} rows overflow int32 row indices")
    scans = ScanSet(
        *(jnp.asarray(np.stack(c), real) for c in scan_cols[:4]),
        jnp.asarray(np.stack(scan_cols[4])),
    )
    floats = {"T_target_map", "T_init"}
    pairs = PairSet(
        **{k: jnp.asarray(np.stack(v), real if k in floats else None) for k, v in pair_cols.items()}
    )
    return BatchData(scans, pairs, info)


# --------------------------------------------------------------------------------------------
# Device side: registrations, trajectories, errors


def register_pair(learned: Learned, scans: ScanSet, pair: PairSet, config: BatchConfig) -> Array:
    """One registration (``pair`` holds one row of each PairSet field): ``T_target_source``
    (4, 4) after ``config.rounds`` GICP rounds from ``pair.T_init``."""
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
        "plane",
    )  # fmt: skip
    candidates = Cloud(geo.rotate(R, gather(scans.points)) + t, t_covs, pair.valid, t_feats)
    s, rows = pair.source, pair.rows
    s_covs, s_feats = attributes(
        scans.values[s, rows], scans.vectors[s, rows], scans.pca[s, rows], learned, "plane"
    )
    source = Cloud(scans.points[s, rows], s_covs, pair.row_mask & scans.mask[s, rows], s_feats)
    max_d2 = jnp.asarray(config.max_correspondence_distance**2, scans.points.dtype)
    temperature = (
        jnp.asarray(config.temperature, scans.points.dtype)
        if config.association == "soft"
        else None
    )

    def round_(T: Array, _) -> tuple[Array, None]:
        T, _, _ = gicp_round(
            T, source, candidates, max_d2, config.inner_steps, config.adjoint, temperature
        )
        return T, None

    # A scan, so that XLA compiles one round, not config.rounds copies of it; each round
    # rematerialised in the backward pass, so that the gradient keeps only the rounds' poses,
    # not every round's per-candidate intermediates (half the memory, a quicker first step).
    return jax.lax.scan(jax.checkpoint(round_), pair.T_init, length=config.rounds)[0]


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
