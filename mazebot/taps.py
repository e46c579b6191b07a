"""Taps: where the product lets someone else watch what it does, without patching it.

The simulator, the benchmark (and a logger on the real robot, one day) need to see the
encoder readings, the notes for the status page and the throttles that reach the motor HAT.
Rather than assigning over the product's methods at run time, each of those objects offers
a small, typed, documented tap: a tuple of listeners it calls with what just happened
(``WheelEncoders.on_read``, ``SharedState.note_listeners``, ``FakeMotorKit.on_write``).

Nobody listening costs one test of an empty tuple. A listener is an observer, never a part
of the robot: whatever it raises is logged (the first time, then every
``LOG_EVERY``-th time per tap) and dropped, so a broken listener can neither stop an
odometry reading nor a fault from being raised nor a motor write from happening.
:func:`notify` is that rule, in one place.

Example::

    encoders.on_read += (lambda reading: readings.append(reading),)
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from typing import Final, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

#: A listener that raises on every call is logged on its first failure and then once every this many.
LOG_EVERY: Final = 1000

#: Failures of the listeners of each tap (by its name), since the process started.
failures: Counter[str] = Counter()


def notify(listeners: tuple[Callable[[T], None], ...], value: T, tap: str) -> None:
    """Call each listener with ``value``; an exception in one is logged and the others still run.

    ``tap`` names the tap in the log line (``"encoders.on_read"``). Callers test the tuple
    first (``if self.on_read: notify(...)``), so an empty tap costs no call.
    """
    for listener in listeners:
        try:
            listener(value)
        except Exception:
            failures[tap] += 1
            if failures[tap] % LOG_EVERY == 1:
                log.exception("a listener of %s failed (%d so far); the robot carries on", tap, failures[tap])
