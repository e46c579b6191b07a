"""Work in stages: a generator that yields between its stages and returns a result.

A long computation on the event loop (a SLAM keyframe scan, a planner tick) holds up
every other task until it ends; the 20 Hz control tick then runs late by as much. Written
as a generator that yields where it may be interrupted, the same code serves both kinds
of caller: offline tools run it to the end at once (:func:`run_steps`), the daemon's
tasks let the loop run between two stages (:func:`run_steps_async`). The stages and
their order do not depend on the caller, so neither does the result.

Example::

    def work() -> Generator[None, None, int]:
        a = first_half()
        yield                       # the loop may run other tasks here
        return a + second_half()

    run_steps(work())               # offline: all at once
    await run_steps_async(work())   # in a task: the loop runs between the halves
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Generator
from typing import TypeVar

T = TypeVar("T")


def run_steps(steps: Generator[None, None, T]) -> T:
    """Run every stage at once and return the result."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


async def run_steps_async(steps: Generator[None, None, T], cpu_s: list[float] | None = None) -> T:
    """Run the stages with the event loop free in between; adds their thread CPU time to ``cpu_s[0]``.

    The CPU time counts only the stages themselves, not what other tasks did in between
    (the benchmark's per-scan figure). If the awaiting task is cancelled, the generator
    is closed where it stands.
    """
    try:
        while True:
            start_s = time.thread_time()
            try:
                next(steps)
            except StopIteration as stop:
                return stop.value
            finally:
                if cpu_s is not None:
                    cpu_s[0] += time.thread_time() - start_s
            await asyncio.sleep(0)
    finally:
        steps.close()
