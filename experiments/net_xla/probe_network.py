"""Where the shipped gloam_net network's time goes, alone (issue 42): each part jitted on its
own over the grid-path inputs of val 403 frames 100..109, medians of 3 passes.

python probe_network.py DATA [CHUNK_KIB [OUT.npz [REF.npz]]]: the layers' chunk size (default
the package's), the embeddings written to OUT and their largest difference from REF's. XLA's
own flags come from $XLA_FLAGS, as for any JAX process."""

import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from gloam_jax import pointcloud as pc
from gloam_jax.datasets import open_dataset
from gloam_jax.features import net as N
from gloam_jax.models import load_model, shipped_model_path


def scan_inputs(data: str, frames=range(100, 110)):
    """The shipped net model's network and its grid-path inputs for val 403 ``frames``."""
    backbone = load_model(shipped_model_path("net")).backbone()
    g, c = backbone.grid, backbone.net.config
    sequence = open_dataset(data, sequence="403")
    inputs = []
    for i in frames:
        scan = sequence.frame(i)[0]
        band = pc.range_band(scan, g["min_range"], g["max_range"])
        grid = pc.voxel_grid(band.xyz, g["resolution"])
        centres = grid.means(band.xyz)
        values = grid.means(band.intensity().astype(np.float64)[:, None])[:, 0]
        nbr0 = N._knn(N.KdTree(centres), centres, g["k"])
        x = N.build_inputs(centres, N.scan_intensity(values, c), c, nbr0=nbr0)
        inputs.append(jax.tree.map(jnp.asarray, x))
    return backbone.net, inputs


@jax.jit
def stem_local0(net, x):
    return net.local0(jax.nn.relu(net.stem(x.inputs)), x.xyz, x.nbr0)


@jax.jit
def pool(net, x, h0):
    return jnp.max(h0[x.nbr0[x.sub]], axis=1)


@jax.jit
def local1(net, x, h1):
    return net.local1(h1, x.xyz[x.sub], x.nbr1)


@jax.jit
def decode(net, x, h0, h1):
    return N.embed(net.decode.weight, net.decode.bias, jnp.concatenate([h0, h1[x.up]], -1))


@jax.jit
def whole(net, x):
    return net.embedding(x)


def main() -> None:
    if len(sys.argv) > 2:
        N._CHUNK_BYTES = int(sys.argv[2]) << 10
    net, inputs = scan_inputs(sys.argv[1])
    ms: dict[str, list[float]] = {}

    def timed(name, fn, *args):
        out = jax.block_until_ready(fn(*args))
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        ms.setdefault(name, []).append(1e3 * (time.perf_counter() - t0))
        return out

    for _ in range(3):
        for x in inputs:
            h0 = timed("stem + local aggregation 0", stem_local0, net, x)
            h1 = timed("max-pool onto level 1", pool, net, x, h0)
            h1 = timed("local aggregation 1", local1, net, x, h1)
            timed("upsample + decode", decode, net, x, h0, h1)
            timed("whole network", whole, net, x)
    flags = os.environ.get("XLA_FLAGS", "(none)")
    print(f"XLA_FLAGS {flags}, chunks of {N._CHUNK_BYTES >> 10} KiB")
    print(f"level 0 {inputs[-1].nbr0.shape}, level 1 {inputs[-1].nbr1.shape}")
    for name, v in ms.items():
        print(f"{name:30s} {np.median(v):6.2f} ms")
    if len(sys.argv) > 3:
        out = [np.asarray(whole(net, x)) for x in inputs]
        np.savez(sys.argv[3], *out)
    if len(sys.argv) > 4:
        with np.load(sys.argv[4]) as ref:
            diff = max(float(np.abs(ref[f"arr_{i}"] - o).max()) for i, o in enumerate(out))
        print(f"largest difference from {sys.argv[4]}: {diff:.2e}")


if __name__ == "__main__":
    main()
