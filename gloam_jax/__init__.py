"""gloam-jax: differentiable Generalized LOAM (learned GICP LiDAR odometry) in JAX.

The public API, loaded on first use (``import gloam_jax`` itself loads no JAX)::

    import gloam_jax
    result = gloam_jax.align(target_points, source_points)
    result.T_target_source
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING

from gloam_jax.errors import InputError

try:
    __version__ = version("gloam-jax")
except PackageNotFoundError:  # a source tree that was not installed
    __version__ = "0.0.0+unknown"

# public name -> the module that owns it
_EXPORTS = {
    "align": "gloam_jax.registration",
    "prepare": "gloam_jax.registration",
    "align_prepared": "gloam_jax.registration",
    "PreparedCloud": "gloam_jax.registration",
    "RegistrationResult": "gloam_jax.registration",
    "GICPConfig": "gloam_jax.gicp",
    "PreprocessConfig": "gloam_jax.preprocess",
    "Odometry": "gloam_jax.odometry",
    "OdometryConfig": "gloam_jax.odometry",
    "load_model": "gloam_jax.models",
    "load_config": "gloam_jax.config",
}

if TYPE_CHECKING:
    from gloam_jax.config import load_config
    from gloam_jax.gicp import GICPConfig
    from gloam_jax.models import load_model
    from gloam_jax.odometry import Odometry, OdometryConfig
    from gloam_jax.preprocess import PreprocessConfig
    from gloam_jax.registration import (
        PreparedCloud,
        RegistrationResult,
        align,
        align_prepared,
        prepare,
    )


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'gloam_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__all__ = [
    "InputError",
    "__version__",
    "align",
    "prepare",
    "align_prepared",
    "PreparedCloud",
    "RegistrationResult",
    "GICPConfig",
    "PreprocessConfig",
    "Odometry",
    "OdometryConfig",
    "load_model",
    "load_config",
]
