"""The repository's ``scripts/`` and experiments' probes as modules, for the tests of them."""

import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def import_script(name: str, experiment: str | None = None):
    """``scripts/<name>.py``, or ``experiments/<experiment>/<name>.py``, as a module (scripts
    import each other by name; a probe puts ``scripts/`` on the path itself)."""
    folder = ROOT / "scripts" if experiment is None else ROOT / "experiments" / experiment
    assert (folder / f"{name}.py").is_file(), f"{folder / name}.py is missing"
    sys.path.insert(0, str(folder))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(folder))
