"""Where the tests find the real data (mazes, pose graphs, laser logs): ``$MAZEBOT_DATA``, else
``../shared/data`` beside the checkout (the Makefile's rule); tests that need a file skip without it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA_DIR = Path(os.environ.get("MAZEBOT_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
MAZES = DATA_DIR / "mazes"
POSEGRAPHS = DATA_DIR / "posegraphs"
CARMEN = DATA_DIR / "carmen"

#: skips a test when the shared maze files are not there
needs_mazes = pytest.mark.skipif(not MAZES.is_dir(), reason=f"shared maze data not found at {MAZES}; set MAZEBOT_DATA")


def carmen_log(name: str) -> Path:
    """The shared CARMEN log ``name``; skips the calling test when it is not there."""
    path = CARMEN / name
    if not path.is_file():
        pytest.skip(f"CARMEN log not found at {path}; set MAZEBOT_DATA")
    return path
