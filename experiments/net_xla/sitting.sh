#!/usr/bin/env bash
# The plan's quiet sitting: probe_network.py at 512 KiB, 1 MiB and 2 MiB chunks, three
# interleaved rounds, each size's embeddings compared with the first 2 MiB pass's.
# bash experiments/net_xla/sitting.sh DATA OUT_DIR   (alone on the machine)
set -euo pipefail
data=$1 out=$2
here=$(dirname "$0")
mkdir -p "$out"
python "$here/probe_network.py" "$data" 2048 "$out/ref.npz" > "$out/ref.txt"
for round in 1 2 3; do
  for kib in 512 1024 2048; do
    python "$here/probe_network.py" "$data" "$kib" "$out/emb_${kib}.npz" "$out/ref.npz" \
      > "$out/round${round}_${kib}.txt"
    echo "round $round, $kib KiB: $(grep 'whole network' "$out/round${round}_${kib}.txt")," \
      "$(grep 'largest difference' "$out/round${round}_${kib}.txt" | sed 's/.*: //')"
  done
done
