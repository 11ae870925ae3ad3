"""The ``gloam`` command line: simulate, run, eval, demo, init-model, model-info, train,
train-backbone, segment, config."""

from __future__ import annotations

import os

# Lineax checks the linear solves of a gradient (its tangent solves) with a host callback that
# raises: equinox's EQX_ON_ERROR=raise. Training skips a step whose gradient is not finite
# anyway (training.grad), and JAX never writes a program with a host callback to its
# persistent compilation cache, so the training step compiled again on every run. With "nan"
# a failed solve gives that skipped step, and a rerun loads the step. Set before JAX and
# equinox load; a setting in the environment wins.
os.environ.setdefault("EQX_ON_ERROR", "nan")

from gloam_jax.cli import backbone, config, run, simulate, train  # noqa: F401  (they register their commands)
from gloam_jax.cli.common import app

__all__ = ["app"]

if __name__ == "__main__":
    app()
