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
