"""Run folders under the state directory, and atomic file writes.

Each ``mazebot run`` gets ``STATE_DIR/runs/<YYYYmmdd-HHMMSS>/`` (``STATE_DIR`` is
``[daemon] state_dir``, else systemd's ``$STATE_DIRECTORY`` — ``/var/lib/mazebot`` with
the shipped unit — else ``~/.local/state/mazebot``). A run is named by its folder name;
``latest`` names the newest.

Atomic writes (:func:`write_atomic`): a temporary file in the same directory, written,
flushed and fsync'ed, then ``os.replace``'d over the target, then the directory fsync'ed
(POSIX ``rename(2)`` is atomic within one file system), so a crash or a power cut leaves
either the old file or the new one, never half a map.
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mazebot.errors import UsageError
from mazebot.files import write_atomic as write_atomic  # re-exported: the run files are written with it
from mazebot.web.auth import resolve_state_dir

RUNS_DIR = "runs"
META_FILE = "meta.json"


class RunNotFound(UsageError):
    """The run named on the command line does not exist (exit 2)."""


def runs_root(state_dir_setting: str) -> Path:
    """``STATE_DIR/runs`` for the configured ``[daemon] state_dir``."""
    return resolve_state_dir(state_dir_setting) / RUNS_DIR


def new_run_dir(root: Path, now: dt.datetime | None = None) -> Path:
    """A fresh, empty ``root/<timestamp>`` folder (``-2``, ``-3`` ... if the second is taken)."""
    stamp = (now or dt.datetime.now()).strftime("%Y%m%d-%H%M%S")
    root.mkdir(parents=True, exist_ok=True)
    for attempt in range(1, 1000):
        path = root / (stamp if attempt == 1 else f"{stamp}-{attempt}")
        try:
            path.mkdir()
        except FileExistsError:
            continue
        return path
    raise UsageError(f"cannot create a run folder in {root}: too many runs named {stamp}")


@dataclass(frozen=True)
class RunInfo:
    """One saved run as ``mazebot runs`` lists it."""

    name: str
    path: Path
    meta: dict[str, Any]


def read_meta(run_dir: Path) -> dict[str, Any]:
    """The run's ``meta.json`` (empty if it was never saved or cannot be read)."""
    try:
        return json.loads((run_dir / META_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def list_runs(root: Path) -> list[RunInfo]:
    """Saved runs, oldest first."""
    if not root.is_dir():
        return []
    return [RunInfo(p.name, p, read_meta(p)) for p in sorted(root.iterdir()) if p.is_dir()]


def find_run(root: Path, name: str) -> Path:
    """The folder of run ``name``: a folder name under ``root``, ``latest``, or a path to a run folder."""
    if name == "latest":
        saved = [r for r in list_runs(root) if r.meta]
        if not saved:
            raise RunNotFound(f"no saved run in {root}; `mazebot run` saves one")
        return saved[-1].path
    candidate = Path(name).expanduser()
    for path in (root / name, candidate):
        if path.is_dir() and (path / META_FILE).is_file():
            return path
    raise RunNotFound(f"run {name!r} not found in {root} (nor as a folder with {META_FILE}); `mazebot runs` lists them")
