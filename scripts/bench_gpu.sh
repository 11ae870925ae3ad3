#!/usr/bin/env bash
# Speed on a CUDA machine, one run: the backbones' inference (net against geometric) and the
# odometry (ours against small_gicp and KISS-ICP), then the backbones again on that machine's CPU.
#
#   GLOAM_COMMIT=<commit> scripts/bench_gpu.sh DATA OUT
#
# DATA: a KITTI-layout root holding sequence 00 (docs/benchmarks.md names the scans measured).
# OUT: a folder for bench_backbones_gpu.json, bench_odometry_gpu.json, bench_backbones_cpu.json
# and machine.txt. Each benchmark writes its file as soon as it ends, so a run cut short keeps
# what it measured. The peers need `pip install small_gicp kiss-icp`.
set -u
data=$1
out=$2
threads=$(nproc)
mkdir -p "$out"
export PYTHONUNBUFFERED=1
{
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
    python3 -c 'import jax, jaxlib; print("jax", jax.__version__, jax.devices())'
    echo "cpus $threads, commit ${GLOAM_COMMIT:-unknown}"
} | tee "$out/machine.txt"
python3 scripts/bench_backbones.py "$data" --sequence 00 --scans 10 --out "$out/bench_backbones_gpu.json"
python3 scripts/bench_odometry.py "$data" --sequences 00 --threads "$threads" \
    --methods gicp,small_gicp,gloam_net,gloam,kiss-icp --out "$out/bench_odometry_gpu.json"
JAX_PLATFORMS=cpu python3 scripts/bench_backbones.py "$data" --sequence 00 --scans 10 \
    --out "$out/bench_backbones_cpu.json"
