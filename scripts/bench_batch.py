"""Batch evaluation throughput: the same registrations vmapped at once and one at a time.

    python scripts/bench_batch.py --config configs/train_tpe.yaml --out results/bench_batch.json

Prepares the training windows of the config (cached with ``--cache``), then registers every
pair (a) all at once, ``jit(vmap(register_pair))``, (b) in a Python loop over the same
jitted single-pair function, with the same candidate sets, rounds and model (the estimates
must agree), and (c) in a loop of the odometry's registration, ``registration.align_prepared``, on
the same source points, target scans and initial guesses (k-d tree candidates refreshed on
the host every round, until converged). Timed after compilation, best of ``--repeats``.
Prints registrations/s and each path's mean t_err over the windows.

    python scripts/bench_batch.py --devices 1,2,4 --out bench_sharded.json

instead times the batch evaluation (:class:`gloam_jax.training.batch.Evaluator`, hard
association) with the pairs split over the first 1, 2, 4 devices, in one run (the counts
taking turns, best of ``--repeats`` each), and prints registrations/s and the ratio to the
first count. On a CPU host it asks XLA for that many virtual host devices
(``--xla_force_host_platform_device_count``, set before JAX starts); they share the
machine's cores. ``--data``, ``--sequences`` and ``--frames`` override the
config's training data.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

from gloam_jax.config import load_config
from gloam_jax.io import write_atomic
from gloam_jax.learned import attributes
from gloam_jax.models import learned_parts
from gloam_jax.neighbors import KdTree
from gloam_jax.registration import PreparedCloud, align_prepared
from gloam_jax.training import batch
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.problem import setup


def best_of(repeats: int, fn, *args) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times), out


def align_loop(data: batch.BatchData, learned, config: batch.BatchConfig):
    """(c): a function running align_prepared over every pair, and the clouds it uses."""
    scans, pairs = data.scans, data.pairs
    attrs = jax.jit(lambda v, V, f: attributes(v, V, f, learned, data.regularizer))
    clouds = []
    for s in range(scans.points.shape[0]):
        m = np.asarray(scans.mask[s])
        covs, feats = attrs(scans.values[s][m], scans.vectors[s][m], scans.pca[s][m])
        points = np.asarray(scans.points[s], np.float64)[m]
        feats = None if learned.conversion is None else np.asarray(feats)
        clouds.append((points, np.asarray(covs, np.float64), feats))
    targets = [PreparedCloud(p, c, KdTree(p), f) for p, c, f in clouds]
    sources = []
    for b in range(data.num_pairs):
        p, c, f = clouds[int(pairs.source[b])]
        rows = np.asarray(pairs.rows[b])[np.asarray(pairs.row_mask[b])]
        sub = None if f is None else f[rows]
        sources.append(PreparedCloud(p[rows], c[rows], KdTree(p[rows]), sub))
    gicp = dataclasses.replace(
        config.gicp,
        num_candidates=config.gicp.num_candidates if learned.conversion is not None else 1,
    )
    T_init = np.asarray(pairs.T_init, np.float64)
    target_of = np.asarray(pairs.target)

    def run():
        return np.stack([
            align_prepared(targets[target_of[b]], sources[b], T_init[b], gicp).T_target_source
            for b in range(data.num_pairs)
        ])  # fmt: skip

    return run


def mean_t_err(T_rel, data: batch.BatchData) -> float:
    t, _ = batch.window_errors(jax.numpy.asarray(T_rel, jax.numpy.float32), data.windows)
    return float(100 * np.mean(np.asarray(t)))


def host_devices(count: int) -> None:
    """Ask XLA for ``count`` CPU devices; only takes effect before JAX's first computation."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if "host_platform_device" not in f]
    flags.append(f"--xla_force_host_platform_device_count={count}")
    os.environ["XLA_FLAGS"] = " ".join(flags)


def bench_devices(problem, cfg: TrainConfig, counts: list[int], methods: list[str], repeats: int):
    """Rows of registrations/s with the pairs split over the first N devices, N in counts.
    The counts take turns within each repeat, so that a busy machine slows them alike; each
    keeps its best time."""
    devices = jax.devices()
    if max(counts) > len(devices):
        raise SystemExit(f"--devices asks for {max(counts)} devices; JAX sees {len(devices)}")
    data, config = problem.data, dataclasses.replace(cfg.batch, association="hard")
    rows = []
    for method in methods:
        learned = learned_parts(problem.model, method)
        evaluators, first_call, best, results = {}, {}, {}, {}
        for n in counts:
            evaluators[n] = batch.Evaluator(data, config, batch.pair_mesh(devices[:n]))
            t0 = time.perf_counter()
            evaluators[n](learned)  # compiles
            first_call[n], best[n] = time.perf_counter() - t0, np.inf
        for _ in range(repeats):
            for n in counts:
                seconds, results[n] = best_of(1, evaluators[n], learned)
                best[n] = min(best[n], seconds)
        base = counts[0]
        for n in counts:
            row = {
                "method": method,
                "devices": n,
                "device_kind": devices[0].device_kind,
                "pairs": data.num_pairs,
                "padded_pairs": data.num_pairs + (-data.num_pairs % n),
                "source_points": int(data.pairs.rows.shape[1]),
                "rounds": config.rounds,
                "first_call_s": first_call[n],
                "batch_s": best[n],
                "batch_per_s": data.num_pairs / best[n],
                "ratio_to_first": best[base] / best[n],
                "max_abs_difference_to_first": float(
                    np.max(np.abs(results[n].T_rel - results[base].T_rel))
                ),
                "t_err_percent": float(100 * np.mean(results[n].t_err)),
            }
            rows.append(row)
            print(f"{method}: {n} device(s) ({row['device_kind']}), {data.num_pairs} registrations "
                  f"in {best[n]:.3f} s: {row['batch_per_s']:.0f}/s, {row['ratio_to_first']:.2f}x "
                  f"{base} device(s); max |T - T_{base}| "
                  f"{row['max_abs_difference_to_first']:.1e}; t_err {row['t_err_percent']:.3f} %",
                  flush=True)  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("configs/train_tpe.yaml"))
    parser.add_argument("--run", type=Path, default=Path("runs/bench_batch"))
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--methods", default="gicp,gloam")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--devices", default=None, help="e.g. 1,2,4: the sharded batch only")
    parser.add_argument("--data", default=None, help="KITTI-layout root (default: the config's)")
    parser.add_argument("--sequences", default=None, help="comma-separated ids")
    parser.add_argument("--frames", type=int, default=None, help="first N scans of each")
    args = parser.parse_args()
    counts = None if args.devices is None else [int(n) for n in args.devices.split(",")]
    if counts is not None:
        if min(counts) < 1:
            raise SystemExit("--devices: counts must be >= 1")
        host_devices(max(counts))  # before JAX starts; GPUs, when present, stay the default
    cfg = load_config(args.config, TrainConfig)
    overrides = {"data": args.data, "frames": args.frames}
    if args.sequences is not None:
        overrides["sequences"] = tuple(args.sequences.split(","))
    cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    if cfg.batch.map_scans != 1:
        raise SystemExit(f"{args.config}: the align_prepared loop registers scan to scan; "
                         "use a config with map_scans: 1")  # fmt: skip
    problem = setup(cfg, args.run, cache_dir=args.cache)
    if counts is not None:
        rows = bench_devices(problem, cfg, counts, args.methods.split(","), args.repeats)
        if args.out is not None:
            meta = {
                "cpus": os.cpu_count(),
                "jax": jax.__version__,
                "devices": [str(d) for d in jax.devices()],
                "command": " ".join(sys.argv),
            }
            write_atomic(args.out, json.dumps({"machine": meta, "rows": rows}, indent=2))
        return
    data, config = problem.data, dataclasses.replace(cfg.batch, association="hard")
    # Data as arguments, not closed-over constants, which XLA would try to fold (minutes).
    register_pairs = jax.jit(batch.register_pairs, static_argnums=(3, 4))
    one = jax.jit(batch.register_pair, static_argnums=(3, 4))
    pairs = [jax.tree_util.tree_map(lambda x, b=b: x[b], data.pairs) for b in range(data.num_pairs)]

    def batched(learned):
        return register_pairs(learned, data.scans, data.pairs, config, data.regularizer)

    def loop(learned):
        return [one(learned, data.scans, p, config, data.regularizer) for p in pairs]

    rows = []
    for method in args.methods.split(","):
        learned = learned_parts(problem.model, method)
        jax.block_until_ready(batched(learned))
        jax.block_until_ready(one(learned, data.scans, pairs[0], config, data.regularizer))
        t_batch, T_batch = best_of(args.repeats, batched, learned)
        t_loop, T_loop = best_of(args.repeats, loop, learned)
        diff = float(np.max(np.abs(np.asarray(T_batch) - np.stack(T_loop))))
        run_align = align_loop(data, learned, config)
        run_align()  # compiles each padded size once
        t_align, T_align = best_of(args.repeats, run_align)
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
            "align_loop_s": t_align,
            "align_loop_per_s": data.num_pairs / t_align,
            "speedup_vs_align_loop": t_align / t_batch,
            "t_err_batch_percent": mean_t_err(T_batch, data),
            "t_err_align_loop_percent": mean_t_err(T_align, data),
        }
        rows.append(row)
        print(f"{method}: {data.num_pairs} registrations, batch {row['batch_per_s']:.0f}/s, "
              f"loop {row['loop_per_s']:.0f}/s ({row['speedup']:.1f}x, max |T_batch - T_loop| "
              f"{diff:.1e}), align_prepared loop {row['align_loop_per_s']:.0f}/s "
              f"({row['speedup_vs_align_loop']:.1f}x); t_err batch "
              f"{row['t_err_batch_percent']:.2f} %, align loop "
              f"{row['t_err_align_loop_percent']:.2f} %", flush=True)  # fmt: skip
    if args.out is not None:
        meta = {"cpus": os.cpu_count(), "jax": jax.__version__, "device": str(jax.devices()[0])}
        write_atomic(args.out, json.dumps({"machine": meta, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
