#!/bin/bash
# PLAN.md's second candidate, run because 0.5 m failed rule 1 (402, 405): the worktree's
# gicp.yaml with map_resolution: 0.25, on the same worlds (baselines as for 0.5 m).
set -e
cd /work/wt_mv
PYTHONPATH=/work/wt_mv python scripts/make_tables.py --split val_long --data data/long \
  --data data/long_d1 --sequences 401,402,403,404,405 --model d=default \
  --out /work/main/results/map_voxels_025
