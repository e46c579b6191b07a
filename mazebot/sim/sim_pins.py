"""gpiozero mock pins for long simulations: the same pins, with a bounded edge history.

gpiozero's ``MockPin`` records every state change in ``pin.states`` (a list that only
grows) so that tests can assert on the sequence of levels. The simulator drives about
3 000 edges per second on the four encoder pins; over a 16×16 maze tour (tens of
millions of edges) that list alone grew the process by hundreds of megabytes.

``BoundedHistoryPin`` is a ``MockPin`` in every other respect: same state handling, same
``when_changed`` dispatch (so the real encoder code is called exactly as before), same
test controls (``drive_high``, ``drive_low``, ``states``, ``assert_states``); only
``states`` keeps the last ``HISTORY`` changes instead of all of them.

Example::

    factory = MockFactory(pin_class=BoundedHistoryPin)
    pin = factory.pin(17)
    for _ in range(10_000):
        pin.drive_low()
        pin.drive_high()
    len(pin.states)   # HISTORY, not 20 001
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from time import monotonic

from gpiozero.pins.mock import MockFactory, MockPin, PinState


class SimPinFactory(MockFactory):
    """A ``MockFactory`` whose clock is the simulator's, and whose driven edges carry their own time.

    On the robot lgpio stamps every edge where it happens (the kernel's line event) and
    gpiozero hands that stamp to the pin callback; the wheel encoders keep it so odometry
    is dated by when the wheels turned, not by when a busy process got round to the edge
    (:mod:`mazebot.io.encoders`). gpiozero's own mock pins stamp an edge with the time it is
    driven, on the real monotonic clock. Here:

    - ``time_source`` is the clock of ``ticks()`` and of every edge driven without a time
      (the virtual clock in ``run --sim`` and the virtual-clock benchmarks, where the world
      drives the pins as it steps);
    - :meth:`drive` drives an edge at a given time: the daemon's GPIO thread of the quota
      benchmark (:class:`mazebot.sim.remote_devices.GpioEdgeThread`) replays the world's
      edges with the time the world made them, as the kernel's stamps would be.

    Example::

        factory = SimPinFactory(pin_class=BoundedHistoryPin, time_source=clock.now_s)
        factory.drive(factory.pin(17), 0, time_s=12.5)   # the callback sees ticks == 12.5
    """

    def __init__(self, *args: object, time_source: Callable[[], float] = monotonic, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)
        self.time_source = time_source
        self._event_time_s: float | None = None

    def ticks(self) -> float:  # an instance's clock, not gpiozero's static one
        return self.time_source()

    def edge_time(self) -> float:
        """The time stamp of the edge being driven now."""
        return self.time_source() if self._event_time_s is None else self._event_time_s

    def drive(self, pin: MockPin, level: int, time_s: float) -> None:
        """Drive ``pin`` to ``level`` as an edge that happened at ``time_s`` (on ``time_source``'s clock)."""
        self._event_time_s = time_s
        try:
            if level:
                pin.drive_high()
            else:
                pin.drive_low()
        finally:
            self._event_time_s = None


class BoundedHistoryPin(MockPin):
    """A ``MockPin`` whose ``states`` history keeps only the most recent changes."""

    #: Changes kept in ``states`` (the initial state counts as one).
    HISTORY = 64
    _state: bool  # MockPin's level (gpiozero has no type information)

    def clear_states(self) -> None:
        self._last_change = self._now()
        self.states = deque([PinState(0.0, self._state)], maxlen=self.HISTORY)

    def _now(self) -> float:
        """The edge's time: the :class:`SimPinFactory`'s, else (a plain ``MockFactory``) gpiozero's monotonic clock."""
        edge_time = getattr(self._factory, "edge_time", None)
        return monotonic() if edge_time is None else float(edge_time())

    def _change_state(self, value: bool) -> bool:
        # MockPin._change_state with the history bounded by the deque, stamped by the factory's clock
        if self._state != value:
            t = self._now()
            self._state = value
            self.states.append(PinState(t - self._last_change, value))
            self._last_change = t
            return True
        return False
