"""Training and batch-evaluation data on the host: prepared scans, pairs, a cache, stacking.

A window of a KITTI-layout sequence becomes a :class:`PreparedWindow` (each scan prepared once:
the preprocessing of :mod:`gloam_jax.preprocess`, its k-NN eigendecomposition, PCA features)
and :class:`PreparedPairs` (each pair's source rows, its local map and the fixed candidate
sets in it, and the initial guess). :func:`load_windows` caches both (apart, since pairs are
cheap to redo) and :func:`stack` pads them into the device arrays of
:mod:`gloam_jax.training.batch`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax import covariance as cov
from gloam_jax import geometry as geo
from gloam_jax import io
from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError
from gloam_jax.features import Backbone
from gloam_jax.features.pca import FeaturePCA
from gloam_jax.neighbors import KdTree
from gloam_jax.preprocess import PreprocessConfig, deskew_centres, on_grid, voxel_centres
from gloam_jax.training.batch import BatchConfig, BatchData, PairBatch, ScanSet, Window
from gloam_jax.training.losses import scaled_lengths, segment_plan


class PreparedScan(NamedTuple):
    """One prepared scan: voxel centres (n, 3) float64, ascending eigenvalues (n, 3) and
    eigenvectors (n, 3, 3) of their k-NN covariances, PCA features (n, 6) (width 0 without
    a model), float32."""

    points: np.ndarray
    values: np.ndarray
    vectors: np.ndarray
    pca: np.ndarray


@dataclass
class PreparedWindow:
    """The prepared scans of one window and its ground truth: camera-0 poses (n, 4, 4) and
    the calibration ``Tr_cam_velo`` (4, 4)."""

    name: str
    scans: list[PreparedScan]
    gt_cam: np.ndarray
    Tr_cam_velo: np.ndarray


@dataclass
class PreparedPairs:
    """The n - 1 pairs of a window; pair k registers scan k + 1 to the map of scan k.

    Per pair: the source rows used (P_k,), the candidates (P_k, K) as rows of the map's
    scans with the map ``slots`` they come from and which are ``valid``; the map's scans
    ``map_scans`` (M,) and their poses in scan k's frame ``T_map`` (M, 4, 4). ``T_init``
    (n - 1, 4, 4): the initial guesses."""

    rows: list[np.ndarray]
    candidates: list[np.ndarray]
    slots: list[np.ndarray]
    valid: list[np.ndarray]
    map_scans: list[np.ndarray]
    T_map: list[np.ndarray]
    T_init: np.ndarray


_PER_PAIR = tuple(f.name for f in dataclasses.fields(PreparedPairs) if f.name != "T_init")


@jax.jit
def _knn_eigen(points: jax.Array, neighbours: jax.Array) -> tuple[jax.Array, jax.Array]:
    return cov.eigendecompose(cov.knn_covariances(points, neighbours))


def _prepare_scan(seq, i, config, pca, backbone, velocity, frame_dt) -> PreparedScan:
    scan = seq.scan(i)
    path = str(seq.scan_path(i))
    grid_backbone = None if pca is None else on_grid(backbone, config)
    features = None
    if pca is not None and grid_backbone is None:
        features = backbone(scan, path=path, frame=i)
    centres = voxel_centres(scan, seq.point_times(i), config, pca=pca, features=features,
                            backbone=grid_backbone, source=path)  # fmt: skip
    points, pca_features = deskew_centres(centres, velocity, frame_dt), centres.features
    # The odometry's neighbourhoods: the grid backbone's where it found them (VoxelCentres)
    neighbours = centres.neighbours
    if neighbours is None:
        neighbours, _ = KdTree(points, path).query(points, config.num_neighbors)
    size = pc.bucket_size(len(points))
    values, vectors = _knn_eigen(
        jnp.asarray(pc.pad(points, size)[0], jnp.float32), jnp.asarray(pc.pad(neighbours, size)[0])
    )
    n = len(points)
    pca_features = (
        np.zeros((n, 0), np.float32) if pca_features is None else pca_features.astype(np.float32)
    )
    return PreparedScan(points, np.asarray(values)[:n], np.asarray(vectors)[:n], pca_features)


def _velocities(rel_gt: np.ndarray) -> np.ndarray:
    """se(3) motion per frame (n, 6) from the (n - 1, 4, 4) ground-truth frame-to-frame
    motions; frame 0 takes frame 1's."""
    xi = np.asarray(geo.se3_log_jit(rel_gt), np.float64)
    return np.concatenate([xi[:1], xi])


def prepare_scans(
    seq: io.KittiSequence,
    frames: range,
    config: PreprocessConfig,
    pca: FeaturePCA | None = None,
    backbone: Backbone | None = None,
    progress: Callable[[int], None] | None = None,
) -> PreparedWindow:
    """The prepared scans of one window of ``seq`` (PCA features when ``pca`` is given, from
    ``backbone``'s features) and its ground truth.

    Scans are deskewed with the ground truth's velocity, so training sees clean sweeps, as an
    odometry with a good velocity estimate does.
    """
    gt_cam = seq.gt_poses_cam
    if gt_cam is None:
        raise InputError(seq.sequence_dir, "training and batch evaluation need ground truth")
    frames = range(frames.start, min(frames.stop, len(seq)), 1)
    if len(frames) < 2:
        raise InputError(seq.sequence_dir, f"need at least 2 scans, have {len(frames)}")
    if pca is not None and backbone is None:
        raise InputError(None, "a model needs the backbone that makes its features")
    gt_cam = gt_cam[frames.start : frames.stop]
    velocity = _velocities(io.frame_motions(io.cam_to_lidar_poses(gt_cam, seq.Tr_cam_velo)))
    times = seq.times
    scans = []
    for k, i in enumerate(frames):
        dt = float(times[i] - times[i - 1]) if i > 0 else config.sweep_duration
        scans.append(_prepare_scan(seq, i, config, pca, backbone, velocity[k], dt))
        if progress is not None:
            progress(k)
    return PreparedWindow(seq.sequence, scans, gt_cam, seq.Tr_cam_velo)


def prepare_pairs(window: PreparedWindow, config: BatchConfig) -> PreparedPairs:
    """Each pair of a window: source rows (a fixed random subset), its local map and the
    candidates in it, and the initial guess.

    The initial guess is the previous interval's ground-truth motion (constant velocity; the
    identity for the first pair); the candidates are found at that guess. The map of pair k
    holds up to ``map_scans`` scans, k, k - map_stride, ..., placed by the ground truth.
    """
    scans, name = window.scans, window.name
    gt_lidar = io.cam_to_lidar_poses(window.gt_cam, window.Tr_cam_velo)
    rel_gt = io.frame_motions(gt_lidar)
    M = config.map_scans
    rng = np.random.default_rng(config.seed)
    out = {key: [] for key in _PER_PAIR}
    T_init = []
    for k in range(len(scans) - 1):
        source = scans[k + 1].points
        n = len(source)
        sub = np.arange(n)
        if n > config.max_source_points:
            sub = np.sort(rng.choice(n, config.max_source_points, replace=False))
        members = [k - j * config.map_stride for j in range(M) if k - j * config.map_stride >= 0]
        T_map = np.linalg.inv(gt_lidar[k]) @ gt_lidar[members]
        merged = np.concatenate(
            [scans[m].points @ T[:3, :3].T + T[:3, 3] for m, T in zip(members, T_map, strict=True)]
        )
        slot_of = np.concatenate([np.full(len(scans[m].points), j) for j, m in enumerate(members)])
        row_of = np.concatenate([np.arange(len(scans[m].points)) for m in members])
        T0 = rel_gt[k - 1] if k > 0 else np.eye(4)
        moved = source[sub] @ T0[:3, :3].T + T0[:3, 3]
        c, v = KdTree(merged, f"{name}: map of pair {k}").query(
            moved, config.gicp.num_candidates, config.candidate_radius
        )
        unused = M - len(members)  # early pairs: fewer scans; the spare slots go unused
        out["rows"].append(sub)
        out["candidates"].append(row_of[c].astype(np.int32))
        out["slots"].append(slot_of[c].astype(np.int8))
        out["valid"].append(v)
        out["map_scans"].append(np.asarray(members + [k] * unused, np.int32))
        out["T_map"].append(np.concatenate([T_map, np.tile(np.eye(4), (unused, 1, 1))]))
        T_init.append(T0)
    return PreparedPairs(**out, T_init=np.stack(T_init))


def _cache_keys(seq, frames, preprocess, config, pca, backbone) -> tuple[str, str]:
    """Keys of a window's prepared scans and of its pairs (which also depend on the scans):
    each hashes only the settings that change what it holds."""
    parts = {
        "sequence": str(seq.sequence_dir.resolve()),
        "frames": [frames.start, frames.stop],
        "preprocess": {k: getattr(preprocess, k) for k in PreprocessConfig.SCAN_FIELDS},
        "backbone": None if backbone is None else [backbone.name, backbone.options()],
    }
    h = hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode())
    # What the window reads, so that new files in the same folder (a sequence simulated
    # again, another ground truth) are not taken for the cached ones: the ground truth and
    # calibration by value, the scans and their point times by size and modification time.
    gt = seq.gt_poses_cam
    arrays = [seq.Tr_cam_velo, None if gt is None else gt[frames.start : frames.stop]]
    for a in [*arrays, *(pca if pca is not None else ())]:
        if a is not None:
            h.update(np.ascontiguousarray(a, np.float64).tobytes())
    files = [seq.scan_path(i) for i in frames]
    files += [t for t in map(seq._times_path, frames) if t.exists()]
    stats = [(p.name, p.stat()) for p in files]
    h.update(json.dumps([[name, st.st_size, st.st_mtime_ns] for name, st in stats]).encode())
    scan_key = h.hexdigest()[:16]
    pair_parts = {
        "num_candidates": config.gicp.num_candidates,
        **{k: getattr(config, k) for k in ("candidate_radius", "max_source_points", "seed",
                                           "map_scans", "map_stride")},
    }  # fmt: skip
    pair_key = hashlib.sha1(json.dumps([scan_key, pair_parts]).encode()).hexdigest()[:16]
    return scan_key, pair_key


def _save_scans(path: Path, w: PreparedWindow) -> None:
    arrays = {"gt_cam": w.gt_cam, "Tr_cam_velo": w.Tr_cam_velo}
    for k, scan in enumerate(w.scans):
        arrays |= {f"scan{k}_{name}": a for name, a in scan._asdict().items()}
    io.write_npz(path, name=np.array(w.name), **arrays)


def _load_scans(path: Path) -> PreparedWindow:
    with np.load(path, allow_pickle=False) as z:
        n = len(z["gt_cam"])
        scans = [PreparedScan(*(z[f"scan{k}_{a}"] for a in PreparedScan._fields)) for k in range(n)]
        return PreparedWindow(str(z["name"]), scans, z["gt_cam"], z["Tr_cam_velo"])


def _save_pairs(path: Path, p: PreparedPairs) -> None:
    arrays = {f"pair{k}_{a}": getattr(p, a)[k] for a in _PER_PAIR for k in range(len(p.rows))}
    io.write_npz(path, T_init=p.T_init, **arrays)


def _load_pairs(path: Path) -> PreparedPairs:
    with np.load(path, allow_pickle=False) as z:
        n = len(z["T_init"])
        per_pair = {a: [z[f"pair{k}_{a}"] for k in range(n)] for a in _PER_PAIR}
        return PreparedPairs(**per_pair, T_init=z["T_init"])


def open_sequences(
    root: str | Path | Sequence[str | Path], names: Sequence[str]
) -> list[io.KittiSequence]:
    """The sequences ``names`` of ``root``, or of each of several roots in turn (a one-line
    error for any that is missing)."""
    roots = [root] if isinstance(root, str | Path) else root
    return [io.KittiSequence(r, name) for r in roots for name in names]


def prepare_window(
    seq: io.KittiSequence,
    preprocess: PreprocessConfig,
    config: BatchConfig,
    pca: FeaturePCA | None = None,
    backbone: Backbone | None = None,
    *,
    frames: int | None = None,
    cache_dir: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> tuple[PreparedWindow, Path | None]:
    """The prepared first ``frames`` scans (all by default) of ``seq`` (:func:`prepare_scans`),
    read from or saved to ``cache_dir`` (atomically) when given; and where its pairs are cached
    (None without a cache)."""
    name = seq.sequence
    window = range(0, len(seq) if frames is None else min(frames, len(seq)))
    scan_path = pair_path = None
    if cache_dir is not None:
        scan_key, pair_key = _cache_keys(seq, window, preprocess, config, pca, backbone)
        scan_path = Path(cache_dir) / f"scans_{name}_{scan_key}.npz"
        pair_path = Path(cache_dir) / f"pairs_{name}_{pair_key}.npz"
        scan_path.parent.mkdir(parents=True, exist_ok=True)
    if scan_path is not None and scan_path.is_file():
        return _load_scans(scan_path), pair_path
    step = None if progress is None else partial(progress, name, len(window))
    w = prepare_scans(seq, window, preprocess, pca, backbone, step)
    if scan_path is not None:
        _save_scans(scan_path, w)
    return w, pair_path


def load_windows(
    root: str | Path | Sequence[str | Path],
    sequences: Sequence[str],
    preprocess: PreprocessConfig,
    config: BatchConfig,
    pca: FeaturePCA | None = None,
    backbone: Backbone | None = None,
    *,
    frames: int | None = None,
    cache_dir: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> BatchData:
    """Prepare the first ``frames`` scans (all by default) of each sequence under ``root`` (a
    root, or several: each sequence of each, in that order) and stack them (:func:`stack`).
    With ``cache_dir``, prepared scans and pairs are saved there (atomically, apart) and
    reused by later runs with the same settings and PCA."""
    windows = []
    for seq in open_sequences(root, sequences):
        w, pair_path = prepare_window(
            seq, preprocess, config, pca, backbone,
            frames=frames, cache_dir=cache_dir, progress=progress,
        )  # fmt: skip
        if pair_path is not None and pair_path.is_file():
            pairs = _load_pairs(pair_path)
        else:
            pairs = prepare_pairs(w, config)
            if pair_path is not None:
                _save_pairs(pair_path, pairs)
        windows.append((w, pairs))
    return stack(windows, config, preprocess.regularizer)


def stack(
    windows: list[tuple[PreparedWindow, PreparedPairs]],
    config: BatchConfig,
    regularizer: str = "plane",
) -> BatchData:
    """Pad and concatenate prepared windows into device arrays (float32, or float64 under
    x64): scans padded to the largest one's bucket, pairs to ``max_source_points``."""
    real = geo.real_dtype()
    all_scans = [s for w, _ in windows for s in w.scans]
    size = pc.bucket_size(max(len(s.points) for s in all_scans))
    P = max(len(r) for _, p in windows for r in p.rows)
    scan_cols = {key: [] for key in ScanSet._fields}
    pair_cols = {key: [] for key in PairBatch._fields}
    info, scan_offset, pair_offset = [], 0, 0
    for w, p in windows:
        for scan in w.scans:
            n_points = len(scan.points)
            padded = scan._replace(**{k: pc.pad(np.asarray(a), size)[0]
                                      for k, a in scan._asdict().items()})  # fmt: skip
            padded.values[n_points:] = 1.0  # padded rows: unit spheres, finite
            padded.vectors[n_points:] = np.eye(3)
            for k, a in padded._asdict().items():
                scan_cols[k].append(a)
            scan_cols["mask"].append(pc.pad(scan.points, size)[1])
        n = len(w.scans)
        for k in range(n - 1):
            rows, row_mask = pc.pad(p.rows[k].astype(np.int32), P)
            # Candidates as rows of the flattened scans: the map slot's scan, then the row.
            scan_of = scan_offset + p.map_scans[k][p.slots[k].astype(np.int64)]
            flat = (scan_of * size + p.candidates[k]).astype(np.int32)
            pair_cols["target"].append(scan_offset + k)
            pair_cols["source"].append(scan_offset + k + 1)
            pair_cols["rows"].append(rows)
            pair_cols["row_mask"].append(row_mask)
            pair_cols["candidates"].append(pc.pad(flat, P)[0])
            pair_cols["slots"].append(pc.pad(p.slots[k].astype(np.int32), P)[0])
            pair_cols["valid"].append(pc.pad(p.valid[k], P)[0])
            pair_cols["T_target_map"].append(p.T_map[k])
            pair_cols["T_init"].append(p.T_init[k])
        gt = np.asarray(w.gt_cam, np.float64)
        lengths = scaled_lengths(gt, config.segment_fractions, source=w.name)
        plan = segment_plan(gt, lengths, step=config.segment_step, source=w.name)
        info.append(Window(w.name, pair_offset, pair_offset + n - 1, gt, w.Tr_cam_velo, plan))
        scan_offset, pair_offset = scan_offset + n, pair_offset + n - 1
    if scan_offset * size >= 1 << 31:
        raise InputError(None, f"{scan_offset} scans of {size} rows overflow int32 row indices")
    scans = ScanSet(
        **{k: jnp.asarray(np.stack(v), None if k == "mask" else real)
           for k, v in scan_cols.items()}
    )  # fmt: skip
    floats = {"T_target_map", "T_init"}
    pairs = PairBatch(
        **{k: jnp.asarray(np.stack(v), real if k in floats else None) for k, v in pair_cols.items()}
    )
    return BatchData(scans, pairs, info, regularizer)
