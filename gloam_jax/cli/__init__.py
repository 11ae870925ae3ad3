"""The ``gloam`` command line: simulate, run, eval, demo, init-model, train, train-backbone."""

from __future__ import annotations

from gloam_jax.cli import backbone, config, run, simulate, train  # noqa: F401  (they register their commands)
from gloam_jax.cli.common import app

__all__ = ["app"]

if __name__ == "__main__":
    app()
