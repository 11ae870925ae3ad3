"""Per-frame rotation error of each run on long validation cells (default: the VLP-16 worlds):
its mean (a bias that drifts) and spread (noise that does not add up), about each camera axis
(``gloam_jax.metrics.frame_rotation_drift``), beside each run's t_err; a table and a scatter.

KITTI's scored poses are camera-0 poses (x right, y down, z forward): x is pitch, y yaw, z roll.
Reads make_tables' runs under OUT; writes NAME.md and NAME.png next to this script.

    python experiments/vlp16_drawn/pitch_bias.py results/vlp16_model
    python experiments/vlp16_drawn/pitch_bias.py results/vlp16_fresh --draws long_d2,long_d4 \
        --name ../vlp16_fresh/pitch_bias
    python experiments/vlp16_drawn/pitch_bias.py results/grid_fresh_d2 --draws long_d2,long_d3 \
        --worlds 401,403,404 --name hdl64_pitch
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gloam_jax.io import read_kitti_poses  # noqa: E402
from gloam_jax.metrics import frame_rotation_drift  # noqa: E402


def runs(out: Path, draws: list[str], worlds: list[str]):
    """(cell, run name, drift dict, t_err %) of every scored run under ``out``."""
    labels = sorted(p.name for p in out.iterdir() if p.is_dir())
    for world in worlds:
        for draw in draws:
            for label in (x for x in labels if x == "GICP" or x.startswith("GLOAM")):
                for run in map(Path, sorted(glob.glob(f"{out}/{label}/*/{draw}-*/{world}"))):
                    metrics = run / "metrics.json"
                    scored = json.loads(metrics.read_text()) if metrics.is_file() else {}
                    if "t_err_percent" not in scored:  # not finished, or not scored yet
                        continue
                    drift = frame_rotation_drift(
                        read_kitti_poses(run / f"{world}_gt_kitti.txt"),
                        read_kitti_poses(run / f"{world}_poses_kitti.txt"),
                    )
                    model = run.parent.parent.name
                    name = label if model == "-" else f"{label} {model}"
                    yield f"{world} {draw}", name, drift, scored["t_err_percent"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="make_tables' --out")
    parser.add_argument("--draws", default="long,long_d1", help="data folders (draws)")
    parser.add_argument("--name", default="pitch_bias", help="output stem, beside this script")
    parser.add_argument("--worlds", default="402,406,407,408", help="world ids")
    args = parser.parse_args()
    rows = list(runs(args.out, args.draws.split(","), args.worlds.split(",")))
    lines = [
        f"Per-frame rotation error on long validation worlds {args.worlds} ({args.out}): mean and "
        "sample std, millidegrees a frame; pitch is about camera x.",
        "",
        "| cell | run | pitch mean | yaw mean | roll mean | pitch std | t_err (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    for cell, name, d, t_err in rows:
        m, s = d["mean_mdeg"], d["std_mdeg"]
        lines.append(
            f"| {cell} | {name} | {m[0]:+.2f} | {m[1]:+.2f} | {m[2]:+.2f} | {s[0]:.1f} "
            f"| {t_err:.3f} |"
        )
    pitch = np.array([abs(d["mean_mdeg"][0]) for _, _, d, _ in rows])
    t_err = np.array([t for *_, t in rows])
    r = float(np.corrcoef(pitch, t_err)[0, 1])
    # Within each cell (world and draw), against GICP's run there: does a model that adds pitch
    # bias lose? Pooled over cells, the correlation also carries how hard each world is.
    gicp = {cell: (abs(d["mean_mdeg"][0]), t) for cell, name, d, t in rows if name == "GICP"}
    pairs = np.array([(abs(d["mean_mdeg"][0]) - gicp[c][0], t / gicp[c][1])
                      for c, name, d, t in rows if name != "GICP" and c in gicp])  # fmt: skip
    r_cell = float(np.corrcoef(pairs[:, 0], pairs[:, 1])[0, 1])
    lines += [
        "",
        f"Correlation of |pitch mean| and t_err over {len(rows)} runs: {r:.3f}",
        f"Within each cell, of the change in |pitch mean| against GICP's and the t_err ratio to "
        f"GICP's, over {len(pairs)} model runs: {r_cell:.3f}",
    ]
    stem = Path(__file__).parent / args.name
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for group in ("GICP", "GLOAM"):
        pick = [i for i, (_, n, _, _) in enumerate(rows) if n.startswith(group)]
        ax.scatter(pitch[pick], t_err[pick], s=14, label=group)
    ax.set_xlabel("|mean pitch error| (mdeg a frame)")
    ax.set_ylabel("t_err (%)")
    ax.set_title(f"worlds {args.worlds}: t_err against the pitch bias (r = {r:.2f})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(stem.with_suffix(".png"), dpi=110)
    print("\n".join(lines[-2:]))


if __name__ == "__main__":
    main()
