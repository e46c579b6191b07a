"""The clock's beat: followers run in the beating task's wake-ups, or on their own time without them."""

from __future__ import annotations

import asyncio

from mazebot.clock import Beat
from mazebot.sim.virtual_time import run_virtual


async def _follow(beat: Beat, beats: int, timeout_s: float, log: list[tuple[float, bool]], times: int) -> None:
    loop = asyncio.get_running_loop()
    for _ in range(times):
        on_beat = await beat.wait(beats, timeout_s)
        log.append((loop.time(), on_beat))


def test_a_follower_runs_at_every_nth_beat_and_on_its_own_time_once_the_beats_stop() -> None:
    beat = Beat()
    log: list[tuple[float, bool]] = []
    ticks: list[float] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()
        follower = asyncio.create_task(_follow(beat, 2, 0.1, log, 8))
        for _ in range(10):  # 40 Hz for 0.25 s, then silence
            await asyncio.sleep(0.025)
            ticks.append(loop.time())
            beat.tick()
        await follower

    run_virtual(main())
    on_beats = [t for t, on in log if on]
    assert len(on_beats) == 5  # beats 2, 4, 6, 8, 10
    for t, k in zip(on_beats, (1, 3, 5, 7, 9), strict=True):
        assert 0 <= t - ticks[k] < 1e-4  # in the beat's wake-up: the loop's clock has not moved
    timed_out = [t for t, on in log if not on]
    assert len(timed_out) == 3
    assert abs(timed_out[0] - (ticks[-1] + 0.1)) < 1e-3  # then every time-out, measured from the last return
    assert abs(timed_out[1] - timed_out[0] - 0.1) < 1e-3
    assert beat.count == 10
