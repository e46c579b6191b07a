"""The virtual-time loop: timers fire in order, instantly, with the clock they expect."""

from __future__ import annotations

import asyncio
import time

import pytest

from mazebot.clock import RealClock
from mazebot.sim.virtual_time import run_virtual


def test_an_hour_of_sleeping_takes_no_real_time() -> None:
    async def sleepy() -> float:
        await asyncio.sleep(3600)
        return RealClock().now_s()

    wall = time.perf_counter()
    assert run_virtual(sleepy()) == pytest.approx(3600.0, abs=1e-3)  # + a microsecond a loop pass
    assert time.perf_counter() - wall < 5.0  # generous: it is instantaneous in practice


def test_timers_interleave_as_in_real_time() -> None:
    order: list[tuple[str, float]] = []

    async def ticker(name: str, period_s: float, n: int) -> None:
        loop = asyncio.get_running_loop()
        for _ in range(n):
            await asyncio.sleep(period_s)
            order.append((name, round(loop.time(), 3)))

    async def both() -> None:
        await asyncio.gather(ticker("fast", 0.1, 5), ticker("slow", 0.25, 2))

    run_virtual(both())
    assert [t for _, t in order] == sorted(t for _, t in order)
    assert ("slow", 0.25) in order
    assert ("fast", 0.5) in order


def test_executor_work_completes() -> None:
    async def job() -> int:
        return await asyncio.get_running_loop().run_in_executor(None, sum, range(10))

    assert run_virtual(job()) == 45
