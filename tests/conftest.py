"""Fixtures shared by several test modules."""

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
        patch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("user_cache")))
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
