"""Probe: what separates our GICP from small_gicp on scans without motion distortion.

    python experiments/undistorted_scans/probe_undistorted.py data/val_worlds --sequence 204 \\
        --frames 100 --out experiments/undistorted_scans/probe_undistorted_204

A diagnosis, not a feature (experiments/undistorted_scans/README.md). Every run sees the raw
scans without per-point times and our preprocessing where it can (0.5 m voxels, 3-100 m crop,
no deskew unless the name says ``auto``):

* ``sg_vgicp_every``: small_gicp's odometry of bench_odometry.py (VGICP to a Gaussian voxel map
  of 1 m, every frame inserted, LRU horizon 100) on those scans;
* ``sg_vgicp_keyframes``: the same map fed only keyframes 1 m apart;
* ``sg_gicp_points``: small_gicp's GICP to a point map of the last 20 keyframes, as ours has
  (covariances from 10 neighbours in the merged map);
* ``ours_off``: ``gicp.yaml`` with deskew off;
* ``ours_voxels_nearest_off`` / ``ours_voxels_off`` / ``ours_voxels_auto``: ours with the local
  map replaced, in this process only, by small_gicp's: keyframes of 1 cm (every frame), the
  last 100 merged into 1 m voxels, each the mean of its points and of their covariances; each
  source point is paired with the nearest voxel mean, or (as VGICP does) with the voxel it
  falls in, within the correspondence distance;
* ``ours_voxels_keyframes_auto``: that voxel map (VGICP's pairing) built from ``gicp.yaml``'s
  own keyframes (1 m apart, the last 20), with its deskew.

Scores: devkit t_err (%) / r_err (deg/100 m) over 10-80 % of the window's path. ``OUT.json``
is rewritten atomically after each run (a killed probe resumes); ``OUT.md`` is the table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))  # the user tools it uses

import numpy as np  # noqa: E402
from bench_odometry import _CompileCounter, run_ours  # noqa: E402
from compare_peers import RawScans, score  # noqa: E402
from make_tables import commit  # noqa: E402

from gloam_jax import covariance as cov  # noqa: E402
from gloam_jax import io  # noqa: E402
from gloam_jax import odometry as odo  # noqa: E402
from gloam_jax import pointcloud as pc  # noqa: E402
from gloam_jax.config import build_dataclass, load_config  # noqa: E402
from gloam_jax.io.files import write_atomic  # noqa: E402
from gloam_jax.neighbors import KdTree  # noqa: E402
from gloam_jax.registration import PreparedCloud  # noqa: E402

VOXEL = 1.0  # m, small_gicp's GaussianVoxelMap resolution in bench_odometry.py


def _voxel_keys(points: np.ndarray) -> np.ndarray:
    """One int64 per 1 m voxel (21 bits an axis, as small_gicp's voxel grid)."""
    k = np.floor(points / VOXEL).astype(np.int64) + (1 << 20)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


class VoxelLookup:
    """KdTree's query for k = 1, answered by the voxel each query falls in (VGICP's rule)."""

    def __init__(self, keys: np.ndarray, means: np.ndarray) -> None:
        self.keys, self.points = keys, means

    def __len__(self) -> int:
        return len(self.keys)

    def query(self, queries: np.ndarray, k: int, max_distance: float = np.inf):
        assert k == 1, "VGICP pairs each point with one voxel"
        key = _voxel_keys(np.asarray(queries[:, :3], np.float64))
        i = np.clip(np.searchsorted(self.keys, key), 0, len(self.keys) - 1)
        d2 = np.sum((self.points[i] - queries[:, :3]) ** 2, axis=1)
        found = (self.keys[i] == key) & (d2 <= max_distance**2)
        return np.where(found, i, 0).astype(np.int32)[:, None], found[:, None]


def _gaussian_voxels(keyframes: list[dict], nearest: bool) -> PreparedCloud:
    points = np.concatenate([f["points"] for f in keyframes])
    covs = np.concatenate([f["covs"] for f in keyframes])
    means, covs = pc.voxel_means(points, VOXEL, [points, covs])
    # A voxel's mean lies in the voxel, so it gives the voxel's key; sorted for the lookup.
    keys = _voxel_keys(means)
    order = np.argsort(keys)
    keys, means, covs = keys[order], means[order], covs[order]
    normals, planarity = (np.asarray(a, np.float64) for a in cov.surface(*np.linalg.eigh(covs)))
    tree = KdTree(means, "voxel map") if nearest else VoxelLookup(keys, means)
    return PreparedCloud(means, covs, tree, None, normals=normals, planarity=planarity)


class _MapRows:
    """LocalMap.size for the voxel map: its padded rows follow the voxel count."""

    def __get__(self, local_map, owner=None) -> int:
        cloud = local_map.cloud
        return 0 if cloud is None else pc.bucket_size(int(1.2 * len(cloud.points)))

    def __set__(self, local_map, value) -> None:
        pass  # LocalMap.add sizes a keyframe map; the voxel map sizes itself


@contextlib.contextmanager
def voxel_map(nearest: bool):
    """The odometry's local map as Gaussian voxels, while the block runs."""
    merge, size = odo._merge, odo.LocalMap.__dict__.get("size")
    odo._merge = lambda keyframes, _size: _gaussian_voxels(keyframes, nearest)
    odo.LocalMap.size = _MapRows()
    try:
        yield
    finally:
        odo._merge = merge
        if size is None:
            del odo.LocalMap.size
        else:
            odo.LocalMap.size = size


def _scans(raw: RawScans, n: int):
    """small_gicp's prepared scans, cropped and downsampled as ``gicp.yaml`` has it."""
    import small_gicp

    prep = load_config("gicp").preprocess
    for i in range(n):
        points = raw.scan(i)[:, :3].astype(np.float64)
        points = pc.crop_range(points, prep.min_range, prep.max_range)
        yield small_gicp.preprocess_points(points, prep.downsampling_resolution, num_threads=2)[0]


def _moved(last: np.ndarray | None, T: np.ndarray) -> bool:
    return last is None or np.linalg.norm((np.linalg.inv(last) @ T)[:3, 3]) > 1.0


def run_small_gicp(raw: RawScans, n: int, target: str):
    import small_gicp

    T, T_last_current, last, keyframes, poses = np.eye(4), np.eye(4), None, [], []
    voxelmap = small_gicp.GaussianVoxelMap(VOXEL)
    voxelmap.set_lru(horizon=100, clear_cycle=10)
    for down in _scans(raw, n):
        guess = T @ T_last_current
        if target == "points" and keyframes:
            cloud = small_gicp.PointCloud(np.concatenate(keyframes))
            tree = small_gicp.KdTree(cloud, num_threads=2)
            small_gicp.estimate_covariances(cloud, tree, num_neighbors=10, num_threads=2)
            T_new = small_gicp.align(cloud, down, tree, guess, num_threads=2).T_target_source
        elif target != "points" and voxelmap.size() > 0:
            T_new = small_gicp.align(voxelmap, down, guess, num_threads=2).T_target_source
        else:
            T_new = T
        T_last_current, T = np.linalg.inv(T) @ T_new, T_new
        if target == "every" or _moved(last, T):
            last = T.copy()
            if target == "points":
                keyframes = [*keyframes, down.points()[:, :3] @ T[:3, :3].T + T[:3, 3]][-20:]
            else:
                voxelmap.insert(down, T)
        poses.append(T.copy())
    return np.stack(poses), [float("nan")] * n, {}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--sequence", required=True)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--runs", default=None, help="comma-separated names (default: all)")
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.json and OUT.md")
    args = parser.parse_args()

    seq = io.KittiSequence(args.data, args.sequence)
    raw, n = RawScans(seq), min(args.frames, len(seq))
    base = load_config("gicp")
    every = {"keyframe_distance": 0.01, "max_keyframes": 100}
    ours = {
        "ours_off": ({"preprocess": {"deskew": "off"}}, None),
        "ours_voxels_nearest_off": ({**every, "preprocess": {"deskew": "off"}}, True),
        "ours_voxels_off": ({**every, "preprocess": {"deskew": "off"}}, False),
        "ours_voxels_auto": (every, False),
        "ours_voxels_keyframes_auto": ({}, False),
    }
    runs = ["sg_vgicp_every", "sg_vgicp_keyframes", "sg_gicp_points", *ours]
    if args.runs is not None:
        unknown = set(args.runs.split(",")) - set(runs)
        if unknown:
            raise SystemExit(f"unknown runs {sorted(unknown)}; known: {runs}")
        runs = args.runs.split(",")
    chosen = "" if args.runs is None else f" --runs {args.runs}"
    script = "experiments/undistorted_scans/probe_undistorted.py"
    command = f"python {script} {args.data} --sequence {args.sequence}"
    meta = {"command": f"{command} --frames {n}{chosen} --out {args.out}", "commit": commit()}
    json_path = args.out.with_suffix(".json")
    results = json.loads(json_path.read_text())["results"] if json_path.exists() else {}
    for name in runs:
        if name in results:
            continue
        if name.startswith("sg_"):
            out = run_small_gicp(raw, n, name.rsplit("_", 1)[1])
        else:
            changes, nearest = ours[name]
            config = build_dataclass(type(base), changes, name, base=base)
            with voxel_map(nearest) if nearest is not None else contextlib.nullcontext():
                out = run_ours(raw, n, config, None, _CompileCounter())
        results[name] = {k: v for k, v in score(seq, *out).items() if "ms" not in k}
        print(name, json.dumps(results[name]), flush=True)
        write_atomic(json_path, json.dumps({**meta, "results": results}, indent=1))
    lines = [f"`{meta['command']}` at `{meta['commit']}`; t_err (%) / r_err (deg/100 m).", "",
             "| run | t_err / r_err |", "|---|---|"]  # fmt: skip
    lines += [f"| {k} | {v['t_err']:.3f} / {v['r_err']:.3f} |" for k, v in results.items()]
    write_atomic(args.out.with_suffix(".md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
