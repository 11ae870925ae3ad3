"""The project's shared real data, found beside the repository (``../shared/data``)."""

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_path(relative: str) -> Path:
    """``../shared/data/<relative>``. Missing, a test skips on a developer's machine but fails
    under CI (``CI=true``), where the data is always laid beside the clone."""
    path = SHARED_DATA / relative
    if not path.exists():
        message = f"shared data {path} not present"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    return path
