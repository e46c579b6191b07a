"""Quadrature signals of a simulated wheel, driven onto gpiozero mock pins.

The simulator knows each wheel's true rotation angle; this module turns it into the
edges a real two-channel encoder would produce, one pin change at a time, on
gpiozero's ``MockFactory`` pins. The daemon's real encoder code counts them exactly as
it would count lgpio edges on the robot.

Forward rotation is channel A leading channel B (the usual convention)::

    step:   0   1   2   3   0 …
    A:      0   1   1   0   0
    B:      0   0   1   1   0

Each edge has its own time, as on the robot, where the kernel stamps every line event and
lgpio hands the events of all lines to one thread in the order of their stamps: the
simulator steps the physics every few milliseconds, and :meth:`QuadratureSignal.edges_to`
says where within a step each quarter step was crossed (the wheel's angle taken as linear
over the step), so the robot can drive both wheels' edges in time order, each stamped
where it happened (:meth:`mazebot.sim.robot.SimulatedRobot.step`).
"""

from __future__ import annotations

import math
import random

from gpiozero.pins.mock import MockFactory, MockPin

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
        self._factory = factory
        self._a = factory.pin(a_pin)
        self._b = factory.pin(b_pin)
        self._steps_per_rad = 4 * lines_per_rev / math.tau
        # Start where the pins rest when the encoder driver enables its pull resistors
        # (both high with pull-ups), so claiming the pins later changes nothing.
        self._offset = 2 if idle_high else 0
        self._step = 0
        self._angle_rad = 0.0  # the angle of the last update: where the next step's edges start
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

    def edges_to(self, wheel_angle_rad: float) -> list[tuple[float, int]]:
        """The quarter steps between the last angle and this one, not yet driven: ``(share, step)``
        each, oldest first, ``share`` the part of the way from the last angle (0, 1] at which the
        wheel crossed into ``step``. Drive them with :meth:`emit`, in this order (with another
        wheel's in between, by their shares: :meth:`mazebot.sim.robot.SimulatedRobot.step`).

        Example::

            for share, step in signal.edges_to(angle):
                signal.emit(step, time_s=start_s + share * (end_s - start_s))
        """
        scaled, start = wheel_angle_rad * self._steps_per_rad, self._angle_rad * self._steps_per_rad
        self._angle_rad = wheel_angle_rad
        target = math.floor(scaled)
        step, span = self._step, scaled - start
        if target == step:
            return []
        if self.dead:
            self._step = target  # the wheel turns; the pins do not follow
            return []
        if target > step:  # forward: step s is entered where the scaled angle reaches s
            return [(min(1.0, max(0.0, (s - start) / span)), s) for s in range(step + 1, target + 1)]
        # backward: step s is entered where the scaled angle falls below s + 1
        return [(min(1.0, max(0.0, (s + 1 - start) / span)), s) for s in range(step - 1, target - 1, -1)]

    def emit(self, step: int, time_s: float | None = None) -> None:
        """Drive the one channel that changes to enter ``step`` (one from the last step driven: from
        :meth:`edges_to`), with its bounce or loss if those are injected; ``time_s``: the edge's
        time on a :class:`mazebot.sim.sim_pins.SimPinFactory` (None: the time it is driven)."""
        self._step = step
        self.edges += 1
        a, b = _GRAY[(step + self._offset) & 3]
        pin, level = (self._a, a) if self._a.state != a else (self._b, b)  # exactly one channel changes
        rng = self.rng
        if rng is not None and self.lost_edge_probability and rng.random() < self.lost_edge_probability:
            pin._change_state(bool(level))  # the level changes without an interrupt: nobody hears of this edge
            return
        self._set(pin, level, time_s)
        if rng is not None and self.bounce_probability and rng.random() < self.bounce_probability:
            self._set(pin, 1 - level, time_s)  # the contact bounces back ...
            self._set(pin, level, time_s)  # ... and settles

    def update(self, wheel_angle_rad: float) -> int:
        """Emit every edge between the last angle and this one, now; returns how many (signed)."""
        before = self._step
        for _, step in self.edges_to(wheel_angle_rad):
            self.emit(step)
        return 0 if self.dead else self._step - before

    def _set(self, pin: MockPin, level: int, time_s: float | None = None) -> None:
        drive = getattr(self._factory, "drive", None) if time_s is not None else None
        if drive is not None:
            drive(pin, level, time_s)
        elif level:
            pin.drive_high()
        else:
            pin.drive_low()
