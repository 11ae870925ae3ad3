"""The one exception type for bad user input."""

from __future__ import annotations

import os


class InputError(ValueError):
    """Bad input, reported in one line as ``<file>: <problem>``.

    The CLI prints the message alone (no traceback), so the message must say which file is
    wrong and how.
    """

    def __init__(self, source: str | os.PathLike[str] | None, problem: str) -> None:
        self.source = None if source is None else os.fspath(source)
        self.problem = problem
        super().__init__(problem if self.source is None else f"{self.source}: {problem}")


def check_setting(ok: bool, name: str, rule: str, value: object) -> None:
    """Raise ``InputError("<name> must be <rule>, not <value>")`` unless ``ok``: the settings
    dataclasses check themselves with it, so a bad value fails where it is made."""
    if not ok:
        raise InputError(None, f"{name} must be {rule}, not {value!r}")


def is_int(value: object, minimum: int) -> bool:
    """An integer (not a bool, not a float like 2.5) of at least ``minimum``."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def is_positive(value: object) -> bool:
    """A finite number above zero."""
    return (
        isinstance(value, int | float) and not isinstance(value, bool) and 0 < value < float("inf")
    )
