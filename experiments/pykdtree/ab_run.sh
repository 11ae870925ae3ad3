#!/bin/bash
# gloam run on val 403 d0 (1000 frames), gicp then gloam, the old tree ($OLD, a worktree of the
# parent commit with data/ linked in) and the new ($NEW), alternating; results under $OUT.
set -e
OLD=${OLD:-/work/wtbase} NEW=${NEW:-/work/main} OUT=${OUT:-/tmp/pykdtree_ab}
export OMP_NUM_THREADS=2
mkdir -p "$OUT"
for m in gicp gloam; do
  for v in old new; do
    d=$OLD; [ $v = new ] && d=$NEW
    (cd "$d" && PYTHONPATH=$d python -m gloam_jax run data/long --sequence 403 --method $m \
      --out "$OUT/ab_${m}_$v" > "$OUT/ab_${m}_$v.log" 2>&1)
  done
done
