"""Watches the sensors for the faults a task cannot see from inside: silence and dead wires.

- **Lidar silence**: no revolution for ``lidar_silence_s`` (a revolution takes 0.18 s) means
  the robot no longer knows what is in front of it: a ``lidar`` fault, so the control task
  stops the wheels within one control period. The driver reconnects by itself; the
  fault clears with the first new revolution.
- **Dead encoder**: a wheel whose motor has been driven well above the deadband for
  ``encoder_dead_s`` while its tick count did not move, and the other wheel's did: a
  cut encoder wire. Odometry is then wrong, so this is a fault too; it is latched (the
  evidence only exists while driving) and the user's next start gives it another try.

- **Bouncing encoders**: impossible transitions (a contact bouncing, an edge lost) are
  counted by the decoders; new ones are said in ``/api/status`` (an ``encoders``
  event, at most every ``NOTE_EVERY_S``). The wheels go on: SLAM corrects the odometry.
- **Weak motor**: per wheel, the measured speed for the throttle given; a wheel that
  runs at less than ``weak_ratio`` of the other's for the same throttle, for
  ``weak_checks`` checks in a row, is said (a ``motors`` event): the wheel controller
  makes up for it, but a gearbox or a motor is failing.

All are plain checks on ``SharedState`` at 10 Hz; they never touch a device.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from mazebot.clock import Clock
from mazebot.state import SharedState

log = logging.getLogger(__name__)

#: How often the checks run.
PERIOD_S = 0.1
#: Ticks the other wheel must have counted for a silent encoder to be suspicious.
OTHER_WHEEL_TICKS = 40
#: Wheels slower than this, or driven less than this throttle above the deadband (where the
#: deadband's estimate and the motor's lag decide the speed: an open-loop arc's inner wheel
#: at 0.14 looked like a motor at 35 %), tell nothing about their motor's strength. 0.12 kept
#: a turn in place at 0.18-0.20 out of the check until 300 ms after a weak motor began.
MIN_WHEEL_SPEED_MPS = 0.015
WEAK_CHECK_EFFECTIVE_THROTTLE = 0.10
#: A wheel whose speed changed by more than this share since the previous check is still
#: following a new throttle (the motor's lag: a turn in place reversing one wheel showed it
#: at 18 % of its throttle's speed for two checks, changing by 70-340 % a check), and tells
#: nothing about its strength. 20 % also held back a really weak motor whose wheel control
#: was still pushing it harder (said after 600 ms instead of 300).
STEADY_SPEED_SHARE = 0.5
#: While any fault is active, and this long after the last one cleared, the wheels are held
#: or starting again from rest (the motors' lag, half-failed throttle writes): their speeds
#: tell nothing about a motor's strength. Without it the fault suite said a weak motor in
#: the runs of lidar-motor-stop, motor-i2c and slam-raise.
FAULT_SETTLE_S = 1.0
#: Events about the same trouble (bouncing encoders, a weak motor) at most this often.
NOTE_EVERY_S = 5.0


@dataclass
class _Wheel:
    since_s: float | None = None  # when the current stretch of "driven but silent" began
    ticks: int = 0  # the tick count at its start
    other_ticks: int = 0


class HealthMonitor:
    """The checks, one call per period (see the module docstring)."""

    def __init__(
        self,
        lidar_silence_s: float = 0.4,
        startup_grace_s: float = 5.0,
        encoder_dead_s: float = 0.2,
        driven_throttle: float = 0.15,
        motor_deadband: float = 0.08,
        weak_ratio: float = 0.5,
        weak_checks: int = 2,
    ) -> None:
        self.lidar_silence_s = float(lidar_silence_s)
        self.startup_grace_s = float(startup_grace_s)
        self.encoder_dead_s = float(encoder_dead_s)
        self.driven_throttle = float(driven_throttle)
        self.motor_deadband = float(motor_deadband)
        self.weak_ratio = float(weak_ratio)
        self.weak_checks = int(weak_checks)
        self._started_s: float | None = None
        self._wheels = (_Wheel(), _Wheel())
        self._invalid_seen = 0
        self._weak_streak = [0, 0]
        self._fault_seen_s: float | None = None  # the last check that saw an active fault
        self._last_speeds_mps: tuple[float, ...] | None = None
        self._last_note_s: dict[str, float] = {}

    def check(self, state: SharedState, now_s: float) -> None:
        if self._started_s is None:
            self._started_s = now_s
        self._check_lidar(state, now_s)
        self._check_encoders(state, now_s)
        self._check_bounce(state, now_s)
        self._check_motor_strength(state, now_s)

    def _note(self, state: SharedState, source: str, message: str, now_s: float) -> None:
        last_s = self._last_note_s.get(source)
        if last_s is not None and now_s - last_s < NOTE_EVERY_S:
            return
        self._last_note_s[source] = now_s
        log.warning("%s", message)
        state.note(source, message, now_s)

    def _check_bounce(self, state: SharedState, now_s: float) -> None:
        invalid = state.sensors.encoder_invalid_transitions
        new, self._invalid_seen = invalid - self._invalid_seen, invalid
        if new > 0:
            self._note(state, "encoders", f"the wheel encoders reported {new} impossible transitions in "
                       f"{PERIOD_S:g} s (bouncing contacts or lost edges, {invalid} so far): the odometry may "
                       "drift, SLAM corrects it; check the encoder wiring", now_s)

    def _check_motor_strength(self, state: SharedState, now_s: float) -> None:
        """Speed per effective throttle of each wheel; one far below the other is a weak motor.

        Only wheels in steady motion count: turning the way they are pushed, well above the
        deadband, at about the speed of the previous check.
        """
        gains = []
        last = self._last_speeds_mps or tuple(state.wheel_speeds_mps)
        self._last_speeds_mps = tuple(state.wheel_speeds_mps)
        if state.faults:
            self._fault_seen_s = now_s
        if self._fault_seen_s is not None and now_s - self._fault_seen_s < FAULT_SETTLE_S:
            self._weak_streak = [0, 0]
            return
        for throttle, speed, last_speed in zip(state.throttles, state.wheel_speeds_mps, last, strict=True):
            effective = abs(throttle) - self.motor_deadband
            driven = (
                effective >= WEAK_CHECK_EFFECTIVE_THROTTLE
                and abs(speed) >= MIN_WHEEL_SPEED_MPS
                and throttle * speed > 0
                and abs(speed - last_speed) <= STEADY_SPEED_SHARE * abs(speed)
            )
            gains.append(abs(speed) / effective if driven else None)
        if gains[0] is None or gains[1] is None or max(gains) <= 0:
            self._weak_streak = [0, 0]
            return
        for side in (0, 1):
            ratio = gains[side] / gains[1 - side] if gains[1 - side] > 0 else 1.0
            weak = ratio < self.weak_ratio
            self._weak_streak[side] = self._weak_streak[side] + 1 if weak else 0
            if self._weak_streak[side] >= self.weak_checks:
                name = ("left", "right")[side]
                share = 100 * gains[side] / gains[1 - side]
                self._note(state, "motors", f"the {name} motor gives only {share:.0f} % of the other's speed for "
                           "the same throttle: the wheel control makes up for it; check that motor, its gearbox "
                           "and its wires", now_s)

    def _check_lidar(self, state: SharedState, now_s: float) -> None:
        scan = state.latest_scan
        last_s = scan.end_time_s if scan is not None else self._started_s + self.startup_grace_s  # type: ignore[operator]
        silent_s = now_s - last_s
        active = any(f.source == "lidar" for f in state.faults)
        if silent_s > self.lidar_silence_s:
            if not active:
                what = "no lidar data yet" if scan is None else f"no lidar data for {silent_s:.1f} s"
                message = f"{what}: check the lidar's USB cable and power; reconnecting by itself"
                log.warning("%s", message)
                state.raise_fault("lidar", message, now_s)
        elif active:
            state.clear_faults("lidar")
            state.note("lidar", "lidar data flows again", now_s)
            log.info("lidar data flows again")

    def _check_encoders(self, state: SharedState, now_s: float) -> None:
        ticks = (state.sensors.encoder_ticks_left, state.sensors.encoder_ticks_right)
        for side, (wheel, name) in enumerate(zip(self._wheels, ("left", "right"), strict=True)):
            driven = abs(state.throttles[side]) >= self.driven_throttle
            mine, other = ticks[side], ticks[1 - side]
            if not driven or mine != wheel.ticks:
                wheel.since_s = now_s if driven else None
                wheel.ticks, wheel.other_ticks = mine, other
                continue
            if wheel.since_s is None:
                wheel.since_s, wheel.other_ticks = now_s, other
                continue
            if now_s - wheel.since_s >= self.encoder_dead_s and abs(other - wheel.other_ticks) >= OTHER_WHEEL_TICKS:
                message = (
                    f"the {name} wheel's encoder counted nothing for {now_s - wheel.since_s:.1f} s while its motor "
                    "drove: check the encoder's wires; press start to try again"
                )
                log.warning("%s", message)
                state.raise_fault("encoders", message, now_s, latched=True)
                wheel.since_s = None


async def run(state: SharedState, clock: Clock, monitor: HealthMonitor) -> None:
    while True:
        monitor.check(state, clock.now_s())
        await clock.sleep(PERIOD_S)
