"""The lost-robot search on virtual time: it takes the CPU time it costs, not whatever the race gives.

On virtual time (:mod:`mazebot.sim.virtual_time`) the loop's clock runs on while a job is in an
executor, as fast as the loop can spin. The search for a lost robot
(:func:`mazebot.slam.relocalize.search_pose`) runs in a thread of the daemon's process: there it
waits for the GIL behind a loop that never sleeps (in one kidnap run it got 0.13 s of CPU in
1.0 s of wall time), and every wall second is as many simulated seconds as the simulator is
faster than real time. A kidnap then looked re-localized after 8 s on a quiet machine (the
simulator 6× real time) and after 1.8 s on a loaded one (1×): a figure of the benchmark machine,
not of the robot.

Here such a job runs at once on the loop's thread (which costs no virtual time: the world waits)
and its result is handed over after the CPU time it took, on the virtual clock: as if it ran on a
core of its own (the Pi 4 has four) while the world went on. Loop-closure jobs go to the daemon's
executor unchanged (its worker process).

Example (``run_daemon``'s ``instrument`` hook on a virtual-time run)::

    executor = CpuTimedExecutor(daemon_executor, asyncio.get_running_loop())
    await loop.run_in_executor(executor, search_pose, slam, scan, history, guess, params)
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import time
from collections.abc import Callable
from concurrent.futures import Executor
from typing import Any

from mazebot.slam.slam import LoopClosureJob


class CpuTimedExecutor(Executor):
    """Plain callables run inline and finish after their thread CPU time; loop-closure jobs go to ``inner``."""

    def __init__(self, inner: Executor, loop: asyncio.AbstractEventLoop) -> None:
        self._inner = inner
        self._loop = loop
        self.cpu_s: list[float] = []  # what each inline job cost (the bench's record)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        if isinstance(fn, LoopClosureJob) and not args and not kwargs:
            return self._inner.submit(fn)
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        start_s = time.thread_time()
        try:
            result = fn(*args, **kwargs)
        except Exception as exc:  # handed over like a thread's exception
            self._later(time.thread_time() - start_s, future, functools.partial(future.set_exception, exc))
        else:
            self._later(time.thread_time() - start_s, future, functools.partial(future.set_result, result))
        return future

    def _later(self, cpu_s: float, future: concurrent.futures.Future[Any], settle: Callable[[], None]) -> None:
        self.cpu_s.append(cpu_s)

        def deliver() -> None:
            if not future.cancelled():  # the SLAM task stopped waiting for it
                settle()

        self._loop.call_later(cpu_s, deliver)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """The daemon shuts the inner executor down itself."""
