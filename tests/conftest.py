"""Fixtures shared by several test modules."""

import dataclasses
import os
import types

import pytest

# First, so that gloam_jax/cli/__init__.py sets EQX_ON_ERROR=nan before equinox loads, as in
# the gloam command line: the training step has no host callback, and JAX's compilation cache
# can keep it.
from gloam_jax.cli.common import use_compilation_cache
from gloam_jax.simulate import simulate


@pytest.fixture(scope="session", autouse=True)
def session_cache(tmp_path_factory):
    """The user cache (scan cache, JAX compilation cache) in a folder of this session, not
    ~/.cache: tests neither read what earlier runs left nor leave anything."""
    with pytest.MonkeyPatch.context() as patch:
        # Under pytest-xdist, one cache for all workers (beside their own folders): a program
        # one worker compiled, the other loads.
        base = tmp_path_factory.getbasetemp()
        if os.environ.get("PYTEST_XDIST_WORKER"):
            base = base.parent
        cache = base / "user_cache"
        cache.mkdir(exist_ok=True)
        patch.setenv("XDG_CACHE_HOME", str(cache))
        # On from the start, as in every gloam command: tests that build the same program
        # (the same training step, the same batch evaluation) compile it once.
        use_compilation_cache(True)
        yield


@pytest.fixture(scope="session")
def sim_sequence(tmp_path_factory):
    """40 frames of a thinned HDL-64 along a procedural urban drive (about 35 m)."""
    root = tmp_path_factory.mktemp("sim")
    simulate(root, frames=40, num_beams=32, num_columns=1000, seed=7, style="urban")
    return root


@pytest.fixture(scope="session")
def tiny_training(sim_sequence, tmp_path_factory):
    """Tiny training runs on the drive, shared by every training test: ``.config(**fields)``
    makes a TrainConfig of 6 scans from ``.start`` (``.model``: the GICP start, PCA on every
    10th scan) with ``.batch`` (2 rounds, 200 source points, soft association, implicit
    adjoint). The same data and settings make the same programs (the training step, the
    evaluation), which the session's compilation cache then compiles once."""
    from gloam_jax.features import get_backbone
    from gloam_jax.models import save_model
    from gloam_jax.training.batch import BatchConfig
    from gloam_jax.training.config import TrainConfig
    from gloam_jax.training.problem import fit_initial_model

    model = fit_initial_model(sim_sequence, ["00"], get_backbone("geometric"), every=10,
                              init="gicp")  # fmt: skip
    start = tmp_path_factory.mktemp("start") / "start.npz"
    save_model(start, model)
    batch = BatchConfig(
        rounds=2, max_source_points=200, association="soft", segment_fractions=(0.3, 0.6),
        segment_step=2, gicp=dataclasses.replace(BatchConfig().gicp, adjoint="implicit"),
    )  # fmt: skip

    def config(**fields) -> TrainConfig:
        defaults = {"data": str(sim_sequence), "sequences": ("00",), "frames": 6,
                    "init_model": str(start), "batch": batch}  # fmt: skip
        return TrainConfig(**{**defaults, **fields})

    return types.SimpleNamespace(config=config, start=start, model=model, batch=batch)
