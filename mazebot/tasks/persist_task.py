"""Saving the run while it runs, and once more when it ends.

Every ``[persist] save_period_s`` the SLAM state is copied on the loop
(:func:`~mazebot.persist.snapshot.take_snapshot`, well under a millisecond for a maze)
and written in a worker thread (:func:`~mazebot.persist.snapshot.save_snapshot`, every
file atomic), so a slow SD card never holds up the control loop. When the task is
cancelled (the daemon stops) it saves one last time, synchronously: nothing else runs
any more. A failed save (disk full) is counted in ``state.record.save_errors`` and
logged; the robot carries on.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mazebot.clock import Clock
from mazebot.cpu_budget import PartMeter
from mazebot.persist.snapshot import save_snapshot, take_snapshot
from mazebot.slam.slam import Slam
from mazebot.state import SharedState

log = logging.getLogger(__name__)


def _save(state: SharedState, slam: Slam, run_dir: Path, extra: Callable[[], dict[str, Any]]) -> Any:
    snapshot = take_snapshot(slam, extra())
    return lambda: save_snapshot(snapshot, run_dir)


def _measured(write: Callable[[], None], meter: PartMeter) -> None:
    """``write()`` in the executor's thread, its CPU time on the saving meter."""
    with meter.measure():
        write()


async def run(
    state: SharedState,
    slam: Slam,
    run_dir: Path,
    clock: Clock,
    period_s: float,
    extra: Callable[[], dict[str, Any]] = dict,
) -> None:
    loop = asyncio.get_running_loop()
    meter = state.cpu.part("saving")
    state.record.run_dir = str(run_dir)
    try:
        while True:
            await clock.sleep(period_s)
            if not slam.keyframes:
                continue
            write = _save(state, slam, run_dir, extra)
            try:
                await loop.run_in_executor(None, _measured, write, meter)
                state.record.saves += 1
            except OSError as exc:
                state.record.save_errors += 1
                log.error("saving the run to %s failed: %s", run_dir, exc)
    finally:
        if slam.keyframes:
            try:
                _save(state, slam, run_dir, extra)()
                state.record.saves += 1
                log.info("run saved in %s", run_dir)
            except OSError as exc:
                state.record.save_errors += 1
                log.error("saving the run to %s failed: %s", run_dir, exc)
