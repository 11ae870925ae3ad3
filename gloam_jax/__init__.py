"""gloam-jax: differentiable Generalized LOAM (learned GICP LiDAR odometry) in JAX."""

from __future__ import annotations

from gloam_jax.errors import InputError

__version__ = "0.1.0"

__all__ = ["InputError", "__version__"]
