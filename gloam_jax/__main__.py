"""``python -m gloam_jax``: the ``gloam`` command line."""

from gloam_jax.cli import app

if __name__ == "__main__":  # not when a spawned worker imports this module
    app()
