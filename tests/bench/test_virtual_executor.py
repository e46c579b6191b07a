"""On virtual time the lost-robot search takes its CPU time on the simulated clock (mazebot.bench.virtual_executor)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
import time

import pytest

from mazebot.bench.virtual_executor import LOOP_JOB_LATENCY_S, SEARCH_LATENCY_S, CpuTimedExecutor
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


def test_a_search_answers_after_its_fixed_cost_on_the_virtual_clock_and_a_loop_closure_goes_to_the_worker() -> None:
    # a search of 50 ms of CPU or of 10: each answers SEARCH_LATENCY_S later, so a run does not
    # depend on how fast this machine ran the search
    loop = VirtualTimeLoop(start_s=100.0)
    inner = RecordingExecutor()

    async def main() -> tuple[float, str, str, float, str]:
        executor = CpuTimedExecutor(inner, asyncio.get_running_loop())
        running = asyncio.get_running_loop()
        t0 = running.time()
        found = await running.run_in_executor(executor, _burn, 0.05)
        waited_s = running.time() - t0
        t1 = running.time()
        await running.run_in_executor(executor, _burn, 0.01)
        assert running.time() - t1 == pytest.approx(SEARCH_LATENCY_S, abs=1e-4)
        job = object.__new__(LoopClosureJob)  # only its type matters here
        submitted_s = running.time()
        merged = await running.run_in_executor(executor, job)
        assert running.time() - submitted_s == pytest.approx(LOOP_JOB_LATENCY_S, abs=1e-4)  # a pass of the loop is 1 µs
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
    assert cpu_s >= 0.05  # what it took is recorded for the report
    assert waited_s == pytest.approx(SEARCH_LATENCY_S, abs=1e-4)  # on the simulated clock: the model's cost
    assert len(inner.jobs) == 1 and isinstance(inner.jobs[0], LoopClosureJob)


class SlowWorker(concurrent.futures.Executor):
    """Finishes each job after ``wall_s`` of real time, in a thread (a worker process on a busy core)."""

    def __init__(self, wall_s: float) -> None:
        self.wall_s = wall_s

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[override]
        future: concurrent.futures.Future = concurrent.futures.Future()

        def work() -> None:
            time.sleep(self.wall_s)
            future.set_result("merged late")

        threading.Thread(target=work, daemon=True).start()
        return future


def test_a_loop_closure_lands_at_the_same_simulated_instant_however_long_the_worker_takes() -> None:
    """The hand-over time is the model's, not the worker's: the loop waits for a slow one."""
    loop = VirtualTimeLoop(start_s=10.0)

    async def main() -> tuple[float, str, float]:
        running = asyncio.get_running_loop()
        executor = CpuTimedExecutor(SlowWorker(wall_s=0.3), running)
        ticks: list[float] = []

        async def ticking() -> None:  # a task on a timer, as the simulator's: it must not run ahead
            while True:
                ticks.append(running.time())
                await asyncio.sleep(0.01)

        ticker = asyncio.ensure_future(ticking())
        submitted_s = running.time()
        wall0 = time.perf_counter()
        merged = await running.run_in_executor(executor, object.__new__(LoopClosureJob))
        waited_wall_s = time.perf_counter() - wall0
        ticker.cancel()
        return running.time() - submitted_s, merged, waited_wall_s, ticks

    try:
        waited_s, merged, waited_wall_s, ticks = loop.run_until_complete(main())
    finally:
        loop.close()
    assert merged == "merged late"
    assert waited_s == pytest.approx(LOOP_JOB_LATENCY_S, abs=1e-4)  # a pass of the loop is 1 µs
    assert waited_wall_s >= 0.3  # the worker's real time was waited for ...
    assert ticks[-1] <= 10.0 + LOOP_JOB_LATENCY_S + 1e-4  # ... with the simulated world standing still
