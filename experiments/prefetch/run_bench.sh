#!/usr/bin/env bash
# The whole `gloam run` process, 300 frames of the validation world 403 (urban HDL-64), gicp
# and gloam, before the prefetch thread (BEFORE: a checkout of 65cb621) and after (AFTER: this
# checkout), alternated over two repetitions; then small_gicp on the same frames for scale.
#   bash experiments/prefetch/run_bench.sh /work/wt42b . data/long experiments/prefetch/bench
set -euo pipefail
BEFORE=$(realpath "$1") AFTER=$(realpath "$2") DATA=$(realpath "$3") OUT=$4
RUNS=${RUNS:-/tmp/prefetch_runs}
mkdir -p "$OUT" "$RUNS"
for rep in 1 2; do
  for code in before after; do
    tree=$([ "$code" = before ] && echo "$BEFORE" || echo "$AFTER")
    for method in gicp gloam; do
      run="$RUNS/$code-$method-$rep"
      start=$(date +%s.%N)
      # run from the checkout itself: python -m puts the working folder first on the path
      (cd "$tree" && PYTHONPATH="$tree" python -m gloam_jax run "$DATA" --sequence 403 \
        --frames 300 --method "$method" --out "$run" > /dev/null 2>&1)
      end=$(date +%s.%N)
      echo "$rep $code $method $(python -c "print(round($end - $start, 2))")" | tee -a "$OUT/wall.txt"
    done
  done
done
python scripts/bench_odometry.py "$DATA" --sequences 403 --frames 300 --threads 2 \
  --methods small_gicp --out "$OUT/small_gicp.json"
python - "$RUNS" "$OUT/metrics.json" <<'PY'
import json, sys
from pathlib import Path
keys = ("median_ms_per_frame", "median_ms_features", "wall_ms_per_frame", "t_err_percent")
rows = {}
for m in sorted(Path(sys.argv[1]).glob("*/*/metrics.json")):
    metrics = json.loads(m.read_text())
    rows[m.parent.parent.name] = {k: metrics.get(k) for k in keys}
Path(sys.argv[2]).write_text(json.dumps(rows, indent=2) + "\n")
print(json.dumps(rows, indent=2))
PY
