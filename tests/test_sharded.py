"""Sharded batch registration: the pairs split over 4 devices give the one-device results.

XLA fixes the number of host devices when JAX starts, so the checks run this file as a
script, once, in a fresh Python with ``XLA_FLAGS=--xla_force_host_platform_device_count=4``
(4 virtual CPU devices), which computes both the 1-device and the 4-device results and saves
them for the tests to compare. The pair counts (9 and 5) are not multiples of 4, so the
padding is exercised too.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

DEVICES = 4


@pytest.fixture(scope="module")
def worker(sim_sequence, tiny_training, tmp_path_factory) -> tuple[dict, Path]:
    """The worker's results for both checks: its metadata, and the folder of its arrays."""
    out = tmp_path_factory.mktemp("sharded")
    env = dict(os.environ)
    flag = f"--xla_force_host_platform_device_count={DEVICES}"
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {flag}".strip()
    env["JAX_PLATFORMS"] = "cpu"
    cmd = [sys.executable, __file__, str(sim_sequence), str(out), str(tiny_training.start)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return json.loads((out / "meta.json").read_text()), out


def test_sharded_evaluator_matches_one_device(sim_sequence, worker):
    """9 pairs (padded to 12) over 4 devices: the same registrations and window errors as on
    one device, and as this process's own (unsharded) Evaluator."""
    metas, out = worker
    meta = metas["evaluate"]
    assert meta["devices"] == DEVICES
    assert meta["pairs"] == 9
    # Each device holds 3 of the 12 padded pairs, and computes a third of what one device
    # computes for all 9: the work is split, not repeated.
    assert meta["shard_pairs"] == [3, 3, 3, 3]
    assert meta["flops_4"] == pytest.approx(meta["flops_1"] / 3, rel=0.1)
    one, four = (np.load(out / f"evaluate_{n}.npz") for n in (1, DEVICES))
    assert one["T_rel"].shape == four["T_rel"].shape == (9, 4, 4)
    np.testing.assert_allclose(four["T_rel"], one["T_rel"], atol=2e-5)
    np.testing.assert_allclose(four["t_err"], one["t_err"], rtol=1e-5)
    np.testing.assert_allclose(four["r_err"], one["r_err"], rtol=1e-5, atol=1e-9)
    assert 0 < float(one["t_err"][0]) < 0.05

    # The same data and settings in this process (one CPU device, the default mesh).
    from gloam_jax.learned import Learned
    from gloam_jax.training import batch
    from gloam_jax.training.data import load_windows

    data = load_windows(sim_sequence, ["00"], _preprocess(), _eval_config(), frames=10)
    here = batch.Evaluator(data, _eval_config())(Learned())
    np.testing.assert_allclose(four["T_rel"], here.T_rel, atol=2e-5)
    np.testing.assert_allclose(four["t_err"], here.t_err, rtol=1e-5)


def test_sharded_gradient_step_matches_one_device(worker):
    """A train_grad step with the pairs (5, padded to 8) over 4 devices (soft association
    through the implicit adjoint, both MLPs) logs the one-device loss and takes Adam's step
    from the one-device gradient (read back from Adam's first moment in its checkpoint)."""
    metas, out = worker
    meta = metas["grad"]
    assert meta["devices"] == DEVICES
    assert meta["pairs"] == 5
    assert np.isfinite(meta["loss_1"]) and meta["loss_1"] > 0
    # The 4-device step's loss is another fusion of the same sums (with its gradient, over
    # the pairs in another order): float32 noise.
    assert meta["loss_step"] == pytest.approx(meta["loss_1"], rel=1e-4)
    g = np.load(out / "grad.npz")
    one, four = g["moment_expected"], g["moment_after"]
    assert np.all(np.isfinite(one)) and np.linalg.norm(one) > 0
    # Float32 sums over the pairs in another order: agreement relative to the gradient's size.
    assert np.linalg.norm(four - one) <= 1e-4 * np.linalg.norm(one)
    # Adam's first step is about learning_rate x sign(gradient): the weights moved by about
    # 0.01 each, as the one-device gradient says (within a tenth of a step).
    assert np.max(np.abs(g["params_after"] - g["params_before"])) > 5e-3
    np.testing.assert_allclose(g["params_after"], g["params_expected"], rtol=0, atol=1e-3)


# --------------------------------------------------------------------------------------------
# The worker: runs in a fresh Python with 4 host devices.


def _preprocess():
    from gloam_jax.preprocess import PreprocessConfig

    return PreprocessConfig(downsampling_resolution=0.5)


def _eval_config():
    from gloam_jax.training import batch

    return batch.BatchConfig(rounds=2, max_source_points=300, segment_fractions=(0.3, 0.6))


def _grad_config():
    import dataclasses

    from gloam_jax.training import batch

    config = batch.BatchConfig(
        rounds=2, max_source_points=200, association="soft", segment_fractions=(0.3, 0.6),
        segment_step=2,
    )  # fmt: skip
    return dataclasses.replace(config, gicp=dataclasses.replace(config.gicp, adjoint="implicit"))


def _evaluate(root: Path, out: Path) -> dict:
    import jax

    from gloam_jax.learned import Learned
    from gloam_jax.training import batch
    from gloam_jax.training.data import load_windows

    data = load_windows(root, ["00"], _preprocess(), _eval_config(), frames=10)
    devices = jax.devices()
    meta = {"devices": len(devices), "pairs": data.num_pairs}
    for n in (1, DEVICES):
        evaluator = batch.Evaluator(data, _eval_config(), batch.pair_mesh(devices[:n]))
        result = evaluator(Learned())
        np.savez(out / f"evaluate_{n}.npz", **result._asdict())
        # What one device computes: XLA's count for the compiled program (a device's share).
        compiled = evaluator._run.lower(Learned(), evaluator._scans, evaluator._pairs).compile()
        cost = compiled.cost_analysis()
        meta[f"flops_{n}"] = float((cost[0] if isinstance(cost, list) else cost)["flops"])
    shards = evaluator._pairs.target.addressable_shards
    meta["shard_pairs"] = [int(s.data.shape[0]) for s in shards]
    return meta


def _grad(root: Path, out: Path, start: Path) -> dict:
    """From ``start``, the GICP start model of conftest's tiny_training."""
    import jax
    from jax.flatten_util import ravel_pytree

    from gloam_jax.training import batch
    from gloam_jax.training.config import GradConfig, TrainConfig
    from gloam_jax.training.grad import CHECKPOINT, _optimizer, load_checkpoint, train_grad
    from gloam_jax.training.problem import setup

    cfg = TrainConfig(
        data=str(root), sequences=("00",), frames=6, init_model=str(start),
        batch=_grad_config(), grad=GradConfig(steps=1, eval_every=1, learning_rate=0.01),
    )  # fmt: skip
    problem = setup(cfg, out / "run", cache_dir=out / "cache")
    data, params = problem.data, problem.init_params
    devices = jax.devices()
    meta = {"devices": len(devices), "pairs": data.num_pairs}
    # The loss and gradient on one device, and the Adam step they make.
    one = batch.pair_mesh(devices[:1])
    value, grad = jax.jit(jax.value_and_grad(lambda p: batch.loss(p, data, cfg.batch, one)))(params)
    meta["loss_1"] = float(value)
    optimizer = _optimizer(problem)
    start = optimizer.init(params)
    updates, expected_state = optimizer.update(grad, start, params)
    expected = jax.tree_util.tree_map(lambda p, u: p + u, params, updates)
    # One train_grad step on all 4 devices: the loss it logged, and the weights and Adam state
    # it wrote. Adam's first moment after one step is 0.1 x the (clipped) gradient it used.
    train_grad(problem, mesh=batch.pair_mesh(devices))
    history = json.loads((out / "run" / "history.json").read_text())
    meta["loss_step"] = history[-1]["soft_loss"]
    templates = {"params": params, "state": start}
    trees, _ = load_checkpoint(out / "run" / CHECKPOINT, templates)
    flat = lambda tree: np.asarray(ravel_pytree(tree)[0])  # noqa: E731
    np.savez(
        out / "grad.npz",
        params_before=flat(params),
        params_after=flat(trees["params"]),
        params_expected=flat(expected),
        moment_after=flat(trees["state"][1][0].mu),
        moment_expected=flat(expected_state[1][0].mu),
    )
    return meta


if __name__ == "__main__":
    from gloam_jax.cli.common import use_compilation_cache

    # The session's cache (XDG_CACHE_HOME from conftest): what is compiled twice here (to count
    # its flops) compiles once.
    use_compilation_cache(True)
    root, out, start = (Path(a) for a in sys.argv[1:4])
    meta = {"evaluate": _evaluate(root, out), "grad": _grad(root, out, start)}
    (out / "meta.json").write_text(json.dumps(meta))
