#!/bin/bash
# One sitting, alone: the padded device map (HEAD, a worktree at /work/wt_old) against the
# candidates gathered on the host (the patched tree at /work/main); val 403 d0, 1000 frames.
set -e
cd /work/wt_old && PYTHONPATH=/work/wt_old python scripts/bench_odometry.py data/long \
  --sequences 403 --threads 2 --methods gicp,gloam --out experiments/host_gather/speed_device_map.json
cd /work/main && PYTHONPATH=/work/main python scripts/bench_odometry.py data/long \
  --sequences 403 --threads 2 --methods gicp,gloam --out experiments/host_gather/speed_host_gather.json
