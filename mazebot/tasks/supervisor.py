"""Runs every task of the daemon and decides what a crash or a signal means.

A task that raises must never leave a motor turning: the supervisor zeroes the motors
first, then records the fault in the shared state (the web page shows it), logs the
traceback once, and keeps the other tasks (and the web server) running, unless the
configuration asks the daemon to exit on faults. A stop request (SIGINT/SIGTERM)
zeroes the motors synchronously, before anything is cancelled, so the wheels stop
within the signal handler's own latency.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine
from typing import Any, Protocol

from mazebot.clock import Clock
from mazebot.errors import EXIT_OK, EXIT_SOFTWARE
from mazebot.state import SharedState

log = logging.getLogger(__name__)

TaskFactory = Callable[[], Coroutine[Any, Any, None]]


class Stoppable(Protocol):
    """Anything that can bring the motors to zero immediately (the motor driver)."""

    def stop(self) -> None: ...


class Supervisor:
    """Starts named tasks, watches them, and stops everything safely.

    Example::

        sup = Supervisor(state, motors, clock, exit_on_fault=False)
        sup.start("lidar", lambda: lidar_task(...))
        exit_code = await sup.wait()   # returns after request_stop() or a fatal fault
    """

    def __init__(
        self, state: SharedState, motors: Stoppable, clock: Clock, *, exit_on_fault: bool
    ) -> None:
        self._state = state
        self._motors = motors
        self._clock = clock
        self._exit_on_fault = exit_on_fault
        self._tasks: dict[str, asyncio.Task[None]] = {}
        self._stopped = asyncio.Event()
        self._exit_code = EXIT_OK

    @property
    def tasks(self) -> dict[str, asyncio.Task[None]]:
        return dict(self._tasks)

    def start(self, name: str, factory: TaskFactory) -> None:
        """Start ``factory()`` as task ``name``; its crash becomes a fault, never silence."""
        if name in self._tasks and not self._tasks[name].done():
            raise ValueError(f"task {name!r} is already running")
        task = asyncio.create_task(factory(), name=name)
        self._tasks[name] = task
        task.add_done_callback(self._on_done)

    def stop_motors(self) -> None:
        """Zero the motors now; a failure to do so is logged loudly, never swallowed quietly."""
        try:
            self._motors.stop()
        except Exception:
            log.critical("could not stop the motors", exc_info=True)

    def request_stop(self, reason: str = "stop requested", exit_code: int = EXIT_OK) -> None:
        """Zero the motors at once, then let ``wait()`` cancel the tasks and return."""
        self.stop_motors()
        if not self._stopped.is_set():
            log.info("stopping: %s", reason)
            self._exit_code = exit_code
            self._stopped.set()

    def _on_done(self, task: asyncio.Task[None]) -> None:
        if task.cancelled() or self._stopped.is_set():
            return
        name = task.get_name()
        exc = task.exception()
        if exc is None:
            log.debug("task %s finished", name)
            return
        self.stop_motors()
        reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        self._state.raise_fault(name, f"task {name} crashed ({reason}); motors stopped", self._clock.now_s())
        log.error("task %s crashed; motors stopped", name, exc_info=exc)
        if self._exit_on_fault:
            self.request_stop(f"task {name} crashed and daemon.exit_on_fault is set", EXIT_SOFTWARE)

    async def wait(self) -> int:
        """Block until a stop is requested, then cancel every task; returns the exit code."""
        try:
            await self._stopped.wait()
        finally:
            self.stop_motors()
            await self.cancel_all()
            self.stop_motors()
        return self._exit_code

    async def cancel_all(self) -> None:
        pending = [t for t in self._tasks.values() if not t.done()]
        for t in pending:
            t.cancel()
        if pending:
            await asyncio.gather(*pending, return_exceptions=True)
