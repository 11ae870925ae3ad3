"""Experiment configuration: the odometry dataclasses, read from and written to YAML.

A YAML file holds the fields of :class:`~gloam_jax.odometry.OdometryConfig`, with the GICP
ones under ``gicp:``. Unknown keys and wrongly typed values are errors naming the file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, get_args, get_type_hints

import yaml

from gloam_jax.errors import InputError
from gloam_jax.gicp import GICPConfig
from gloam_jax.io import write_atomic
from gloam_jax.odometry import OdometryConfig


def _build(cls, values: dict[str, Any], source: str, prefix: str = ""):
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise InputError(source, f"unknown setting '{prefix}{unknown[0]}'; known: {sorted(names)}")
    kwargs = {}
    for name, value in values.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, dict):
                raise InputError(source, f"{prefix}{name} must be a mapping")
            kwargs[name] = _build(hint, value, source, f"{prefix}{name}.")
            continue
        allowed = get_args(hint)
        if allowed and all(isinstance(a, str) for a in allowed):  # a Literal of strings
            if value not in allowed:
                raise InputError(
                    source, f"{prefix}{name} must be one of {list(allowed)}, not {value!r}"
                )
        elif hint in (int, float) and (
            isinstance(value, bool) or not isinstance(value, (int, float))
        ):
            raise InputError(source, f"{prefix}{name} must be a number, not {value!r}")
        elif hint is bool and not isinstance(value, bool):
            raise InputError(source, f"{prefix}{name} must be true or false, not {value!r}")
        kwargs[name] = hint(value) if hint in (int, float) else value
    return cls(**kwargs)


def load_config(path: str | Path | None) -> OdometryConfig:
    """Odometry settings from a YAML file (defaults for what it leaves out); None: defaults."""
    if path is None:
        return OdometryConfig()
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    try:
        values = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise InputError(path, f"not valid YAML ({err})".replace("\n", " ")) from None
    if not isinstance(values, dict):
        raise InputError(path, "expected a mapping of settings at the top level")
    return _build(OdometryConfig, values, str(path))


def config_dict(config: OdometryConfig) -> dict[str, Any]:
    return dataclasses.asdict(config)


def dump_config(config: OdometryConfig, path: str | Path) -> None:
    header = "# gloam-jax odometry settings (fields of gloam_jax.odometry.OdometryConfig)\n"
    write_atomic(path, header + yaml.safe_dump(config_dict(config), sort_keys=False))


__all__ = ["GICPConfig", "OdometryConfig", "config_dict", "dump_config", "load_config"]
