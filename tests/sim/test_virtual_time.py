"""The virtual-time loop: timers fire in order, instantly, with the clock they expect."""

from __future__ import annotations

import asyncio

import pytest

from mazebot.clock import RealClock
from mazebot.sim.virtual_time import run_virtual


def test_an_hour_of_sleeping_takes_no_real_time() -> None:
    async def sleepy() -> float:
        await asyncio.sleep(3600)
        return RealClock().now_s()

    # on real time this would take an hour: pytest-timeout ([tool.pytest.ini_options] timeout) fails it
    assert run_virtual(sleepy()) == pytest.approx(3600.0, abs=1e-3)  # + a microsecond a loop pass


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


def test_a_slow_cpu_makes_steps_of_daemon_tasks_cost_time_and_stalls_the_loop() -> None:
    from mazebot.sim.virtual_time import SlowCpu, VirtualTimeLoop

    slow = SlowCpu(callback_cost_s=0.01, stall_every_s=1.0, stalls_s=(0.2, 0.3))
    steps: dict[str, list[float]] = {"simulator": [], "planner": []}

    async def spin(name: str) -> None:
        loop = asyncio.get_running_loop()
        for _ in range(5):
            steps[name].append(loop.time())
            await asyncio.sleep(0)

    async def both() -> None:
        await asyncio.gather(asyncio.create_task(spin("simulator"), name="simulator"),
                             asyncio.create_task(spin("planner"), name="planner"))
        await asyncio.sleep(2.5)

    loop = VirtualTimeLoop(slow=slow)
    try:
        loop.run_until_complete(both())
    finally:
        loop.close()
    # each step of the planner costs 10 ms of the clock; the simulator's own cost nothing
    assert loop.costly_callbacks >= 5
    gaps = [b - a for a, b in zip(steps["planner"], steps["planner"][1:], strict=False)]
    assert all(gap >= 0.01 for gap in gaps), gaps
    # stalls at 1 s and 2.2 s (0.2 then 0.3 s of nothing running): the clock jumped
    assert loop.stalled_s == pytest.approx(0.5)
