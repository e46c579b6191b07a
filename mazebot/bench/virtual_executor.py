"""The lost-robot search and the loop closures on virtual time: each answers after a fixed cost, not a race.

On virtual time (:mod:`mazebot.sim.virtual_time`) the loop's clock runs on while a job is in an
executor, as fast as the loop can spin. The search for a lost robot
(:func:`mazebot.slam.relocalize.search_pose`) runs in a thread of the daemon's process: there it
waits for the GIL behind a loop that never sleeps (in one kidnap run it got 0.13 s of CPU in
1.0 s of wall time), and every wall second is as many simulated seconds as the simulator is
faster than real time. A kidnap then looked re-localized after 8 s on a quiet machine (the
simulator 6× real time) and after 1.8 s on a loaded one (1×): a figure of the benchmark machine,
not of the robot.

Here such a job runs at once on the loop's thread (which costs no virtual time: the world waits)
and its result is handed over ``SEARCH_LATENCY_S`` simulated seconds later: as if it ran on a
Pi's core of its own (the Pi 4 has four) while the world went on. The hand-over once waited the
job's own thread CPU time instead; that varied by tens of milliseconds from run to run of one
seed (0.064–0.100 s for one search), and so did where the robot stood when it was found, and
everything after: a fault run's outcome was not a function of its seed. The thread CPU time is
still recorded (``cpu_s``) for the report.

Loop-closure jobs still run in the daemon's executor (its worker process, on the other core), but
their results no longer land whenever the worker happens to finish: that made SLAM's estimate,
and so every accuracy figure, differ from run to run of one seed by millimetres, because the
worker's wall time decided at which scan a correction was merged. A job's result is handed over
``LOOP_JOB_LATENCY_S`` simulated seconds after it was submitted (a fixed cost model of the
job, not a measurement), and if the worker is not done by then the loop waits for it, with
virtual time standing still. A run is then a function of its seed.

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

#: Longest the loop waits for the worker to finish a job whose hand-over time has come; past it the
#: job counts as failed (a SLAM fault), so a hung worker cannot hang a benchmark.
WORKER_WAIT_MAX_S = 300.0


#: Simulated seconds from a loop-closure job's submission to its result reaching SLAM. On this
#: machine the worker takes a median 25 ms a job on a 6×6 tour (p90 69, max 148 ms) and 62 ms on a
#: 16×16 one (p90 158 ms, max 1.5 s): a Pi 4 core, several times slower, needs a few hundred
#: milliseconds for most. Before this model, results landed a median 1.07 s (p90 2.2 s) after
#: submission on a simulator running ~15× real time. At 1 s the loop waits for the worker ~0.3 s
#: of wall time in a 6×6 tour.
LOOP_JOB_LATENCY_S = 1.0
#: Simulated seconds from a lost-robot search's submission to its result reaching SLAM. A search
#: costs the same whatever its window (:func:`mazebot.slam.relocalize.search_pose` coarsens its
#: steps as it widens it): 64–100 ms of thread CPU on this machine in a 4×4 kidnap run, so a few
#: hundred milliseconds on a Pi 4 core, three to five times slower. A fixed cost model, as for the
#: loop-closure jobs, not a measurement.
SEARCH_LATENCY_S = 0.4

class CpuTimedExecutor(Executor):
    """Plain callables run inline and are handed over ``SEARCH_LATENCY_S`` later; loop-closure jobs
    go to ``inner`` and are handed over ``LOOP_JOB_LATENCY_S`` after submission, both on the virtual
    clock (see the module docstring)."""

    def __init__(self, inner: Executor, loop: asyncio.AbstractEventLoop) -> None:
        self._inner = inner
        self._loop = loop
        self.cpu_s: list[float] = []  # what each inline job cost (the bench's record)
        self.worker_wait_s = 0.0  # wall time the loop stood waiting for loop-closure results

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        if isinstance(fn, LoopClosureJob) and not args and not kwargs:
            return self._hand_over_later(self._inner.submit(fn), LOOP_JOB_LATENCY_S)
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        start_s = time.thread_time()
        try:
            result = fn(*args, **kwargs)
        except Exception as exc:  # handed over like a thread's exception
            settle = functools.partial(future.set_exception, exc)
        else:
            settle = functools.partial(future.set_result, result)
        self.cpu_s.append(time.thread_time() - start_s)
        self._later(SEARCH_LATENCY_S, future, settle)
        return future

    def _later(self, latency_s: float, future: concurrent.futures.Future[Any], settle: Callable[[], None]) -> None:
        def deliver() -> None:
            if not future.cancelled():  # the SLAM task stopped waiting for it
                settle()

        self._loop.call_later(latency_s, deliver)

    def _hand_over_later(
        self, running: concurrent.futures.Future[Any], latency_s: float
    ) -> concurrent.futures.Future[Any]:
        """A future settled with ``running``'s outcome exactly ``latency_s`` from now on the loop's clock."""
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()

        def hand_over() -> None:
            if future.cancelled():  # the SLAM task stopped waiting (the daemon is stopping)
                return
            wall0_s = time.perf_counter()
            try:  # not done yet: the world waits for the worker (the loop's clock does not move)
                result = running.result(timeout=WORKER_WAIT_MAX_S)
            except concurrent.futures.CancelledError:
                future.cancel()
            except Exception as exc:  # handed over like the worker's own exception (or the wait's timeout)
                future.set_exception(exc)
            else:
                future.set_result(result)
            finally:
                self.worker_wait_s += time.perf_counter() - wall0_s

        self._loop.call_later(latency_s, hand_over)
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """The daemon shuts the inner executor down itself."""
