#!/bin/bash
# The validation of PLAN.md: the candidate (worktree with map_resolution: 0.5 in gicp.yaml) on
# val_long 401-405, then the current map on 402 and 405 (worktree unpatched).
set -e
cd /work/wt_mv
PYTHONPATH=/work/wt_mv python scripts/make_tables.py --split val_long --data data/long \
  --data data/long_d1 --sequences 401,402,403,404,405 --model d=default \
  --out /work/main/results/map_voxels_05
cd /work/wt_base
PYTHONPATH=/work/wt_base python scripts/make_tables.py --split val_long --data data/long \
  --data data/long_d1 --sequences 402,405 --model d=default \
  --out /work/main/results/map_voxels_base
