"""Where gloam_net's ``features`` stage goes in the odometry (experiments/small_net):
val 403 d0, the first FRAMES frames as bench_odometry runs them, with the shipped model or
MODEL; median ms a frame of the network call (to its result on the host) and of the rest of
:meth:`NetBackbone.voxel_features` (k-NN, level-1 graph, padding), on the prefetch thread.

    python experiments/small_net/probe_features.py FRAMES [MODEL]
"""

import sys
import time
from collections import defaultdict

import numpy as np

sys.path.insert(0, "scripts")
import bench_odometry  # noqa: E402

from gloam_jax import io  # noqa: E402
from gloam_jax.cli.common import use_compilation_cache  # noqa: E402
from gloam_jax.config import load_config  # noqa: E402
from gloam_jax.features import net  # noqa: E402

spent: dict = defaultdict(list)


def timed(name, fn):
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        if name == "network":
            out = np.asarray(out)  # as voxel_features takes it
        spent[name].append(1e3 * (time.perf_counter() - start))
        return out

    return wrapper


def main() -> None:
    frames = int(sys.argv[1])
    use_compilation_cache()
    net._embedding = timed("network", net._embedding)
    net.NetBackbone.voxel_features = timed("voxel_features", net.NetBackbone.voxel_features)

    class Counter:
        count = 0

    config = load_config("gloam_jax/configs/gloam_net.yaml")
    weights = sys.argv[2] if len(sys.argv) > 2 else None
    _, _, extra = bench_odometry.run_ours(io.KittiSequence("data/long", "403"), frames, config,
                                          weights, Counter())  # fmt: skip
    network = np.array(spent["network"][20:])
    whole = np.array(spent["voxel_features"][20:])
    print(
        f"{weights or 'shipped'}: frame median / p95 {extra['frame_ms']['median']:.1f} / "
        f"{extra['frame_ms']['p95']:.1f} ms, features stage {extra['median_ms_features']:.1f}; "
        f"voxel_features {np.median(whole):.1f} (network {np.median(network):.1f}, the rest "
        f"{np.median(whole - network):.1f}) ms median"
    )


if __name__ == "__main__":
    main()
