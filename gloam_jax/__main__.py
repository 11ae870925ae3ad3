"""``python -m gloam_jax``: the ``gloam`` command line."""

from gloam_jax.cli import app

app()
