"""Quadrature signals of a simulated wheel, driven onto gpiozero mock pins.

The simulator knows each wheel's true rotation angle; this module turns it into the
edges a real two-channel encoder would produce, one pin change at a time, on
gpiozero's ``MockFactory`` pins. The daemon's real encoder code counts them exactly as
it would count lgpio edges on the robot.

Forward rotation is channel A leading channel B (the usual convention)::

    step:   0   1   2   3   0 …
    A:      0   1   1   0   0
    B:      0   0   1   1   0
"""

from __future__ import annotations

import math

from gpiozero.pins.mock import MockFactory

#: (A, B) levels for each quarter of an encoder line, forward order.
_GRAY = ((0, 0), (1, 0), (1, 1), (0, 1))


class QuadratureSignal:
    """Drives the A/B pins of one encoder from a wheel angle.

    Example::

        signal = QuadratureSignal(factory, a_pin=17, b_pin=18, lines_per_rev=210)
        signal.update(wheel_angle_rad=math.pi)   # half a turn: 420 edges
    """

    def __init__(
        self, factory: MockFactory, a_pin: int, b_pin: int, lines_per_rev: int, *, idle_high: bool = True
    ) -> None:
        if lines_per_rev <= 0:
            raise ValueError(f"lines_per_rev must be positive, got {lines_per_rev}")
        self._a = factory.pin(a_pin)
        self._b = factory.pin(b_pin)
        self._steps_per_rad = 4 * lines_per_rev / math.tau
        # Start where the pins rest when the encoder driver enables its pull resistors
        # (both high with pull-ups), so claiming the pins later changes nothing.
        self._offset = 2 if idle_high else 0
        self._step = 0
        self.edges = 0  # edges driven so far, for tests and stats
        self._drive(_GRAY[self._offset])

    def _drive(self, levels: tuple[int, int]) -> None:
        for pin, level in ((self._a, levels[0]), (self._b, levels[1])):
            if pin.state != level:
                if level:
                    pin.drive_high()
                else:
                    pin.drive_low()

    def update(self, wheel_angle_rad: float) -> int:
        """Emit every edge between the last angle and this one; returns how many."""
        target = math.floor(wheel_angle_rad * self._steps_per_rad)
        n = target - self._step
        direction = 1 if n > 0 else -1
        for _ in range(abs(n)):
            self._step += direction
            a, b = _GRAY[(self._step + self._offset) % 4]
            # exactly one channel changes per quarter step
            pin, level = (self._a, a) if self._a.state != a else (self._b, b)
            if level:
                pin.drive_high()
            else:
                pin.drive_low()
        self.edges += abs(n)
        return n
