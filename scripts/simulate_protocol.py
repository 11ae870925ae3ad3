"""Simulate the training/test protocol in the KITTI layout, along the real ground-truth
trajectories (see gloam_jax.training.protocol).

Without --split: one window per KITTI sequence 00-10, in a scene style like the sequence's
(ids 31-39 are second windows of the training sequences, EXTRA_TRAINING_WINDOWS):

    python scripts/simulate_protocol.py --out data/protocol [--frames 120] [--sequences 01,03]
    python scripts/simulate_protocol.py --out data/protocol --sequences 31,33,35,37,39
    python scripts/simulate_protocol.py --out data/protocol_vlp16 --sensor vlp16   # another sensor

With --split train|val|test: that split's worlds (SPLITS), each a scene family, sensor,
distortion and speed drawn from its id, recorded in sequences/NNN/world.json; val_long and
test_long are the KITTI-length drives (1000 frames, or to the trajectory's end):

    python scripts/simulate_protocol.py --out data/protocol2 --split val [--sequences 201,203]
    python scripts/simulate_protocol.py --out data/long --split val_long

Resumable: a sequence already complete is skipped, an interrupted one continues (each file
is written atomically).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from gloam_jax.io import read_kitti_poses
from gloam_jax.simulate import SENSORS, simulate
from gloam_jax.training.protocol import (
    DEFAULT_FRAMES,
    EXTRA_TRAINING_WINDOWS,
    LONG_FRAMES,
    SPLITS,
    TEST_SEQUENCES,
    TRAIN_SEQUENCES,
    WINDOWS,
    WORLD_FRAMES,
    world_spec,
)

POSES = Path(__file__).resolve().parents[2] / "shared/data/kitti_gt_poses"


def simulate_windows(args: argparse.Namespace) -> None:
    names = args.sequences or ",".join(TRAIN_SEQUENCES + TEST_SEQUENCES)
    for name in names.split(","):
        kitti, window = EXTRA_TRAINING_WINDOWS.get(name, (name, WINDOWS.get(name)))
        if window is None:
            raise SystemExit(f"no protocol window for sequence {name!r}")
        t0 = time.perf_counter()
        simulate(
            args.out,
            trajectory=args.poses / f"{kitti}.txt",
            start=window.start,
            frames=args.frames or DEFAULT_FRAMES,
            style=window.style,
            sensor=args.sensor,  # None: simulate's default, the HDL-64
            seed=args.seed + int(name),
            sequence=name,
        )
        print(
            f"{name} ({window.style}, {args.sensor or 'hdl64'}, from pose {window.start}): "
            f"{time.perf_counter() - t0:.1f} s",
            flush=True,
        )


def simulate_split(args: argparse.Namespace) -> None:
    worlds = SPLITS[args.split]
    if args.sequences:
        wanted = args.sequences.split(",")
        unknown = sorted(set(wanted) - {w.sequence for w in worlds})
        if unknown:
            raise SystemExit(f"not in the {args.split} split: {', '.join(unknown)}")
        worlds = tuple(w for w in worlds if w.sequence in wanted)
    for world in worlds:
        poses = args.poses / f"{world.trajectory}.txt"
        if not poses.is_file():
            raise SystemExit(f"{poses}: no such KITTI pose file (--poses)")
        positions = read_kitti_poses(poses)[:, :3, 3]
        spec = world_spec(world, args.frames, args.seed, positions=positions)
        t0 = time.perf_counter()
        simulate(
            args.out,
            world=spec,
            trajectory=poses,
            sequence=world.sequence,
        )
        print(
            f"{world.sequence} ({args.split}: {world.family}, {spec.sensor.name}, KITTI "
            f"{world.trajectory} from pose {world.start}, {spec.frames} frames at "
            f"{spec.speed_scale:g}x speed, "
            f"distortion {'on' if spec.motion_distortion else 'off'}): "
            f"{time.perf_counter() - t0:.1f} s",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("data/protocol"))
    parser.add_argument("--split", choices=tuple(SPLITS), help="simulate this split's worlds")
    frames = f"default {DEFAULT_FRAMES}; a split's worlds {WORLD_FRAMES}, long ones {LONG_FRAMES}"
    parser.add_argument("--frames", type=int, help=f"{frames} or to the trajectory's end")
    parser.add_argument("--poses", type=Path, default=POSES, help="KITTI ground-truth poses")
    parser.add_argument("--sequences", help="only these ids (comma-separated)")
    parser.add_argument("--seed", type=int, default=0, help="added to every sequence's seed")
    parser.add_argument(
        "--sensor", choices=tuple(SENSORS),
        help="the windows' sensor (default hdl64); not with --split: its worlds draw their own",
    )  # fmt: skip
    args = parser.parse_args()
    if args.split is not None and args.sensor is not None:
        parser.error("--sensor is for the windows; a split's worlds draw their own sensor")
    if args.split is None:
        simulate_windows(args)
    else:
        simulate_split(args)


if __name__ == "__main__":
    main()
