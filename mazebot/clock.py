"""The one clock every task reads time from.

On the robot and in ``run --sim`` this is the event loop's monotonic clock. Benchmarks
swap in a virtual clock so the same task code runs faster than real time (see
``mazebot.sim``). Tasks must take time from here, never from ``time.time()``.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


class Clock(Protocol):
    """A source of monotonic time in seconds and a way to wait on it."""

    def now_s(self) -> float:
        """Monotonic time in seconds."""
        ...

    async def sleep(self, duration_s: float) -> None:
        """Wait ``duration_s`` seconds of this clock's time."""
        ...


class RealClock:
    """The running event loop's clock; ``sleep`` is ``asyncio.sleep``.

    Reading the loop's ``time()`` (monotonic seconds on a normal loop) rather than
    ``time.monotonic()`` directly is what lets the simulator's virtual-time loop run the
    same task code faster than real time: timers, ``asyncio.sleep`` and this clock all
    move together. Outside a running loop it falls back to ``time.monotonic()``.
    """

    def now_s(self) -> float:
        try:
            return asyncio.get_running_loop().time()
        except RuntimeError:
            return time.monotonic()

    async def sleep(self, duration_s: float) -> None:
        await asyncio.sleep(max(0.0, duration_s))
