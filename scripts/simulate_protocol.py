"""Simulate the training/test protocol: one window per KITTI sequence 00-10, in the KITTI
layout, along the real ground-truth trajectories (see gloam_jax.training.protocol).

    python scripts/simulate_protocol.py --out data/protocol [--frames 120] [--sequences 01,03]
    python scripts/simulate_protocol.py --out data/protocol --sequences 31,33,35,37,39

Ids 31-39 are second windows of the training sequences (EXTRA_TRAINING_WINDOWS).

Resumable: a sequence already complete is skipped, an interrupted one continues.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from gloam_jax.simulate import simulate
from gloam_jax.training.protocol import (
    DEFAULT_FRAMES,
    EXTRA_TRAINING_WINDOWS,
    TEST_SEQUENCES,
    TRAIN_SEQUENCES,
    WINDOWS,
)

POSES = Path(__file__).resolve().parents[2] / "shared/data/kitti_gt_poses"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("data/protocol"))
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES)
    parser.add_argument("--poses", type=Path, default=POSES, help="KITTI ground-truth poses")
    parser.add_argument("--sequences", default=",".join(TRAIN_SEQUENCES + TEST_SEQUENCES))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for name in args.sequences.split(","):
        kitti, window = EXTRA_TRAINING_WINDOWS.get(name, (name, WINDOWS.get(name)))
        if window is None:
            raise SystemExit(f"no protocol window for sequence {name!r}")
        t0 = time.perf_counter()
        simulate(
            args.out,
            trajectory=args.poses / f"{kitti}.txt",
            start=window.start,
            frames=args.frames,
            style=window.style,
            seed=args.seed + int(name),
            sequence=name,
        )
        print(
            f"{name} ({window.style}, from pose {window.start}): {time.perf_counter() - t0:.1f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
