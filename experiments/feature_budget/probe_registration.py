"""A learned method's registration with its features served from memory, against the same run
computing them live: what the frame costs apart from the backbone (issue 42, item 1).

    python experiments/feature_budget/probe_registration.py data/long 403 300 \
        --out experiments/feature_budget/registration.json
"""

import argparse
import json
from pathlib import Path

from gloam_jax import pipeline
from gloam_jax.config import load_config
from gloam_jax.datasets import open_dataset


def memo_backbone(dataset, frames):
    """pipeline._backbone, with every frame's features computed before the run."""
    live = pipeline._backbone

    def backbone(odometry, features_dir):
        inner = live(odometry, features_dir)
        if inner is None:
            return None
        ready = {i: inner(dataset.frame(i)[0], frame=i) for i in frames}

        class Ready:
            name = inner.name
            options = inner.options
            fitted_intensity = inner.fitted_intensity

            def __call__(self, scan, *, path=None, frame=None):
                return ready[frame]

        return Ready()

    return backbone


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root")
    parser.add_argument("sequence")
    parser.add_argument("frames", type=int)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--runs", default="gicp:live,gloam:ready,gloam:live")
    args = parser.parse_args()
    dataset = open_dataset(args.root, args.sequence)
    frames = pipeline.select_frames(len(dataset), 0, args.frames)
    live, results = pipeline._backbone, {}
    for run in args.runs.split(","):
        method, features = run.split(":")
        pipeline._backbone = live if features == "live" else memo_backbone(dataset, frames)
        m = pipeline.run_dataset(dataset, load_config(method), f"runs/feature_budget/{method}_"
                                 f"{features}", frames)  # fmt: skip
        results[run] = {
            "t_err_percent": m["t_err_percent"],
            "median_ms_per_frame": m["median_ms_per_frame"],
            "median_ms_features": m.get("median_ms_features"),
            "stage_ms": {k: v["median"] for k, v in m["stage_ms"].items()},
        }
        print(run, json.dumps(results[run]))
    pipeline._backbone = live
    args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
