#!/usr/bin/env bash
# Rule 2's sitting (PLAN.md): gicp with the shipped gloam_net, then with the candidate's model,
# twice in turn, alone on the machine; ratios within each file.
set -euo pipefail
B="data/long --sequences 403 --threads 2 --methods gicp,gloam_net"
for r in 1 2; do
    python scripts/bench_odometry.py $B --out experiments/small_net/speed_shipped_$r.json
    python scripts/bench_odometry.py $B --weights runs/smallnet_s0/model.npz \
        --out experiments/small_net/speed_small_$r.json
done
