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
from time import monotonic

from gpiozero.pins.mock import MockPin, PinState


class BoundedHistoryPin(MockPin):
    """A ``MockPin`` whose ``states`` history keeps only the most recent changes."""

    #: Changes kept in ``states`` (the initial state counts as one).
    HISTORY = 64
    _state: bool  # MockPin's level (gpiozero has no type information)

    def clear_states(self) -> None:
        self._last_change = monotonic()
        self.states = deque([PinState(0.0, self._state)], maxlen=self.HISTORY)

    def _change_state(self, value: bool) -> bool:
        # MockPin._change_state with the history bounded by the deque
        if self._state != value:
            t = monotonic()
            self._state = value
            self.states.append(PinState(t - self._last_change, value))
            self._last_change = t
            return True
        return False
