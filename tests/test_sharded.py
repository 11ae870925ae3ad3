"""Sharded training: the pairs split over 4 devices give the one-device evaluation and step.

XLA fixes the number of host devices when JAX starts, so the 4-device run is this file as a
script, in a fresh Python with ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (4
virtual CPU devices). It and this process run the same training (conftest's tiny run, one
gradient step) from the same config file; this process is the one-device reference, and
shares its programs with the other training tests. The 5 pairs are not a multiple of 4, so
the padding is exercised too.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# One worker runs this module (pytest-xdist --dist loadgroup): its module fixture is built once.
pytestmark = pytest.mark.xdist_group("sharded")


DEVICES = 4


def _run(config_path: Path, run_dir: Path, cache: Path) -> dict:
    """Set up the run of ``config_path``, evaluate its start (hard association, saved as
    ``run_dir/start.npz``) and take one gradient step; returns the devices' metadata."""
    import jax
    from jax.flatten_util import ravel_pytree

    from gloam_jax.config import load_config
    from gloam_jax.training.config import TrainConfig
    from gloam_jax.training.grad import CHECKPOINT, _optimizer, load_checkpoint, train_grad
    from gloam_jax.training.problem import setup

    problem = setup(load_config(config_path, TrainConfig), run_dir, cache_dir=cache)
    evaluator, params = problem.evaluate_hard, problem.init_params
    np.savez(run_dir / "start.npz", **evaluator(params)._asdict())
    train_grad(problem)
    # The step it took: the weights before and after, and Adam's first moment after (0.1 x the
    # clipped gradient it used).
    templates = {"params": params, "state": _optimizer(problem).init(params)}
    trees, _ = load_checkpoint(run_dir / CHECKPOINT, templates)
    flat = lambda tree: np.asarray(ravel_pytree(tree)[0])  # noqa: E731
    np.savez(run_dir / "step.npz", before=flat(params), after=flat(trees["params"]),
             moment=flat(trees["state"][1][0].mu))  # fmt: skip
    # What one device computes: XLA's count for the compiled program (a device's share).
    compiled = evaluator._run.lower(
        params, evaluator._scans, evaluator._pairs, evaluator._head
    ).compile()
    cost = compiled.cost_analysis()
    return {
        "devices": len(jax.devices()),
        "pairs": problem.data.num_pairs,
        "flops": float((cost[0] if isinstance(cost, list) else cost)["flops"]),
        "shard_pairs": [int(s.data.shape[0]) for s in evaluator._pairs.target.addressable_shards],
    }


@pytest.fixture(scope="module")
def runs(tiny_training, tmp_path_factory) -> dict[int, tuple[dict, Path]]:
    """The same run on 1 device (here) and on 4 (the worker): {devices: (metadata, run
    folder)}. One step of test_training's resume test (Adam, learning rate 0.01, 64 random
    source points a pair), on 5 pairs."""
    from gloam_jax.config import dump_config
    from gloam_jax.training.config import GradConfig

    out = tmp_path_factory.mktemp("sharded")
    grad = GradConfig(steps=1, eval_every=1, learning_rate=0.01, source_points=64)
    dump_config(tiny_training.config(mode="grad", grad=grad), out / "config.yaml")
    env = dict(os.environ)
    flag = f"--xla_force_host_platform_device_count={DEVICES}"
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {flag}".strip()
    env["JAX_PLATFORMS"] = "cpu"
    cmd = [sys.executable, __file__, *(str(out / n) for n in ("config.yaml", "four", "cache"))]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    four = json.loads((out / "four" / "meta.json").read_text())
    one = _run(out / "config.yaml", out / "one", out / "cache")
    return {1: (one, out / "one"), DEVICES: (four, out / "four")}


def test_sharded_evaluator_matches_one_device(runs):
    """5 pairs (padded to 8) over 4 devices: the same registrations and window errors as on
    one device, each device computing 2 of the pairs."""
    (one, one_dir), (four, four_dir) = runs[1], runs[DEVICES]
    assert (one["devices"], four["devices"]) == (1, DEVICES)
    assert one["pairs"] == four["pairs"] == 5
    # The work is split, not repeated: each device holds 2 of the 8 padded pairs and computes
    # 2/5 of what one device computes for all 5.
    assert four["shard_pairs"] == [2, 2, 2, 2] and one["shard_pairs"] == [5]
    assert four["flops"] == pytest.approx(one["flops"] * 2 / 5, rel=0.1)
    a, b = np.load(one_dir / "start.npz"), np.load(four_dir / "start.npz")
    assert a["T_rel"].shape == b["T_rel"].shape == (5, 4, 4)
    np.testing.assert_allclose(b["T_rel"], a["T_rel"], atol=2e-5)
    np.testing.assert_allclose(b["t_err"], a["t_err"], rtol=1e-5)
    np.testing.assert_allclose(b["r_err"], a["r_err"], rtol=1e-5, atol=1e-9)
    assert 0 < float(a["t_err"][0]) < 0.05


def test_sharded_gradient_step_matches_one_device(runs):
    """A train_grad step with the pairs over 4 devices (soft association through the implicit
    adjoint, both MLPs) logs the one-device loss and takes the one-device Adam step."""

    def step(run_dir: Path) -> tuple[float, np.lib.npyio.NpzFile]:
        history = json.loads((run_dir / "history.json").read_text())
        assert [h["step"] for h in history] == [0, 1]
        return history[-1]["soft_loss"], np.load(run_dir / "step.npz")

    (loss_1, one), (loss_4, four) = step(runs[1][1]), step(runs[DEVICES][1])
    assert np.isfinite(loss_1) and loss_1 > 0
    # Another fusion of the same sums (with its gradient, over the pairs in another order):
    # float32 noise.
    assert loss_4 == pytest.approx(loss_1, rel=1e-4)
    # Bit for bit: the start's weights as loaded from the same model file, nothing computed.
    np.testing.assert_array_equal(four["before"], one["before"])
    assert np.all(np.isfinite(one["moment"])) and np.linalg.norm(one["moment"]) > 0
    # Float32 sums over the pairs in another order: agreement relative to the gradient's size.
    assert np.linalg.norm(four["moment"] - one["moment"]) <= 1e-4 * np.linalg.norm(one["moment"])
    # Adam's first step is about learning_rate x sign(gradient): the weights moved by about
    # 0.01 each, the same on both (within a tenth of a step).
    assert np.max(np.abs(one["after"] - one["before"])) > 5e-3
    np.testing.assert_allclose(four["after"], one["after"], rtol=0, atol=1e-3)


if __name__ == "__main__":
    from gloam_jax.cli.common import use_compilation_cache

    use_compilation_cache(True)  # the session's cache (XDG_CACHE_HOME from conftest)
    config_path, run_dir, cache = (Path(a) for a in sys.argv[1:4])
    meta = _run(config_path, run_dir, cache)
    (run_dir / "meta.json").write_text(json.dumps(meta))
