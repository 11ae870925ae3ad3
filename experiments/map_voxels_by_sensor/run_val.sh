#!/bin/bash
# PLAN.md's runs: today's map (worktree wt_mv0 at 5cc5c14) and the candidate (wt_mv5: the same
# with map_resolution: 0.5 in gicp.yaml) on val_long 409-411, both draws, side by side.
M="--split val_long --data data/long --data data/long_d1 --sequences 409,410,411 --model d=default"
(cd /work/wt_mv0 && PYTHONPATH=/work/wt_mv0 python scripts/make_tables.py $M \
  --out /work/main/results/mvs_base > /logs/mvs_base.log 2>&1) &
(cd /work/wt_mv5 && PYTHONPATH=/work/wt_mv5 python scripts/make_tables.py $M \
  --out /work/main/results/mvs_05 > /logs/mvs_05.log 2>&1) &
wait
