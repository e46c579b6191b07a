"""An asyncio event loop whose clock jumps ahead instead of waiting.

Benchmarks run the daemon's real task code against the simulator with no real I/O
(the lidar talks over in-memory streams, the encoders are mock pins). Every wait in
such a run is a timer, so when nothing is ready the loop can advance its clock straight
to the next timer instead of sleeping: the run goes as fast as the CPU allows, and the
order of events is exactly the one real time would give. Sockets still work (the
selector is polled without blocking), but their timing becomes meaningless, so the web
server is not started on this loop. Work handed to an executor takes no virtual time.

A :class:`SlowCpu` makes the same loop behave like a slower computer, deterministically:
every callback of the daemon's tasks costs a fixed amount of virtual time (the clock
moves on while it "runs", and everything else waits, as on a busy core), and every so
often the loop stalls for a while with nothing running (a garbage-collector pause, a
throttled cgroup period, another process on the core). The simulated world's own tasks
cost nothing: its physics integrates whatever time passed, so the robot keeps driving at
its last throttle through a stall, as a real one would.
"""

from __future__ import annotations

import asyncio
import selectors
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

#: Virtual time one pass of the event loop takes.
LOOP_PASS_S = 1e-6
#: With no file descriptor but its self-pipe, the loop polls the selector only this often.
DRAIN_EVERY_PASSES = 64


class _JumpingSelector(selectors.DefaultSelector):
    """A selector that polls without blocking and moves the loop's clock instead."""

    def __init__(self, loop_ref: list[VirtualTimeLoop]) -> None:
        super().__init__()
        self._loop_ref = loop_ref
        self._passes = 0

    def select(self, timeout: float | None = None) -> list[tuple[Any, int]]:
        if timeout is None:  # no timer pending: only I/O (an executor job) can wake us
            return super().select(None)
        self._passes += 1
        # With nothing but the loop's self-pipe registered, a poll could only drain that
        # pipe, and the callbacks it announces (executor results) are queued in the
        # loop already, so they run on time without it. Skipping the system call
        # matters at ~1000 passes per simulated second; the pipe is drained every
        # DRAIN_EVERY_PASSES passes so it never fills.
        only_self_pipe = len(self.get_map()) <= 1
        events = [] if only_self_pipe and self._passes % DRAIN_EVERY_PASSES else super().select(0)
        # Every pass of the loop costs a little time, as on a real clock; without it a
        # task that polls with waits shorter than float resolution would never see the
        # clock move, and the run would spin for ever at one instant.
        step_s = timeout if (not events and timeout > 0) else 0.0
        self._loop_ref[0].advance(max(step_s, LOOP_PASS_S))
        return events


@dataclass(frozen=True)
class SlowCpu:
    """How much slower than this machine a virtual-time run behaves (see the module docstring).

    ``callback_cost_s`` virtual seconds pass during each callback of a task not named in
    ``free_tasks`` (nor starting with one of ``free_prefixes``); every ``stall_every_s``
    the loop stalls, each stall taking the next of ``stalls_s`` in turn.
    """

    callback_cost_s: float = 0.0
    stall_every_s: float = 0.0
    stalls_s: tuple[float, ...] = ()
    free_tasks: tuple[str, ...] = ("simulator", "lidar-emulator-stream")
    free_prefixes: tuple[str, ...] = ("bench-", "sim-")

    def costs(self, task_name: str) -> bool:
        """True when callbacks of the task called ``task_name`` take ``callback_cost_s``."""
        return task_name not in self.free_tasks and not task_name.startswith(self.free_prefixes)


#: A Pi-class computer under load (``mazebot bench --slow-cpu``, the timing-independence test):
#: ~4.5 ms of virtual time per task step (the daemon makes ~400 steps per simulated second on
#: this machine, so the loop is busy most of the time and SLAM falls behind the lidar now and
#: then), and a stall every 3 s of 0.1, 0.25 and 0.15 s in turn (0.23 s was measured under a
#: 25 % CPU quota here).
PI_CLASS_CPU = SlowCpu(callback_cost_s=0.0045, stall_every_s=3.0, stalls_s=(0.1, 0.25, 0.15))


class VirtualTimeLoop(asyncio.SelectorEventLoop):
    """A selector event loop on virtual time, starting at ``start_s``.

    Example::

        loop = VirtualTimeLoop()
        loop.run_until_complete(asyncio.sleep(3600))   # returns at once
        loop.time()  # 3600.0
    """

    def __init__(self, start_s: float = 0.0, slow: SlowCpu | None = None) -> None:
        ref: list[VirtualTimeLoop] = []
        super().__init__(selector=_JumpingSelector(ref))
        ref.append(self)
        self._now_s = start_s
        self.slow = slow
        #: virtual seconds the loop stood still in stalls, and callbacks that paid ``callback_cost_s``
        self.stalled_s = 0.0
        self.costly_callbacks = 0
        self._stall_count = 0
        if slow is not None and slow.stall_every_s > 0 and slow.stalls_s:
            super().call_at(start_s + slow.stall_every_s, self._stall)

    def call_soon(  # type: ignore[override]  # typeshed's signature is generic over the callback's arguments
        self, callback: Callable[..., Any], *args: Any, context: Any = None
    ) -> asyncio.Handle:
        """As usual; with a :class:`SlowCpu`, a step of a costly task also moves the clock on."""
        slow = self.slow
        if slow is not None and slow.callback_cost_s > 0:
            task = getattr(callback, "__self__", None)  # a task's step or wake-up
            if isinstance(task, asyncio.Task) and slow.costs(task.get_name()):
                return super().call_soon(self._costly, callback, *args, context=context)
        return super().call_soon(callback, *args, context=context)

    def _costly(self, callback: Callable[..., Any], *args: Any) -> None:
        try:
            callback(*args)
        finally:
            assert self.slow is not None
            self.costly_callbacks += 1
            self.advance(self.slow.callback_cost_s)

    def _stall(self) -> None:
        slow = self.slow
        assert slow is not None
        stall_s = slow.stalls_s[self._stall_count % len(slow.stalls_s)]
        self._stall_count += 1
        self.stalled_s += stall_s
        self.advance(stall_s)
        super().call_at(self._now_s + slow.stall_every_s, self._stall)

    def time(self) -> float:
        return self._now_s

    def advance(self, duration_s: float) -> None:
        """Move the clock forward; only the loop itself calls this, when it is idle."""
        self._now_s += duration_s


def run_virtual(coro: Any, start_s: float = 0.0, slow: SlowCpu | None = None) -> Any:
    """``asyncio.run`` on virtual time (as on a slower computer with ``slow``)."""
    loop = VirtualTimeLoop(start_s, slow)
    try:
        asyncio.set_event_loop(loop)
        return loop.run_until_complete(coro)
    finally:
        asyncio.set_event_loop(None)
        loop.run_until_complete(loop.shutdown_asyncgens())
        loop.close()
