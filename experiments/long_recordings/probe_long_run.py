"""A long simulated drive through `gloam run`: the cost of skipping damaged scans, and a run
killed (SIGKILL) at a random frame then resumed, against the uninterrupted run.

    python experiments/long_recordings/probe_long_run.py --frames 1000 --out RESULTS.json
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gloam_jax import io
from gloam_jax.simulate import simulate


def gloam_run(data: Path, out: Path, *args: str) -> subprocess.Popen:
    """``gloam run`` in a process of its own."""
    command = [sys.executable, "-m", "gloam_jax", "run", str(data), "--out", str(out), *args]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def finished(process: subprocess.Popen, out: Path) -> tuple[dict, np.ndarray, float]:
    """The metrics and LiDAR poses of a run that ends, and its wall time (s)."""
    start = time.monotonic()
    _, err = process.communicate()
    assert process.returncode == 0, err.decode()
    run = out / "latest"
    metrics = json.loads((run / "metrics.json").read_text())
    return metrics, io.read_kitti_poses(run / "00_poses_lidar_kitti.txt"), time.monotonic() - start


def killed_and_resumed(data: Path, out: Path, at: int) -> tuple[int, int, np.ndarray, dict]:
    """A run killed once ``at`` frames are written, then resumed: frames written at the
    kill, the checkpoint's size then (bytes), the final poses, the final metrics."""
    process = gloam_run(data, out)
    while process.poll() is None:
        runs = [p / "metrics.json" for p in out.glob("20*") if (p / "metrics.json").exists()]
        if runs and json.loads(runs[0].read_text())["frames_done"] >= at:
            break
        time.sleep(0.2)
    process.send_signal(signal.SIGKILL)
    process.wait()
    (run,) = out.glob("20*")
    done = json.loads((run / "metrics.json").read_text())["frames_done"]
    size = (run / "checkpoint.npz").stat().st_size
    resumed = subprocess.run([sys.executable, "-m", "gloam_jax", "run", str(data), "--resume",
                              str(run)], capture_output=True, text=True)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr
    metrics = json.loads((run / "metrics.json").read_text())
    return done, size, io.read_kitti_poses(run / "00_poses_lidar_kitti.txt"), metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--beams", type=int, default=32)
    parser.add_argument("--columns", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--damaged", type=int, default=10, help="scans damaged, spread evenly")
    parser.add_argument("--out", type=Path, required=True, help="results (JSON)")
    args = parser.parse_args()
    report: dict = {"args": {k: str(v) for k, v in vars(args).items()}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.monotonic()
        simulate(tmp / "sim", frames=args.frames, style="urban", seed=args.seed,
                 num_beams=args.beams, num_columns=args.columns)  # fmt: skip
        report["simulate_s"] = time.monotonic() - t0
        clean, reference, report["clean_run_s"] = finished(gloam_run(tmp / "sim", tmp / "clean"),
                                                           tmp / "clean")  # fmt: skip
        report["clean"] = {k: clean[k] for k in ("t_err_percent", "r_err_deg_per_100m")}
        report["clean"]["median_ms_per_frame"] = clean["median_ms_per_frame"]
        # Damaged scans: garbage of the right size (passes the up-front checks).
        shutil.copytree(tmp / "sim", tmp / "damaged")
        velodyne = tmp / "damaged" / "sequences" / "00" / "velodyne"
        damaged = np.linspace(0, args.frames, args.damaged + 2).round().astype(int)[1:-1]
        rng = np.random.default_rng(args.seed)
        for i in damaged:
            path = velodyne / f"{i:06d}.bin"
            path.write_bytes(rng.bytes(path.stat().st_size))
        skipped, _, _ = finished(gloam_run(tmp / "damaged", tmp / "skip", "--on-bad-scan", "skip"),
                                 tmp / "skip")  # fmt: skip
        assert skipped["skipped_frames"] == damaged.tolist(), skipped["skipped_frames"]
        report["skip"] = {
            "damaged_frames": damaged.tolist(),
            **{k: skipped[k] for k in ("t_err_percent", "r_err_deg_per_100m")},
        }
        report["skip"]["t_err_change_percent_of_clean"] = 100 * (
            skipped["t_err_percent"] / clean["t_err_percent"] - 1
        )
        at = random.Random(args.seed).randint(100, args.frames - 100)
        done, size, resumed, metrics = killed_and_resumed(tmp / "sim", tmp / "killed", at)
        after = np.linalg.norm(resumed[done:, :3, 3] - reference[done:, :3, 3], axis=1)
        report["kill"] = {"target_frame": at, "frames_written_at_kill": done,
                          "checkpoint_mib": size / 2**20,
                          "max_translation_difference_after_m": float(after.max()),
                          "max_translation_difference_m": float(np.abs(
                              resumed[:, :3, 3] - reference[:, :3, 3]).max()),
                          "t_err_percent": metrics["t_err_percent"]}  # fmt: skip
    io.write_atomic(args.out, json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
