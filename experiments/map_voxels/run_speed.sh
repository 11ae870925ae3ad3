#!/bin/bash
# Speed of the current map and both candidates, one sitting, alone: val 403 d0, 1000 frames.
# CFG_BASE, CFG_05, CFG_025: folders of the shipped configs, the last two with map_resolution.
set -e
for c in base:$CFG_BASE:gicp,gloam 05:$CFG_05:gicp,gloam 025:$CFG_025:gicp; do
  IFS=: read name dir methods <<< "$c"
  python scripts/bench_odometry.py data/long --sequences 403 --threads 2 --methods $methods \
    --configs $dir --out experiments/map_voxels/speed_$name.json
done
