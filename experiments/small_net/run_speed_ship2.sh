#!/usr/bin/env bash
# PLAN_ship2 (rule B2): gloam_net in processes of its own, the shipped model then the candidate
# (seed 2), three times in turn, alone on the machine.
set -euo pipefail
B="data/long --sequences 403 --threads 2 --methods gloam_net --isolate"
for r in 1 2 3; do
    python scripts/bench_odometry.py $B --out experiments/small_net/ship2_shipped_$r.json
    python scripts/bench_odometry.py $B --weights experiments/small_net/models/model_s2.npz \
        --out experiments/small_net/ship2_s2_$r.json
done
