"""Batch evaluation throughput: the same registrations vmapped at once and one at a time.

    python scripts/bench_batch.py --config configs/train_tpe.yaml --out docs/bench_batch.json

Prepares the training windows of the config (cached with ``--cache``), then registers every
pair (a) all at once, ``jit(vmap(register_pair))``, and (b) in a Python loop over the same
jitted single-pair function, with the same candidate sets, rounds and model. Both are timed
after compilation, best of ``--repeats``; the estimates must agree. Prints registrations/s.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import jax
import numpy as np

from gloam_jax import batch
from gloam_jax.config import load_config
from gloam_jax.io import write_atomic
from gloam_jax.models import learned_parts
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.problem import setup


def best_of(repeats: int, fn, *args) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("configs/train_tpe.yaml"))
    parser.add_argument("--run", type=Path, default=Path("runs/bench_batch"))
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--methods", default="gicp,gloam")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    cfg = load_config(args.config, TrainConfig)
    problem = setup(cfg, args.run, cache_dir=args.cache)
    data, config = problem.data, dataclasses.replace(cfg.batch, association="hard")
    batched = jax.jit(lambda lp: batch.register_pairs(lp, data.scans, data.pairs, config))
    one = jax.jit(lambda lp, pair: batch.register_pair(lp, data.scans, pair, config))
    pairs = [jax.tree_util.tree_map(lambda x, b=b: x[b], data.pairs) for b in range(data.num_pairs)]

    def loop(learned):
        return [one(learned, p) for p in pairs]

    rows = []
    for method in args.methods.split(","):
        learned = learned_parts(problem.model, method)
        jax.block_until_ready(batched(learned))
        jax.block_until_ready(one(learned, pairs[0]))
        t_batch, T_batch = best_of(args.repeats, batched, learned)
        t_loop, T_loop = best_of(args.repeats, loop, learned)
        diff = float(np.max(np.abs(np.asarray(T_batch) - np.stack(T_loop))))
        row = {
            "method": method,
            "pairs": data.num_pairs,
            "source_points": int(data.pairs.rows.shape[1]),
            "candidates": int(data.pairs.candidates.shape[2]),
            "rounds": config.rounds,
            "batch_s": t_batch,
            "loop_s": t_loop,
            "batch_per_s": data.num_pairs / t_batch,
            "loop_per_s": data.num_pairs / t_loop,
            "speedup": t_loop / t_batch,
            "max_abs_difference": diff,
        }
        rows.append(row)
        print(f"{method}: {data.num_pairs} registrations, batch {row['batch_per_s']:.0f}/s, "
              f"loop {row['loop_per_s']:.0f}/s, {row['speedup']:.1f}x "
              f"(max |T_batch - T_loop| {diff:.1e})", flush=True)  # fmt: skip
    if args.out is not None:
        meta = {"cpus": os.cpu_count(), "jax": jax.__version__, "device": str(jax.devices()[0])}
        write_atomic(args.out, json.dumps({"machine": meta, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
