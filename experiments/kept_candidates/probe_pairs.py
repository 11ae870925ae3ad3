"""PLAN.md's pairs: each config against its kept-candidates twin on the same long drives.

    python experiments/kept_candidates/probe_pairs.py --out results/kept_candidates

Runs ``gloam run`` once per (draw, world, config) into OUT (a run already there is kept, so a
killed probe resumes) and writes ``pairs.json`` / ``pairs.md`` beside this file.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np

from gloam_jax import io

HERE = Path(__file__).resolve().parent
DRAWS = {"d0": Path("data/long"), "d1": Path("data/long_d1")}
PAIRS = {  # config -> its twin, and the worlds they run
    "configs/gicp.yaml": (HERE / "gicp_kept.yaml", ("401", "403", "404")),
    "configs/gloam.yaml": (HERE / "gloam_kept.yaml", ("403",)),
}


def run(data: Path, world: str, config: Path, out: Path) -> Path:
    if not (out / "latest" / "metrics.json").is_file():
        cmd = ["gloam", "run", str(data), "--sequence", world, "--config", str(config),
               "--out", str(out)]  # fmt: skip
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out / "latest"


def summary(run_dir: Path, world: str) -> dict:
    m = json.loads((run_dir / "metrics.json").read_text())
    frames = json.loads((run_dir / "frames.json").read_text())
    return {
        "t_err": m["t_err_percent"],
        "r_err": m["r_err_deg_per_100m"],
        "queries": float(np.mean([f["queries"] for f in frames[2:]])),
        "degenerate": m["degenerate_frames"],
        "frames": len(frames),
        "poses": io.read_kitti_poses(run_dir / f"{world}_poses_kitti.txt"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/kept_candidates"))
    args = parser.parse_args()
    rows = []
    for config, (twin, worlds) in PAIRS.items():
        for world in worlds:
            for draw, data in DRAWS.items():
                a, b = (
                    summary(run(data, world, c, args.out / Path(c).stem / draw / world), world)
                    for c in (Path(config), twin)
                )
                moved = np.linalg.norm(a.pop("poses")[:, :3, 3] - b.pop("poses")[:, :3, 3], axis=1)
                rows.append({"config": Path(config).stem, "world": world, "draw": draw,
                             "every_round": a, "kept": b, "largest_pose_difference_m":
                             float(moved.max())})  # fmt: skip
                print(json.dumps(rows[-1]), flush=True)
    io.write_atomic(HERE / "pairs.json", json.dumps(rows, indent=2))
    lines = [
        "| config | world, draw | t_err (%) every round / kept | change | queries a frame "
        "| degenerate frames | largest pose difference (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a, b = r["every_round"], r["kept"]
        lines.append(
            f"| {r['config']} | {r['world']} {r['draw']} | {a['t_err']:.4f} / {b['t_err']:.4f} | "
            f"{100 * (b['t_err'] / a['t_err'] - 1):+.2f} % | {a['queries']:.2f} / "
            f"{b['queries']:.2f} | {a['degenerate']} / {b['degenerate']} | "
            f"{r['largest_pose_difference_m']:.4f} |"
        )
    io.write_atomic(HERE / "pairs.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
