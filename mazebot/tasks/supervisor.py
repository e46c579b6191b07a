"""Runs every task of the daemon and decides what a crash or a signal means.

A task that raises must never leave a motor turning: the supervisor zeroes the motors
first, then records the fault in the shared state (the web page shows it), logs the
traceback once, and keeps the other tasks (and the web server) running, unless the
configuration asks the daemon to exit on faults. Tasks started with ``restart=True`` (the
daemon's own) are started again after a back-off that doubles with each crash; once a
restarted task has run for ``healthy_after_s`` its fault clears (and the back-off resets),
so a device fault never ends the process. A stop request (SIGINT/SIGTERM)
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

#: First restart delay of a crashed task, doubled per crash up to ``RESTART_MAX_S``.
RESTART_MIN_S = 0.5
RESTART_MAX_S = 10.0
#: A restarted task that has run this long is healthy again: its fault clears.
HEALTHY_AFTER_S = 3.0


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
        self,
        state: SharedState,
        motors: Stoppable,
        clock: Clock,
        *,
        exit_on_fault: bool,
        restart_min_s: float = RESTART_MIN_S,
        healthy_after_s: float = HEALTHY_AFTER_S,
    ) -> None:
        self._state = state
        self._motors = motors
        self._clock = clock
        self._exit_on_fault = exit_on_fault
        self._tasks: dict[str, asyncio.Task[None]] = {}
        self._factories: dict[str, tuple[TaskFactory, bool]] = {}
        self._crashes: dict[str, int] = {}  # consecutive crashes per task (the back-off)
        self.restart_min_s = restart_min_s
        self.healthy_after_s = healthy_after_s
        self.restarts = 0
        self._stopped = asyncio.Event()
        self._exit_code = EXIT_OK

    @property
    def tasks(self) -> dict[str, asyncio.Task[None]]:
        return dict(self._tasks)

    def start(self, name: str, factory: TaskFactory, *, restart: bool = False) -> None:
        """Start ``factory()`` as task ``name``; its crash becomes a fault, never silence.

        With ``restart`` a crashed task is started again (a new ``factory()``) after a
        back-off; whatever must survive a restart (the map, the odometry) lives outside it.
        """
        if name in self._tasks and not self._tasks[name].done():
            raise ValueError(f"task {name!r} is already running")
        self._factories[name] = (factory, restart)
        self._launch(name)

    def _launch(self, name: str) -> asyncio.Task[None]:
        task = asyncio.create_task(self._factories[name][0](), name=name)
        self._tasks[name] = task
        task.add_done_callback(self._on_done)
        return task

    def stop_motors(self) -> None:
        """Zero the motors now; a failure to do so is logged loudly, never swallowed quietly."""
        try:
            self._motors.stop()
        except Exception:
            log.critical("could not stop the motors", exc_info=True)

    def request_stop(self, reason: str = "stop requested", exit_code: int = EXIT_OK) -> None:
        """Zero the motors at once, then let ``wait()`` cancel the tasks and return."""
        self._state.stopping = True  # the control loop must not drive them again meanwhile
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
        restart = self._factories[name][1] and not self._exit_on_fault
        crashes = self._crashes.get(name, 0)
        delay_s = min(RESTART_MAX_S, self.restart_min_s * 2**crashes)
        then = f"restarting in {delay_s:g} s" if restart else "not restarted"
        self._state.raise_fault(
            name, f"task {name} crashed ({reason}); motors stopped, {then}", self._clock.now_s()
        )
        if crashes == 0:  # the traceback once per series of crashes, not every back-off
            log.error("task %s crashed; motors stopped", name, exc_info=exc)
        else:
            log.error("task %s crashed again (%s)", name, reason)
        if self._exit_on_fault:
            self.request_stop(f"task {name} crashed and daemon.exit_on_fault is set", EXIT_SOFTWARE)
        elif restart:
            self._crashes[name] = crashes + 1
            asyncio.get_running_loop().call_later(delay_s, self._restart, name)

    def _restart(self, name: str) -> None:
        if self._stopped.is_set():
            return
        self.restarts += 1
        log.info("restarting task %s", name)
        task = self._launch(name)
        asyncio.get_running_loop().call_later(self.healthy_after_s, self._check_healthy, name, task)

    def _check_healthy(self, name: str, task: asyncio.Task[None]) -> None:
        if task.done() or self._stopped.is_set() or self._tasks.get(name) is not task:
            return
        self._crashes[name] = 0
        self._state.clear_faults(name)
        self._state.note(name, f"task {name} is running again", self._clock.now_s())
        log.info("task %s is running again", name)

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
