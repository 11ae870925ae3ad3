"""Simulate the labelled scans that train and test the ``net`` backbone.

Training sequences 00-11 mix three scene styles, three sensors and several beam counts; the
held-out sequences 20-22 use seeds no training sequence uses (other worlds, same styles)::

    python scripts/simulate_backbone_data.py --out data/backbone

Reruns resume (the simulator skips finished frames).
"""

from __future__ import annotations

import argparse
import time

from gloam_jax.simulate import simulate

# (sequence, style, sensor, beams, columns, seed)
TRAIN = [
    ("00", "urban", "hdl64", 64, 1024, 101),
    ("01", "suburban", "hdl64", 64, 1024, 102),
    ("02", "highway", "hdl64", 64, 1024, 103),
    ("03", "urban", "vlp16", None, None, 104),
    ("04", "suburban", "os1-64", None, 1024, 105),
    ("05", "urban", "hdl64", 32, 1024, 106),
    ("06", "suburban", "hdl64", 32, 1024, 107),
    ("07", "highway", "os1-64", None, 1024, 108),
    ("08", "urban", "os1-64", None, 1024, 109),
    ("09", "suburban", "vlp16", None, None, 110),
    ("10", "urban", "hdl64", 64, 1024, 111),
    ("11", "highway", "hdl64", 32, 1024, 112),
]
HELD_OUT = [
    ("20", "urban", "hdl64", 64, 1024, 901),
    ("21", "suburban", "os1-64", None, 1024, 902),
    ("22", "highway", "hdl64", 64, 1024, 903),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="data/backbone")
    parser.add_argument("--frames", type=int, default=12)
    args = parser.parse_args()
    for seq, style, sensor, beams, columns, seed in TRAIN + HELD_OUT:
        t0 = time.perf_counter()
        simulate(args.out, frames=args.frames, sensor=sensor, style=style, seed=seed,
                 sequence=seq, num_beams=beams, num_columns=columns)  # fmt: skip
        print(f"{seq} {style} {sensor} beams={beams} seed={seed}: "
              f"{time.perf_counter() - t0:.0f} s", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
