"""Our GICP against small_gicp, KISS-ICP and GenZ-ICP on the same raw scans, in one run.

    python scripts/compare_peers.py data/val_worlds --sequences 201,202 --out results/peers_val \\
        [--methods gicp,small_gicp,kiss-icp,genz-icp] [--frames 100] \\
        [--variant 'voxel025={preprocess: {downsampling_resolution: 0.25}}']

Every method gets the scans as a raw KITTI drive gives them: motion-distorted where the world
was simulated so, and **without per-point times** (the simulator's ``timestamps/`` are not
read), so each method deskews, if at all, from the azimuth. ``gicp`` is
``configs/gicp.yaml`` through :func:`bench_odometry.run_ours` (deskew ``auto`` -> azimuth on
the KITTI layout); ``--variant NAME=YAML`` adds a run of ``gicp.yaml`` with those settings
replaced (one candidate change at a time). small_gicp and KISS-ICP run as in
``bench_odometry.py``; GenZ-ICP with its default configuration and deskew on (azimuth times in
[0, 1], like KISS-ICP), and ``genz-icp-kitti`` with the KITTI preset it ships.

Scores: the devkit's t_err (%) and r_err (deg/100 m) over segments of 10-80 % of each window's
path (``make_tables.window_rte``: the windows are shorter than 100-800 m) or, with ``--devkit``
(the long splits), over the devkit's own 100-800 m segments; and the median milliseconds per
frame. ``OUT.json`` holds every run and is rewritten atomically after each,
so a killed run continues where it stopped; ``OUT.md`` is the table with the command and
commit.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from bench_odometry import PEERS, _CompileCounter, missing_peer, peer_modules, run_ours
from make_tables import commit, machine, window_rte

from gloam_jax import io
from gloam_jax.config import build_dataclass, load_config, parse_mapping
from gloam_jax.errors import InputError


class RawScans:
    """A KITTI sequence seen as raw KITTI gives it: scans and frame times, no per-point times."""

    def __init__(self, seq: io.KittiSequence) -> None:
        self.seq = seq
        self.times = seq.times
        # where run_ours opens the drive to choose the model from its first scans
        self.root, self.sequence = seq.root, seq.sequence

    def scan(self, i: int) -> np.ndarray:
        return self.seq.scan(i)

    def scan_path(self, i: int) -> Path:
        return self.seq.scan_path(i)

    def point_times(self, i: int) -> None:
        return None


def parse_variants(items: list[str]) -> dict[str, dict]:
    """``NAME=YAML`` -> {NAME: settings mapping}; a bad one is a SystemExit line."""
    variants = {}
    for item in items:
        name, _, text = item.partition("=")
        values = parse_mapping(text) if text else None
        if not name or values is None:
            raise SystemExit(f"--variant {item!r}: expected NAME=YAML mapping")
        variants[name] = values
    return variants


def score(
    seq: io.KittiSequence, poses: np.ndarray, ms: list[float], extra: dict, devkit: bool
) -> dict:
    est = io.lidar_to_cam_poses(np.linalg.inv(poses[0]) @ poses, seq.Tr_cam_velo)
    rte = window_rte(seq.gt_poses_cam[: len(est)], est, devkit=devkit)
    return {
        "t_err": rte["t_err"],
        "r_err": rte["r_err"],
        "t_err_by_length": rte["t_err_by_length"],
        "median_ms_per_frame": float(np.median(ms)),
        "frames": len(est),
        **extra,
    }


def world_label(data: Path, name: str) -> str:
    path = data / "sequences" / name / "world.json"
    if not path.is_file():
        return name
    w = json.loads(path.read_text())
    distortion = "distorted" if w.get("motion_distortion") else "undistorted"
    return f"{name} {w['family']} {w['sensor']['name']} {distortion}"


def table(results: dict, data: Path) -> str:
    """Worlds by methods (every one measured so far, in the order first run)."""
    worlds = sorted({k.split("/")[0] for k in results})
    methods = list(dict.fromkeys(k.split("/")[1] for k in results))
    head = ["world", *methods]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for w in worlds:
        cells = []
        for m in methods:
            r = results.get(f"{w}/{m}")
            cells.append(
                "-" if r is None
                else f"{r['t_err']:.3f} / {r['r_err']:.3f} / {r['median_ms_per_frame']:.0f}"
            )  # fmt: skip
        lines.append(f"| {world_label(data, w)} | " + " | ".join(cells) + " |")
    means = []
    for m in methods:
        rows = [results[f"{w}/{m}"] for w in worlds if f"{w}/{m}" in results]
        full = len(rows) == len(worlds)
        means.append(
            f"{np.mean([r['t_err'] for r in rows]):.3f} / {np.mean([r['r_err'] for r in rows]):.3f}"
            f" / {np.mean([r['median_ms_per_frame'] for r in rows]):.0f}"
            if full
            else "-"
        )
    lines.append("| mean | " + " | ".join(means) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--sequences", required=True, help="comma-separated ids")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--methods", default="gicp," + ",".join(PEERS))
    parser.add_argument("--variant", action="append", default=[], help="NAME=YAML over gicp.yaml")
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.json and OUT.md")
    parser.add_argument("--devkit", action="store_true", help="score 100-800 m (long splits)")
    args = parser.parse_args()
    variants = parse_variants(args.variant)
    methods = [*args.methods.split(","), *variants]
    # Checked before any run: a sitting over several drives takes hours.
    if unknown := [m for m in methods if m not in PEERS and m != "gicp" and m not in variants]:
        parser.error(f"unknown method {unknown[0]!r}: gicp, a peer ({', '.join(PEERS)}) or a "
                     "--variant name")  # fmt: skip
    if clash := [v for v in variants if v in PEERS or v == "gicp"]:
        parser.error(f"--variant {clash[0]!r}: the name of a method; choose another")
    if (problem := missing_peer(methods)) is not None:
        parser.error(problem)

    import jax

    counter = _CompileCounter()
    logging.getLogger("jax").addHandler(counter)
    jax.config.update("jax_log_compiles", True)
    logging.getLogger("jax").setLevel(logging.WARNING)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))

    json_path, md_path = args.out.with_suffix(".json"), args.out.with_suffix(".md")
    saved = json.loads(json_path.read_text()) if json_path.exists() else {}
    if saved and saved.get("devkit", False) != args.devkit:
        raise SystemExit(f"{json_path}: scored with another --devkit setting; choose another --out")
    results = saved.get("results", {})
    base = load_config("gicp")
    # Every variant is built before any run, so a bad setting stops at once, not hours in.
    try:
        configs = {m: build_dataclass(type(base), v, m, base=base) for m, v in variants.items()}
    except InputError as e:
        raise SystemExit(f"--variant: {e}") from None
    for name in args.sequences.split(","):
        seq = io.KittiSequence(args.data, name)
        raw = RawScans(seq)
        n = len(seq) if args.frames is None else min(args.frames, len(seq))
        for method in methods:
            key = f"{name}/{method}"
            if key in results:  # resume: keep what an earlier run measured
                continue
            if method in PEERS:
                out = PEERS[method].run(raw, n, args.threads)
            else:
                out = run_ours(raw, n, configs.get(method, base), None, counter)
            results[key] = score(seq, *out, devkit=args.devkit)
            print(key, json.dumps(results[key]), flush=True)
            record = {
                "command": "python " + " ".join(sys.argv),
                "commit": commit(),
                "machine": machine(peer_modules(methods)),
                "date": datetime.now(UTC).isoformat(timespec="seconds"),
                "variants": variants,
                "devkit": args.devkit,
                "results": results,
            }
            io.write_atomic(json_path, json.dumps(record, indent=2))
    text = table(results, args.data)
    print(text)
    header = (
        f"Measured by `python {' '.join(sys.argv)}` at `{commit()}`, "
        f"{datetime.now(UTC):%Y-%m-%d}. Cells: t_err (%) / r_err (deg/100 m) / median ms "
        "per frame, devkit rule over "
        + ("its own 100-800 m segments" if args.devkit else "10-80 % of each window's path")
        + "; raw scans without per-point times.\n\n"
    )
    io.write_atomic(md_path, header + text + "\n")


if __name__ == "__main__":
    main()
