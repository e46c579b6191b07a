"""The odometry task's beats, ticked on the virtual clock for tests of what follows them.

The health checks and the control process do their periodic work in the odometry's wake-ups
(``SharedState.odometry_beat``) so that the loop wakes no more often than the encoders make it. Their
tests tick the beat at a chosen period, stop it to see the fallback timers take over, and note when
each beat fell.
"""

from __future__ import annotations

import asyncio
import math

from mazebot.state import SharedState


async def tick_odometry_beats(state: SharedState, beats: list[float], end_s: float, period_s: float | None,
                              stop_beats_s: float = math.inf) -> None:
    """Tick ``state.odometry_beat`` every ``period_s`` until the loop's clock reaches ``end_s``.

    ``period_s = None`` or a clock past ``stop_beats_s`` means no beats: the loop only idles in short
    sleeps, as while the wheels' encoders are silent. Each beat's time is appended to ``beats``.
    """
    loop = asyncio.get_running_loop()
    while loop.time() < end_s:
        if period_s is None or loop.time() >= stop_beats_s:
            await asyncio.sleep(0.01)
            continue
        await asyncio.sleep(period_s)
        beats.append(loop.time())
        state.odometry_beat.tick()
