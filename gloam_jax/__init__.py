"""gloam-jax: differentiable Generalized LOAM (learned GICP LiDAR odometry) in JAX."""

from __future__ import annotations

from gloam_jax.errors import InputError
from gloam_jax.gicp import GICPConfig, PreparedCloud, RegistrationResult, align, prepare
from gloam_jax.odometry import Odometry, OdometryConfig

__version__ = "0.1.0"

__all__ = [
    "GICPConfig",
    "InputError",
    "Odometry",
    "OdometryConfig",
    "PreparedCloud",
    "RegistrationResult",
    "__version__",
    "align",
    "prepare",
]
