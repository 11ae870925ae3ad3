#!/usr/bin/env bash
# PLAN_ship step 2 (rule B): gicp with the shipped gloam_net, then with the candidate (seed 2),
# three times in turn, alone on the machine; the ratio gloam_net / gicp within each file.
set -euo pipefail
B="data/long --sequences 403 --threads 2 --methods gicp,gloam_net"
for r in 1 2 3; do
    python scripts/bench_odometry.py $B --out experiments/small_net/ship_speed_shipped_$r.json
    python scripts/bench_odometry.py $B --weights experiments/small_net/models/model_s2.npz \
        --out experiments/small_net/ship_speed_s2_$r.json
done
