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
import random

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
        #: the cable is cut: the pins keep their level whatever the wheel does
        self.dead = False
        #: per edge, the chance of contact bounce (the edge is followed by a quick back-and-forth)
        #: and of a lost edge (the pin changes while nobody is told: the next edge is impossible)
        self.bounce_probability = 0.0
        self.lost_edge_probability = 0.0
        self.rng: random.Random | None = None
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
        if self.dead:
            self._step = target  # the wheel turns; the pins do not follow
            return 0
        if self.rng is not None and (self.bounce_probability or self.lost_edge_probability):
            return self._update_glitching(target)
        step = self._step
        n = target - step
        if n == 0:
            return 0
        # One pin change per quarter step, in order, as before; locals and the pins' own
        # level attribute instead of attribute lookups and the ``state`` property per edge
        # (~1 300 edges per simulated second go through here).
        pin_a, pin_b, offset = self._a, self._b, self._offset
        for s in range(step + 1, target + 1) if n > 0 else range(step - 1, target - 1, -1):
            a, b = _GRAY[(s + offset) & 3]
            # exactly one channel changes per quarter step
            if pin_a._state != a:
                if a:
                    pin_a.drive_high()
                else:
                    pin_a.drive_low()
            elif b:
                pin_b.drive_high()
            else:
                pin_b.drive_low()
        self._step = target
        self.edges += abs(n)
        return n

    def _update_glitching(self, target: int) -> int:
        """``update`` with bouncing contacts and lost edges (fault injection)."""
        assert self.rng is not None
        n = target - self._step
        direction = 1 if n > 0 else -1
        for _ in range(abs(n)):
            self._step += direction
            a, b = _GRAY[(self._step + self._offset) % 4]
            pin, level = (self._a, a) if self._a.state != a else (self._b, b)
            if self.rng.random() < self.lost_edge_probability:
                # the level changes without an interrupt: the reader never hears of this edge
                pin._change_state(bool(level))
                continue
            self._set(pin, level)
            if self.rng.random() < self.bounce_probability:
                self._set(pin, 1 - level)  # the contact bounces back ...
                self._set(pin, level)  # ... and settles
        self.edges += abs(n)
        return n

    @staticmethod
    def _set(pin, level: int) -> None:
        if level:
            pin.drive_high()
        else:
            pin.drive_low()
