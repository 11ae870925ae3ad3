"""Which of the level-0 aggregation's steps cost, alone (issue 42): the shipped network's
``local0`` written out, with one step at a time removed (results then differ; only the time
is read): python probe_level0.py DATA (val 403 frame 100)."""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from probe_network import scan_inputs

from gloam_jax.features import net as N

net, inputs = scan_inputs(sys.argv[1], range(100, 101))
x, la = inputs[0], net.local0
h = jax.nn.relu(net.stem(x.inputs))


def aggregation(variant: str):
    def agg(la, h, xyz, nbr):
        half = la.position.weight.shape[1]
        f = jax.nn.relu(la.feature(h))
        f_score = f @ la.score.weight[half:] + la.score.bias

        def rows(i):
            nb = nbr[i]
            rel = xyz[nb] - xyz[i][:, None, :]
            dist = jnp.sqrt(jnp.sum(rel * rel, axis=-1, keepdims=True))
            enc = jax.nn.relu(la.position(jnp.concatenate([rel, dist], axis=-1)))
            if variant == "no score product":
                score = jnp.concatenate([enc, enc], -1) + f_score[nb]
            elif variant == "no score gather":
                score = enc @ la.score.weight[:half] + f_score[i][:, None, :]
            else:
                score = enc @ la.score.weight[:half] + f_score[nb]
            if variant == "no softmax":
                attention = score
            else:
                attention = jax.nn.softmax(score, axis=1)
            pooled = jnp.concatenate(
                [jnp.sum(attention[..., :half] * enc, axis=1),
                 jnp.sum(attention[..., half:] * f[nb], axis=1)], axis=-1,
            )  # fmt: skip
            return jax.nn.relu(la.out(pooled))

        edge_bytes = nbr.shape[1] * la.out.weight.shape[1] * 4
        return N.in_chunks(rows, nbr.shape[0], max(1, N._CHUNK_BYTES // edge_bytes))

    return jax.jit(agg)


ref = np.asarray(la(h, x.xyz, x.nbr0))
for variant in ("as shipped", "no score product", "no score gather", "no softmax", "as shipped"):
    fn = aggregation(variant)
    out = np.asarray(jax.block_until_ready(fn(la, h, x.xyz, x.nbr0)))
    t = []
    for _ in range(20):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(la, h, x.xyz, x.nbr0))
        t.append(time.perf_counter() - t0)
    print(f"{variant:18s} {1e3 * np.median(t):6.2f} ms  max |diff| {np.abs(out - ref).max():.1e}")
