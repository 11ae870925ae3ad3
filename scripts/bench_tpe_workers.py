"""TPE trials per minute with 1 and with N worker processes on this machine, in one run.

    python scripts/bench_tpe_workers.py --config RUN.yaml --cache CACHE --trials 300 \
        --workers 1,2 --repeats 2 [--storage postgresql://...] --out results/workers.json

Each run is the whole ``gloam train --mode tpe`` command (interpreter start, loading the
prepared windows from ``--cache``, every trial, the export) on a fresh study; the worker
counts take turns (1, 2, 2, 1, ...) so that a change in the machine's load falls on both. The
windows should be prepared and the evaluation compiled beforehand (``gloam train ... --cache
CACHE --trials 2`` once), as in a real search, where that is paid once. Prints and writes the
wall time of every run, the load average before it, and each count's median ratio to the first.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from make_tables import commit

from gloam_jax.io import write_atomic


def one_run(args, workers: int, scratch: Path, k: int) -> dict:
    out = scratch / f"w{workers}-{k}"
    shutil.rmtree(out, ignore_errors=True)
    command = ["gloam", "train", "--config", str(args.config), "--out", str(out),
               "--cache", str(args.cache), "--trials", str(args.trials),
               "--workers", str(workers)]  # fmt: skip
    if args.storage:
        # A fresh study per run: a name shared by two runs would let the second find it full.
        study = f"bench-{os.getpid()}-{k}-w{workers}"
        command += ["--storage", args.storage, "--study-name", study]
    load = os.getloadavg()[0]
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    trials = len(json.loads((out / "history.json").read_text()))
    return {"workers": workers, "wall_s": round(wall, 2), "load_before": round(load, 2),
            "completed_trials": trials}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, required=True, help="TrainConfig YAML (tpe mode)")
    parser.add_argument("--cache", type=Path, required=True, help="prepared windows (--cache)")
    parser.add_argument("--trials", type=int, default=300, help="the fixed trial budget")
    parser.add_argument("--workers", default="1,2", help="worker counts, the first the reference")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each count")
    parser.add_argument("--storage", default=None, help="optuna storage URL (default sqlite)")
    parser.add_argument("--out", type=Path, default=None, help="JSON file to write")
    args = parser.parse_args()
    counts = [int(c) for c in args.workers.split(",")]

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-tpe-") as scratch:
        for k in range(args.repeats):
            for workers in counts if k % 2 == 0 else counts[::-1]:
                rows.append(one_run(args, workers, Path(scratch), k))
                print(rows[-1], flush=True)
    median = {c: float(np.median([r["wall_s"] for r in rows if r["workers"] == c])) for c in counts}
    ratio = {c: round(median[c] / median[counts[0]], 3) for c in counts}
    summary = {c: {"median_wall_s": median[c], "ratio_to_first": ratio[c]} for c in counts}
    print(json.dumps(summary, indent=1))
    if args.out is not None:
        result = {
            "command": " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
            "commit": commit(),
            "cpus": os.cpu_count(),
            "storage": args.storage or "sqlite (the run folder's study.db)",
            "trials": args.trials,
            "runs": rows,
            "summary": summary,
        }
        write_atomic(args.out, json.dumps(result, indent=1).encode())


if __name__ == "__main__":
    main()
