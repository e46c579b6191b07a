"""On virtual time the lost-robot search takes its CPU time on the simulated clock (mazebot.bench.virtual_executor)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import time

import pytest

from mazebot.bench.virtual_executor import CpuTimedExecutor
from mazebot.sim.virtual_time import VirtualTimeLoop
from mazebot.slam.slam import LoopClosureJob


def _burn(cpu_s: float, fail: bool = False) -> str:
    start = time.thread_time()
    while time.thread_time() - start < cpu_s:
        sum(range(1000))
    if fail:
        raise ValueError("no pose fits")
    return "found"


class RecordingExecutor(concurrent.futures.Executor):
    def __init__(self) -> None:
        self.jobs: list[object] = []

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[override]
        self.jobs.append(fn)
        future: concurrent.futures.Future = concurrent.futures.Future()
        future.set_result("merged")
        return future


def test_a_search_answers_after_its_cpu_time_on_the_virtual_clock_and_a_loop_closure_goes_to_the_worker() -> None:
    loop = VirtualTimeLoop(start_s=100.0)
    inner = RecordingExecutor()

    async def main() -> tuple[float, str, str, float, str]:
        executor = CpuTimedExecutor(inner, asyncio.get_running_loop())
        running = asyncio.get_running_loop()
        t0 = running.time()
        found = await running.run_in_executor(executor, _burn, 0.05)
        waited_s = running.time() - t0
        job = object.__new__(LoopClosureJob)  # only its type matters here
        merged = await running.run_in_executor(executor, job)
        with pytest.raises(ValueError, match="no pose fits"):
            await running.run_in_executor(executor, _burn, 0.01, True)
        # a search given up on (the task cancelled) is not answered into a cancelled future
        pending = running.run_in_executor(executor, _burn, 0.01)
        pending.cancel()
        await asyncio.sleep(1.0)
        return waited_s, found, merged, executor.cpu_s[0], "ok"

    try:
        waited_s, found, merged, cpu_s, _ = loop.run_until_complete(main())
    finally:
        loop.close()
    assert found == "found" and merged == "merged"
    assert cpu_s >= 0.05
    assert waited_s == pytest.approx(cpu_s, abs=1e-3)  # on the simulated clock: the CPU it took, no more
    assert len(inner.jobs) == 1 and isinstance(inner.jobs[0], LoopClosureJob)
