"""The shipped gloam_net network at several layer chunk sizes, interleaved, alone (issue 42):
python probe_chunks.py DATA [ROUNDS] (val 403 frames 100..109; ms a scan, median and least
of ROUNDS passes per size, and the largest difference from 2 MiB's embeddings)."""

import sys
import time

import jax
import numpy as np
from probe_network import scan_inputs

from gloam_jax.features import net as N

net, inputs = scan_inputs(sys.argv[1])
rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 5
sizes = (256, 512, 1024, 2048)  # KiB
fns = {}
for kib in sizes:
    N._CHUNK_BYTES = kib << 10  # read when traced: each function keeps its own
    fns[kib] = jax.jit(lambda net, x: net.embedding(x))
    for x in inputs:
        jax.block_until_ready(fns[kib](net, x))
ref = [np.asarray(fns[2048](net, x)) for x in inputs]
ms = {kib: [] for kib in sizes}
for _ in range(rounds):
    for kib, fn in fns.items():
        t0 = time.perf_counter()
        for x in inputs:
            jax.block_until_ready(fn(net, x))
        ms[kib].append(1e3 * (time.perf_counter() - t0) / len(inputs))
for kib, fn in fns.items():
    diff = max(
        float(np.abs(np.asarray(fn(net, x)) - r).max()) for x, r in zip(inputs, ref, strict=True)
    )
    print(f"{kib:5d} KiB {np.median(ms[kib]):6.2f} ms (least {min(ms[kib]):.2f}), diff {diff:.1e}")
