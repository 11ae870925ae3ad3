"""Experiment configuration: settings dataclasses, read from and written to YAML.

An odometry YAML file holds the fields of :class:`~gloam_jax.odometry.OdometryConfig`, with the
scan preparation under ``preprocess:`` and the GICP ones under ``gicp:``; a training one those
of :class:`~gloam_jax.training.config.TrainConfig`. Unknown keys and wrongly typed values are
errors naming the file; keys that moved into a section name their new place, and retired
keys (a class's ``RETIRED``, settings that no longer do anything) are ignored. A section left
out, or given in part, keeps the defaults of its parent (e.g. ``batch.gicp`` its 5
candidates). The files in ``configs/`` ship inside the package: :func:`load_config` takes
their name (``gloam``) as well as a path.

A file may start from another: ``base: gicp`` (a shipped config's name) or ``base: mine.yaml``
(a path relative to the file) loads that one first, and the file's own settings replace its
values, section by section. So a variant states only what it changes.
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
from gloam_jax.preprocess import PreprocessConfig

PACKAGED = Path(__file__).resolve().parent / "configs"
"""The settings files shipped with the package (``configs/`` in a checkout)."""


def build_dataclass(cls, values: dict[str, Any], source: str, prefix: str = "", base=None):
    """``cls(**values)`` (``base`` with ``values`` replaced, when given), nested dataclasses
    from nested mappings, with the values checked against the field types; errors name
    ``source`` and the setting."""
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    moved = getattr(cls, "MOVED", {})
    for key in sorted(set(values) & set(moved)):
        raise InputError(source, f"setting '{prefix}{key}' moved to '{prefix}{moved[key]}'")
    values = {k: v for k, v in values.items() if k not in getattr(cls, "RETIRED", {})}
    unknown = sorted(set(values) - names)
    if unknown:
        raise InputError(source, f"unknown setting '{prefix}{unknown[0]}'; known: {sorted(names)}")
    base = cls() if base is None else base
    kwargs = {}
    for name, value in values.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, dict):
                raise InputError(source, f"{prefix}{name} must be a mapping")
            kwargs[name] = build_dataclass(
                hint, value, source, f"{prefix}{name}.", getattr(base, name)
            )
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
        elif hint is int and not isinstance(value, int):
            raise InputError(source, f"{prefix}{name} must be a whole number, not {value!r}")
        elif hint is bool and not isinstance(value, bool):
            raise InputError(source, f"{prefix}{name} must be true or false, not {value!r}")
        kwargs[name] = hint(value) if hint in (int, float) else value
    return dataclasses.replace(base, **kwargs)


def _is_name(text: str) -> bool:
    """Whether ``text`` is a bare name (``gloam``), which stands for a shipped config."""
    path = Path(text)
    return path.suffix == "" and path.name == text


def _shipped_names() -> str:
    return ", ".join(sorted(p.stem for p in PACKAGED.glob("*.yaml")))


def resolve_config(name_or_path: str | Path) -> Path:
    """A settings file: a path, or the name of one shipped with the package (``gloam``)."""
    path = Path(name_or_path)
    if not path.exists() and _is_name(str(name_or_path)):
        packaged = PACKAGED / f"{path.name}.yaml"
        if packaged.is_file():
            return packaged
        raise InputError(path, f"no such file, nor a shipped config (one of {_shipped_names()})")
    if not path.exists():
        raise InputError(path, "file not found")
    return path


def load_config(path: str | Path | None, cls: type = OdometryConfig):
    """Settings of ``cls`` (default: odometry) from a YAML file or a shipped config's name,
    on top of its ``base:`` file when it names one, defaults for what they leave out; None:
    all defaults."""
    if path is None:
        return cls()
    return _load(resolve_config(path), cls, ())


def _load(path: Path, cls: type, chain: tuple[Path, ...]):
    """:func:`load_config` of a resolved ``path``; ``chain`` is the files that based on it."""
    if path.resolve() in chain:
        raise InputError(path, "its base: settings lead back to itself")
    values = _read_mapping(path)
    parent = None
    if "base" in values:
        base = values.pop("base")
        if not isinstance(base, str) or not base:
            raise InputError(path, f"base must name a shipped config or a YAML file, not {base!r}")
        if _is_name(base):
            target = PACKAGED / f"{base}.yaml"
            if not target.is_file():
                raise InputError(
                    path, f"base: {base} is not a shipped config (one of {_shipped_names()})"
                )
        else:
            target = path.parent / base
            if not target.is_file():
                raise InputError(path, f"base: {base} not found (read relative to this file)")
        parent = _load(target, cls, (*chain, path.resolve()))
    try:
        return build_dataclass(cls, values, str(path), base=parent)
    except InputError as err:
        if err.source is None:  # a settings class's own check: name the file
            raise InputError(path, err.problem) from None
        raise


def parse_mapping(text: str) -> dict[str, Any] | None:
    """A YAML mapping given as text (``'{drop: [density]}'``, a command-line value); None when
    the text is not valid YAML or not a mapping, for the caller's one-line error."""
    try:
        values = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    return values if isinstance(values, dict) else None


def _read_mapping(path: Path) -> dict[str, Any]:
    """A settings file's top-level mapping; a one-line error naming the file otherwise."""
    try:
        values = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as err:
        raise InputError(path, f"not valid YAML ({err})".replace("\n", " ")) from None
    except UnicodeDecodeError:
        raise InputError(path, "not a text file (not UTF-8)") from None
    except IsADirectoryError:
        raise InputError(path, "is a directory, not a settings file") from None
    except OSError as err:
        raise InputError(path, f"cannot be read ({err.strerror})") from None
    if not isinstance(values, dict):
        raise InputError(path, "expected a mapping of settings at the top level")
    return values


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
    "PreprocessConfig",
    "build_dataclass",
    "config_dict",
    "dump_config",
    "load_config",
    "resolve_config",
]
