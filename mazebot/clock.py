"""The one clock every task reads time from.

On the robot and in ``run --sim`` this is the event loop's monotonic clock. Benchmarks
swap in a virtual clock so the same task code runs faster than real time (see
``mazebot.sim``). Tasks must take time from here, never from ``time.time()``.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


class Clock(Protocol):
    """A source of monotonic time in seconds and a way to wait on it."""

    def now_s(self) -> float:
        """Monotonic time in seconds."""
        ...

    async def sleep(self, duration_s: float) -> None:
        """Wait ``duration_s`` seconds of this clock's time."""
        ...


class RealClock:
    """The running event loop's clock; ``sleep`` is ``asyncio.sleep``.

    Reading the loop's ``time()`` (monotonic seconds on a normal loop) rather than
    ``time.monotonic()`` directly is what lets the simulator's virtual-time loop run the
    same task code faster than real time: timers, ``asyncio.sleep`` and this clock all
    move together. Outside a running loop it falls back to ``time.monotonic()``.
    """

    def now_s(self) -> float:
        try:
            return asyncio.get_running_loop().time()
        except RuntimeError:
            return time.monotonic()

    async def sleep(self, duration_s: float) -> None:
        await asyncio.sleep(max(0.0, duration_s))


class Beat:
    """The wake-ups of one periodic task, for tasks that may run in them instead of waking the loop themselves.

    An idle event loop that wakes (a timer due, bytes on a descriptor) pays the kernel's return
    from ``epoll_wait`` and a pass of asyncio's machinery (the timer heap, a handle, a future,
    the task's step) before any task does its own work: 20-45 µs of thread CPU on this machine
    for a bare ``epoll_wait`` wake-up, 70-130 µs for one of asyncio's timer sleeps, caches cold
    after the wait (a Pi 4 core is 3-5 times slower). A task that must run about every period,
    at no particular moment (the control process's outputs taken into the shared state, a
    benchmark's pose log), waits for the odometry task's beat instead of a timer of its own:
    woken by :meth:`tick`, its step runs in the next pass of the same wake-up, with no wait in
    between. The beating task only counts and sets its followers' futures; with none waiting
    it changes nothing else (no handle, no pass of the loop).

    Example::

        beat = Beat()
        beat.tick()                                  # the beating task, once a wake-up
        await beat.wait(2, timeout_s=0.1)            # a follower: two beats on, or 0.1 s without them
    """

    def __init__(self) -> None:
        #: beats so far
        self.count = 0
        self._waiters: list[asyncio.Future[None]] = []

    def tick(self) -> None:
        """One beat: every follower waiting for it is released."""
        self.count += 1
        if self._waiters:
            waiters, self._waiters = self._waiters, []
            for waiter in waiters:
                if not waiter.done():
                    waiter.set_result(None)

    async def wait(self, beats: int, timeout_s: float) -> bool:
        """Return ``beats`` beats from now (True), or ``timeout_s`` of the loop's time from now
        without them (False: the beating task is late or gone; the follower runs on its own time).

        One timer a call for the time-out, cancelled when the beats come first: a cancelled
        timer never wakes the loop (asyncio drops cancelled timers at the head of its heap
        before it computes the wait).
        """
        loop = asyncio.get_running_loop()
        target = self.count + max(1, beats)
        deadline_s = loop.time() + max(0.0, timeout_s)
        while self.count < target:
            waiter = loop.create_future()
            self._waiters.append(waiter)
            timer = loop.call_at(deadline_s, _release, waiter)
            try:
                await waiter
            finally:
                timer.cancel()
                if not waiter.done():  # cancelled from outside
                    waiter.cancel()
                if waiter in self._waiters:
                    self._waiters.remove(waiter)
            if self.count < target and loop.time() >= deadline_s:
                return False
        return True


def _release(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)
