"""Experiment configuration: settings dataclasses, read from and written to YAML.

An odometry YAML file holds the fields of :class:`~gloam_jax.odometry.OdometryConfig`, with the
GICP ones under ``gicp:``; a training one those of
:class:`~gloam_jax.training.config.TrainConfig`. Unknown keys and wrongly typed values are
errors naming the file.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

import yaml

from gloam_jax.errors import InputError
from gloam_jax.gicp import GICPConfig
from gloam_jax.io import write_atomic
from gloam_jax.odometry import OdometryConfig


def build_dataclass(cls, values: dict[str, Any], source: str, prefix: str = ""):
    """``cls(**values)``, nested dataclasses from nested mappings, with the values checked
    against the field types; errors name ``source`` and the setting."""
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
            kwargs[name] = build_dataclass(hint, value, source, f"{prefix}{name}.")
            continue
        if get_origin(hint) is tuple:
            if not isinstance(value, list | tuple):
                raise InputError(source, f"{prefix}{name} must be a list, not {value!r}")
            kwargs[name] = tuple(value)
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


def load_config(path: str | Path | None, cls: type = OdometryConfig):
    """Settings of ``cls`` (default: odometry) from a YAML file, defaults for what it leaves
    out; None: all defaults."""
    if path is None:
        return cls()
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    try:
        values = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise InputError(path, f"not valid YAML ({err})".replace("\n", " ")) from None
    if not isinstance(values, dict):
        raise InputError(path, "expected a mapping of settings at the top level")
    return build_dataclass(cls, values, str(path))


def config_dict(config) -> dict[str, Any]:
    """A settings dataclass as plain YAML-ready values (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def dump_config(config, path: str | Path) -> None:
    cls = type(config)
    header = f"# gloam-jax settings (fields of {cls.__module__}.{cls.__qualname__})\n"
    write_atomic(path, header + yaml.safe_dump(config_dict(config), sort_keys=False))


__all__ = [
    "GICPConfig",
    "OdometryConfig",
    "build_dataclass",
    "config_dict",
    "dump_config",
    "load_config",
]
