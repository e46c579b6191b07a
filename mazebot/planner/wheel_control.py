"""From body velocity to motor throttles: kinematics, per-wheel PI(D), in-place turns.

The local planner asks for a body velocity ``(v, ω)``; the motors take a throttle in
[−1, 1]. In between:

1. **Kinematics** (:class:`DiffDriveKinematics`): wheel surface speeds
   ``v_l = v − ω b/2``, ``v_r = v + ω b/2`` (Siegwart, Nourbakhsh & Scaramuzza,
   *Introduction to Autonomous Mobile Robots*, 2nd ed., 3.2), scaled down together when
   one exceeds the wheel limit so the curvature (the path) is kept.

2. **Per-wheel speed control** (:class:`WheelPid`) on the speed measured by the encoders
   (:class:`WheelSpeedEstimator`): a feed-forward that inverts the motor's static map
   (throttle below the deadband does nothing, above it speed grows linearly to
   ``max_wheel_speed_mps``), so the controller starts from the right throttle instead
   of winding up to it, plus PI(D) feedback for what the model misses (unmatched
   motors, battery sag, load). The integral is clamped and frozen while the output
   saturates (anti-windup, Åström & Hägglund, *Advanced PID Control*, 2006, 3.5), the
   derivative acts on the measurement (no kick on setpoint steps), and the integral is
   reset whenever the drive mode changes: a lesson of Gao, Ge, Yong and D'Cruz,
   *Autonomous SLAM Robot* (MECHENG 706 report, 2015; 3.2.5, 7.1), whose
   robot kept veering after a turn because the rotation integral was never cleared.

3. **Setpoint ramps**: wheel targets are rate-limited to the acceleration the motors can
   deliver. A step the motor cannot follow only winds the integral up and overshoots
   once the lagging wheel catches up; a ramp it can follow keeps the error small even
   with a control period of actuation latency.

4. **In-place turns** (:class:`HeadingAligner`): the heading alignment of Vinch, *Design and
   Implementation of an Intelligent Primitive Driver* (MS thesis, U. Florida, 2003; section
   3: rotate in the direction of the shortest angular difference, faster when the error is
   large, stop inside a tolerance band, whose minimum is set by how much the platform keeps
   moving after the stop command). Here the banded speeds become the braking curve ``ω =
   sqrt(2 α |e|)`` (the fastest rate that still stops at the target with deceleration
   ``α``), the error is predicted ahead by the actuation latency (``e − ω_measured ·
   latency``) so the stop command is sent early enough, a re-engage band wider than the stop
   band keeps it from hunting, and the direction of a near-180° turn is locked so noise
   cannot flip it.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

from mazebot.config import ControlConfig, DriveConfig
from mazebot.slam.odometry import wheel_metres_per_tick

# the defaults below are the config's, each written once in mazebot.config
_CONTROL = ControlConfig()
_DRIVE = DriveConfig()


class DriveMode(enum.StrEnum):
    """What the wheels are doing; a change resets the speed integrals."""

    STOP = "stop"  # targets zero: brake
    DRIVE = "drive"  # following a path (DWA)
    TURN = "turn"  # turning in place
    RECOVER = "recover"  # backing off or rotating to get unstuck


class DiffDriveKinematics:
    """Body velocity ↔ wheel surface speeds of a differential drive.

    >>> k = DiffDriveKinematics(track_width_m=0.15, max_wheel_speed_mps=0.5)
    >>> k.wheel_speeds(0.2, 1.0)
    (0.125, 0.275)
    """

    def __init__(
        self, track_width_m: float = _DRIVE.track_width_m, max_wheel_speed_mps: float = _DRIVE.max_wheel_speed_mps
    ) -> None:
        if track_width_m <= 0 or max_wheel_speed_mps <= 0:
            raise ValueError(
                f"track_width_m and max_wheel_speed_mps must be positive, got {track_width_m}, {max_wheel_speed_mps}"
            )
        self.track_width_m = float(track_width_m)
        self.max_wheel_speed_mps = float(max_wheel_speed_mps)

    def wheel_speeds(self, v_mps: float, w_radps: float) -> tuple[float, float]:
        """``(left, right)`` wheel surface speeds in m/s, scaled together into the wheel limit."""
        half = 0.5 * self.track_width_m * w_radps
        left, right = v_mps - half, v_mps + half
        peak = max(abs(left), abs(right))
        if peak > self.max_wheel_speed_mps:
            scale = self.max_wheel_speed_mps / peak
            left, right = left * scale, right * scale
        return (left, right)

    def body_velocity(self, left_mps: float, right_mps: float) -> tuple[float, float]:
        """``(v_mps, w_radps)`` of the body for wheel surface speeds ``(left, right)``."""
        return (0.5 * (left_mps + right_mps), (right_mps - left_mps) / self.track_width_m)


class WheelSpeedEstimator:
    """Wheel surface speeds from cumulative encoder ticks, with a light low-pass filter.

    Example::

        est = WheelSpeedEstimator(metres_per_tick=math.pi * 0.065 / 840)
        est.update(left_ticks, right_ticks, now_s)      # -> (left_mps, right_mps)

    The speed over the last interval is ``Δticks · metres_per_tick / Δt``; at 20 Hz and
    840 ticks per turn a tick is ~2 % of 0.2 m/s, so ``smoothing`` (the weight of the
    previous estimate, 0 = none) trades that quantisation noise against lag.
    """

    def __init__(self, metres_per_tick: float | tuple[float, float], smoothing: float = 0.3) -> None:
        if isinstance(metres_per_tick, tuple):
            left, right = metres_per_tick
        else:
            left = right = metres_per_tick
        if left <= 0 or right <= 0:
            raise ValueError(f"metres_per_tick must be positive, got {metres_per_tick}")
        if not 0.0 <= smoothing < 1.0:
            raise ValueError(f"smoothing must be in [0, 1), got {smoothing}")
        self.metres_per_tick = (float(left), float(right))
        self.smoothing = float(smoothing)
        self._last: tuple[int, int, float] | None = None
        self.speed_mps = (0.0, 0.0)

    @classmethod
    def for_wheel(
        cls, ticks_per_rev: int, wheel_diameter_m: float, smoothing: float = 0.3, diameter_ratio: float = 1.0
    ) -> WheelSpeedEstimator:
        """An estimator for ``ticks_per_rev`` counted ticks per turn of wheels of that mean diameter.

        ``diameter_ratio`` is the right wheel's diameter over the left's, as the odometry
        takes it (:func:`mazebot.slam.odometry.wheel_metres_per_tick`).
        """
        return cls(wheel_metres_per_tick(ticks_per_rev, wheel_diameter_m, diameter_ratio), smoothing)

    def update(self, left_ticks: int, right_ticks: int, now_s: float) -> tuple[float, float]:
        """New speeds ``(left, right)`` in m/s; the first call (no interval yet) returns zeros."""
        last = self._last
        self._last = (left_ticks, right_ticks, now_s)
        if last is None or now_s <= last[2]:
            return self.speed_mps
        dt = now_s - last[2]
        raw_l = (left_ticks - last[0]) * self.metres_per_tick[0] / dt
        raw_r = (right_ticks - last[1]) * self.metres_per_tick[1] / dt
        a = self.smoothing
        self.speed_mps = (a * self.speed_mps[0] + (1 - a) * raw_l, a * self.speed_mps[1] + (1 - a) * raw_r)
        return self.speed_mps

    def reset(self) -> None:
        """Forget the history (after a pause: the next interval would span it)."""
        self._last = None
        self.speed_mps = (0.0, 0.0)


class WheelPid:
    """Speed controller of one wheel: feed-forward plus PI(D), throttle out.

    Example::

        pid = WheelPid(max_wheel_speed_mps=0.6, deadband=0.08)
        throttle = pid.update(target_mps=0.2, measured_mps=0.17, dt_s=0.05)

    Gains are in throttle per m/s (``kp``), throttle per metre of accumulated speed
    error (``ki``, i.e. per m/s per second) and throttle per m/s² (``kd``, on the
    measurement). ``max_wheel_speed_mps`` (wheel speed at full throttle) and
    ``deadband`` (throttle below which the motor does not turn) set the feed-forward
    ``sign(t) · (deadband + (1 − deadband) · |t| / max_wheel_speed_mps)``.
    ``integral_limit`` (throttle) bounds the integral's contribution; a target below
    ``zero_speed_mps`` in magnitude is a stop: the output is exactly 0 (the HAT brakes)
    and the integral is cleared.
    """

    def __init__(
        self,
        kp: float = 0.5,
        ki: float = 4.0,
        kd: float = 0.0,
        max_wheel_speed_mps: float = _DRIVE.max_wheel_speed_mps,
        deadband: float = 0.08,
        integral_limit: float = _CONTROL.integral_limit,
        zero_speed_mps: float = 1e-3,
        reference_tau_s: float = 0.16,
        latency_s: float = 0.0,
    ) -> None:
        if max_wheel_speed_mps <= 0 or not 0.0 <= deadband < 1.0:
            raise ValueError(
                f"need max_wheel_speed_mps > 0 and deadband in [0, 1), got {max_wheel_speed_mps}, {deadband}"
            )
        self.kp, self.ki, self.kd = float(kp), float(ki), float(kd)
        self.max_wheel_speed_mps = float(max_wheel_speed_mps)
        self.deadband = float(deadband)
        self.integral_limit = float(integral_limit)
        self.zero_speed_mps = float(zero_speed_mps)
        self.reference_tau_s = float(reference_tau_s)
        self.latency_s = float(latency_s)
        self._pending: deque[float] = deque()  # targets not yet acting on the wheel (latency)
        self._held_mps = 0.0  # what acts on the wheel until the first pending target arrives
        self.integral = 0.0  # throttle contributed by the integral term
        self.reference_mps = 0.0  # the model's expected wheel speed, what feedback compares with
        self._last_measured: float | None = None

    def feed_forward(self, target_mps: float) -> float:
        """The throttle that would give ``target_mps`` on the nominal motor (deadband compensated)."""
        if abs(target_mps) < self.zero_speed_mps:
            return 0.0
        magnitude = self.deadband + (1.0 - self.deadband) * abs(target_mps) / self.max_wheel_speed_mps
        return math.copysign(min(1.0, magnitude), target_mps)

    def update(self, target_mps: float, measured_mps: float, dt_s: float) -> float:
        """Throttle in [−1, 1] for this period."""
        if abs(target_mps) < self.zero_speed_mps:
            self.reset(measured_mps)
            return 0.0
        # the speed the wheel should have now if it follows the feed-forward as the model says:
        # the target, delayed by the actuation latency, through the motor's first-order lag
        self._pending.append(target_mps)
        delayed = self._pending.popleft() if len(self._pending) > self._delay_periods(dt_s) else self._held_mps
        if self.reference_tau_s > 0 and dt_s > 0:
            self.reference_mps += (delayed - self.reference_mps) * (1.0 - math.exp(-dt_s / self.reference_tau_s))
        else:
            self.reference_mps = delayed
        error = self.reference_mps - measured_mps
        derivative = 0.0
        if self.kd and self._last_measured is not None and dt_s > 0:
            derivative = -(measured_mps - self._last_measured) / dt_s
        self._last_measured = measured_mps
        ff = self.feed_forward(target_mps)
        unclamped = ff + self.kp * error + self.integral + self.kd * derivative
        # conditional integration: freeze while saturated in the direction the error pushes
        saturated = abs(unclamped) >= 1.0 and math.copysign(1.0, unclamped) == math.copysign(1.0, error)
        if not saturated and dt_s > 0:
            self.integral += self.ki * error * dt_s
            self.integral = max(-self.integral_limit, min(self.integral_limit, self.integral))
        out = ff + self.kp * error + self.integral + self.kd * derivative
        # never command the opposite direction of the target (braking is the job of 0)
        if out * target_mps < 0:
            out = 0.0
        return max(-1.0, min(1.0, out))

    def reset(self, measured_mps: float = 0.0) -> None:
        """Clear the integral (and the derivative's memory): on mode changes and stops.

        The reference model restarts from ``measured_mps``, the speed the wheel has now.
        """
        self.integral = 0.0
        self._last_measured = None
        self.reference_mps = measured_mps
        self._held_mps = measured_mps
        self._pending.clear()

    def _delay_periods(self, dt_s: float) -> int:
        return round(self.latency_s / dt_s) if dt_s > 0 else 0


def _lag_step(dt_s: float, tau_s: float) -> float:
    """The share of the way to its target a first-order lag of ``tau_s`` covers in ``dt_s``."""
    return 1.0 - math.exp(-dt_s / tau_s) if tau_s > 0 else 1.0


#: A wheel whose speed now reads under this share of the model's is not weak but silent: an
#: encoder that stopped counting (or a seized wheel), which the health monitor's dead-encoder
#: check makes a fault of. A window still half full of the speeds from before the cut would
#: give any gain between 0 and 1 (the fault suite's encoder-dead run: "the left motor gives
#: only 38 %" 150 ms after the cut), so such a wheel gives no gain at all.
SILENT_SHARE = 0.15
#: An update this many control periods after the previous one finds the wheel gain window stale.
LATE_PERIODS = 2.0
#: A window is judged only when the nominal motor's travel over it spans this many encoder ticks.
#: Its speeds are read from edge-dated travel, which is off by up to a tick at each end of the
#: window: with 10 ticks a healthy wheel's gain is within 20 % and the ratio of two healthy
#: wheels stays above 0.8 / 1.2 = 0.67, over the weak-motor verdict's 0.6. A cheap 20-line
#: encoder (80 ticks a turn, 2.6 mm each) turning in place at 4 cm/s counts 3 ticks in 0.2 s:
#: its healthy right motor was said to give "only 59 %" (a hand-built 8x8 maze, the robot
#: turning on the spot); the default 210-line encoder counts 33 ticks there.
MIN_WINDOW_TICKS = 10


class WheelGainEstimator:
    """How much speed each motor gives for the throttles written, against the nominal motor.

    Example::

        gains = WheelGainEstimator(max_wheel_speed_mps=0.6, deadband=0.08, period_s=0.05)
        left, right = gains.update(state.throttles, state.wheel_speeds_mps)   # None: cannot tell

    The wheel controller's feed-forward assumes a motor model: no motion below the
    deadband, then speed growing linearly to ``max_wheel_speed_mps`` at full throttle.
    Run forward, the same model turns each throttle written into the speed a nominal motor
    would reach; delayed by ``latency_s`` and passed through a first-order lag of
    ``time_constant_s`` (``brake_time_constant_s`` while the throttle is exactly 0: the
    HAT short-brakes the motor, which stops it faster than it coasts), that becomes the
    speed the encoder estimate would *show* now. A motor's gain is the least-squares fit
    of the measured speeds to the model's over the last ``window_s``::

        gain = Σ measured · model / Σ model²

    1 is the nominal motor; the fault suite's weak motor is 0.4.

    Why the model's speed rather than speed per throttle at one instant (the old check):
    the lag explains the transients that made a healthy wheel look weak for a check or
    two (a start from rest, a wheel reversing in a turn in place, a wheel still catching
    up with a throttle step), so no wheel has to wait to be "steady", and a weak motor is
    judged from the first control periods after it weakened, while its controller is
    still pushing it harder. Why not the speed controller's integral, which a weak motor
    winds up: it is reset at every drive-mode change and clamped, so it says how long the
    controller has pushed rather than how hard the motor answers. In the fault suite's
    motor-weak run the left-minus-right integral reached 0.10 after 400 ms and a turn
    reset it to 0.03; in healthy runs it reached 0.08 (median of the runs' maxima, 0.28
    at worst). The fit uses the throttle the integral produced, whatever the mode.

    The defaults are fitted to the control ticks of 43 simulated runs (the 16 training
    mazes, ten 6x6 mazes, the fault suite): one control period of delay (the encoder
    estimate is the mean over the last reading interval, stamped up to 20 ms before the
    tick, then smoothed) and lags of 0.09 s and 0.06 s left 5 mm/s RMS of misfit; with no
    delay and a single 0.12 s lag the start after a braked stop looked like a motor at
    45 %. Only a window whose every model speed is at least ``min_speed_mps`` is judged:
    a wheel crossing zero or idling near the deadband (where a small error in the
    deadband's estimate decides the speed, and a tick is 20 % of the speed) tells nothing.
    The lowest ratio of the two sides' gains of healthy motors was then 0.85 with a 0.2 s
    window (0.70 with 0.15 s), against 0.4 for the weak motor; with the 0.2 s window the
    suite's weak motor, injected at 18 different moments, was said 250-300 ms after it
    weakened, except once, when that motor crawled below 3 cm/s for 1.1 s first (1.3 s).
    Battery sag and unmatched motors scale both sides alike or by a few per cent;
    comparing the two sides is the health monitor's job. ``tick_m``, the wheel travel of one
    counted encoder tick, raises ``min_speed_mps`` for a coarse encoder so that a window spans
    ``MIN_WINDOW_TICKS`` ticks (below that one tick decides the gain).
    """

    def __init__(
        self,
        max_wheel_speed_mps: float = _DRIVE.max_wheel_speed_mps,
        deadband: float = 0.08,
        period_s: float = 0.05,
        latency_s: float = 0.05,
        time_constant_s: float = 0.09,
        brake_time_constant_s: float = 0.06,
        window_s: float = 0.2,
        min_speed_mps: float = 0.03,
        tick_m: float = 0.0,
    ) -> None:
        if max_wheel_speed_mps <= 0 or not 0.0 <= deadband < 1.0 or period_s <= 0 or time_constant_s < 0:
            raise ValueError(
                "need max_wheel_speed_mps > 0, deadband in [0, 1), period_s > 0 and time_constant_s >= 0, got "
                f"{max_wheel_speed_mps}, {deadband}, {period_s}, {time_constant_s}"
            )
        self.max_wheel_speed_mps = float(max_wheel_speed_mps)
        self.deadband = float(deadband)
        self.period_s = float(period_s)
        self.time_constant_s = float(time_constant_s)
        self.window_s = float(window_s)
        # the encoder's resolution sets a floor too: a window must span MIN_WINDOW_TICKS ticks of travel
        self.min_speed_mps = max(float(min_speed_mps), MIN_WINDOW_TICKS * float(tick_m) / self.window_s)
        self.brake_time_constant_s = float(brake_time_constant_s)
        self._keep = _lag_step(self.period_s, self.time_constant_s)
        self._keep_braking = _lag_step(self.period_s, self.brake_time_constant_s)
        self._samples = max(1, round(self.window_s / self.period_s))
        self.latency_s = float(latency_s)
        self._delay = max(0, round(self.latency_s / self.period_s))
        self._pending: deque[tuple[float, float]] = deque()  # throttles written, not yet seen by the encoders
        self.model_mps = [0.0, 0.0]  # what the encoders would show on nominal motors
        self._fits: tuple[deque[tuple[float, float, float]], ...] = (deque(), deque())  # (m·p, p², |p|)
        self.gains: tuple[float | None, float | None] = (None, None)

    def nominal_speed_mps(self, throttle: float) -> float:
        """The steady speed of a nominal motor at ``throttle``: the feed-forward's map, inverted."""
        magnitude = abs(throttle) - self.deadband
        if magnitude <= 0:
            return 0.0
        return math.copysign(self.max_wheel_speed_mps * min(1.0, magnitude / (1.0 - self.deadband)), throttle)

    def update(
        self, throttles: tuple[float, float], measured_mps: tuple[float, float], dt_s: float | None = None
    ) -> tuple[float | None, float | None]:
        """One control period: ``throttles`` written during it, ``measured_mps`` at its end; the gains.

        ``dt_s``, the time since the previous update, defaults to ``period_s``. A period
        much longer than that (a blocked event loop: the motor driver's time-to-live may
        have stopped the wheels meanwhile) leaves the model not knowing what the wheels
        did, so the window starts again.
        """
        if dt_s is not None and dt_s > LATE_PERIODS * self.period_s:
            self.reset()
        self._pending.append((float(throttles[0]), float(throttles[1])))
        acting = self._pending.popleft() if len(self._pending) > self._delay else (0.0, 0.0)
        gains: list[float | None] = []
        for side in (0, 1):
            model = self.model_mps[side]
            keep = self._keep_braking if acting[side] == 0.0 else self._keep
            model += (self.nominal_speed_mps(acting[side]) - model) * keep
            self.model_mps[side] = model
            fit = self._fits[side]
            fit.append((measured_mps[side] * model, model * model, abs(model)))
            if len(fit) > self._samples:
                fit.popleft()
            cross = sum(c for c, _, _ in fit)
            power = sum(p for _, p, _ in fit)
            enough = len(fit) == self._samples and min(a for _, _, a in fit) >= self.min_speed_mps
            silent = abs(measured_mps[side]) < SILENT_SHARE * abs(model)
            gains.append(cross / power if enough and not silent else None)
        self.gains = (gains[0], gains[1])
        return self.gains

    def reset(self) -> None:
        """Forget the window (the wheels were not ours to judge: a fault held them)."""
        self.model_mps = [0.0, 0.0]
        self._pending.clear()
        for fit in self._fits:
            fit.clear()
        self.gains = (None, None)


@dataclass(frozen=True)
class WheelCommand:
    """What :meth:`WheelController.update` decided: throttles and the targets behind them."""

    left_throttle: float
    right_throttle: float
    left_target_mps: float
    right_target_mps: float


class WheelController:
    """Body velocity in, two throttles out, at the control rate.

    Example::

        ctl = WheelController(track_width_m=0.15, max_wheel_speed_mps=0.6, deadband=0.08)
        cmd = ctl.update(v_mps=0.2, w_radps=0.0, mode=DriveMode.DRIVE,
                         measured_mps=(0.18, 0.17), dt_s=0.05)
        motors.set(cmd.left_throttle, cmd.right_throttle)

    ``max_wheel_accel_mps2`` limits how fast each wheel target may change (the ramp);
    ``max_wheel_decel_mps2`` the same when slowing down (braking can be harder). The PID
    gains and the motor model are those of :class:`WheelPid`.
    """

    def __init__(
        self,
        track_width_m: float = _DRIVE.track_width_m,
        max_wheel_speed_mps: float = _DRIVE.max_wheel_speed_mps,
        deadband: float = 0.08,
        kp: float = 0.5,
        ki: float = 4.0,
        kd: float = 0.0,
        integral_limit: float = _CONTROL.integral_limit,
        max_wheel_accel_mps2: float = _CONTROL.max_wheel_accel_mps2,
        max_wheel_decel_mps2: float = 2.0,
    ) -> None:
        self.kinematics = DiffDriveKinematics(track_width_m, max_wheel_speed_mps)
        self.left = WheelPid(kp, ki, kd, max_wheel_speed_mps, deadband, integral_limit)
        self.right = WheelPid(kp, ki, kd, max_wheel_speed_mps, deadband, integral_limit)
        self.max_wheel_accel_mps2 = float(max_wheel_accel_mps2)
        self.max_wheel_decel_mps2 = float(max_wheel_decel_mps2)
        self.mode = DriveMode.STOP
        self.targets_mps = (0.0, 0.0)  # the ramped wheel targets

    def update(
        self, v_mps: float, w_radps: float, mode: DriveMode, measured_mps: tuple[float, float], dt_s: float
    ) -> WheelCommand:
        """Throttles for body velocity ``(v_mps, w_radps)`` given the measured wheel speeds."""
        if mode is not self.mode:
            # a wheel that keeps its direction: the reference model starts from the speed it has, not
            # from rest. From 0 a wheel still rolling forward out of a drive reads as far too fast,
            # P and I hold it back while the other wheel reverses, and a turn in place begun at
            # 0.27 m/s reversed the body for 35 mm (a 16x16 contest maze under a Pi 4's share:
            # 0.095 m/s, into a side wall); now 14 mm. A wheel that must reverse still starts from
            # rest: its hard push is what tells a weak motor within 0.4 s of a turn's start
            want_l, want_r = self.kinematics.wheel_speeds(v_mps, w_radps)
            self.left.reset(measured_mps[0] if measured_mps[0] * want_l > 0 else 0.0)
            self.right.reset(measured_mps[1] if measured_mps[1] * want_r > 0 else 0.0)
            self.mode = mode
        if mode is DriveMode.STOP:
            self.targets_mps = (0.0, 0.0)
            self.left.reset(measured_mps[0])
            self.right.reset(measured_mps[1])
            return WheelCommand(0.0, 0.0, 0.0, 0.0)
        want_l, want_r = self.kinematics.wheel_speeds(v_mps, w_radps)
        left_t, right_t = self._ramp(want_l, want_r, dt_s)
        self.targets_mps = (left_t, right_t)
        throttle_l = self.left.update(left_t, measured_mps[0], dt_s)
        throttle_r = self.right.update(right_t, measured_mps[1], dt_s)
        return WheelCommand(throttle_l, throttle_r, left_t, right_t)

    def _ramp(self, want_l: float, want_r: float, dt_s: float) -> tuple[float, float]:
        """Move both wheel targets toward the wanted ones by the same fraction of the way.

        Each wheel may change by at most its acceleration (or, slowing down, its
        deceleration) limit times ``dt_s``; scaling both steps by one factor keeps the
        ratio of the changes, so an arc is entered on its own curvature.
        """
        factor = 1.0
        for current, want in zip(self.targets_mps, (want_l, want_r), strict=True):
            step = want - current
            speeding_up = abs(want) > abs(current) and want * current >= 0
            limit = (self.max_wheel_accel_mps2 if speeding_up else self.max_wheel_decel_mps2) * dt_s
            if abs(step) > limit:
                factor = min(factor, limit / abs(step))
        cur_l, cur_r = self.targets_mps
        return (cur_l + factor * (want_l - cur_l), cur_r + factor * (want_r - cur_r))

    def reset(self) -> None:
        """Back to a standstill: targets, integrals and mode."""
        self.left.reset()
        self.right.reset()
        self.mode = DriveMode.STOP
        self.targets_mps = (0.0, 0.0)


class HeadingAligner:
    """Turns in place to a heading: shortest direction, braking curve, tolerance band.

    Example::

        aligner = HeadingAligner()
        w_radps, done = aligner.command(heading_rad, target_rad, yaw_rate_radps)

    ``tolerance_rad`` is the stop band (±; Vinch (2003) found ±4° the smallest its turning
    platform held without hunting). ``reengage_rad`` bounds the error tolerated while
    the robot is still coasting after a stop; once it has settled (measured rate below
    ``settle_rate_radps``) outside the band, a slow correction follows. That never
    hunts as long as the coast at the minimum rate, ``min_yaw_rate_radps`` times the
    latency plus the motor's braking time, stays inside the band's width.
    ``max_yaw_rate_radps`` / ``min_yaw_rate_radps`` limit the rate (the minimum keeps
    the wheels above the motor deadband); ``yaw_decel_radps2`` is the deceleration of the
    braking curve; ``latency_s`` how far ahead the heading is predicted with the
    measured yaw rate (actuation latency plus braking time constant); ``lock_rad`` the
    error beyond which the turn direction, once chosen, is kept (near 180° the shortest
    way is ambiguous and noise would flip it).
    """

    def __init__(
        self,
        tolerance_rad: float = math.radians(4.0),
        reengage_rad: float = math.radians(8.0),
        max_yaw_rate_radps: float = _DRIVE.max_yaw_rate_radps,
        min_yaw_rate_radps: float = 0.4,
        yaw_decel_radps2: float = 3.0,
        latency_s: float = 0.05,
        settle_rate_radps: float = 0.05,
        lock_rad: float = math.radians(150.0),
    ) -> None:
        if not 0 < tolerance_rad < reengage_rad:
            raise ValueError(f"need 0 < tolerance_rad < reengage_rad, got {tolerance_rad}, {reengage_rad}")
        if not 0 < min_yaw_rate_radps <= max_yaw_rate_radps:
            raise ValueError(
                f"need 0 < min_yaw_rate_radps <= max_yaw_rate_radps, got {min_yaw_rate_radps}, {max_yaw_rate_radps}"
            )
        self.tolerance_rad = float(tolerance_rad)
        self.reengage_rad = float(reengage_rad)
        self.max_yaw_rate_radps = float(max_yaw_rate_radps)
        self.min_yaw_rate_radps = float(min_yaw_rate_radps)
        self.yaw_decel_radps2 = float(yaw_decel_radps2)
        self.latency_s = float(latency_s)
        self.settle_rate_radps = float(settle_rate_radps)
        self.lock_rad = float(lock_rad)
        self.done = True
        self._direction = 0.0  # +1 counter-clockwise, -1 clockwise, 0 not locked
        self._target_rad: float | None = None

    def error_rad(self, heading_rad: float, target_rad: float) -> float:
        """Signed turn still to go: the shortest way, or the locked way of a near-180° turn."""
        error = math.remainder(target_rad - heading_rad, math.tau)  # in [-pi, pi]
        if self._direction and abs(error) > self.lock_rad and math.copysign(1.0, error) != self._direction:
            error -= math.copysign(math.tau, error)  # keep turning the way we started
        return error

    def command(self, heading_rad: float, target_rad: float, yaw_rate_radps: float = 0.0) -> tuple[float, bool]:
        """``(yaw_rate_radps, done)``: the rate to command now and whether the heading is held.

        ``yaw_rate_radps`` is the measured rate (from the wheel speeds), used to predict
        where the heading will be when this command takes effect.
        """
        if self._target_rad is None or abs(math.remainder(target_rad - self._target_rad, math.tau)) > 1e-6:
            self._target_rad = target_rad  # a new target: a fresh turn
            self.done = False
            self._direction = 0.0
        error = self.error_rad(heading_rad, target_rad)
        if self.done:
            settled = abs(yaw_rate_radps) <= self.settle_rate_radps
            if abs(error) <= self.tolerance_rad or (not settled and abs(error) <= self.reengage_rad):
                return (0.0, True)
            self.done = False  # settled outside the band (or knocked far off): correct it
        predicted = error - yaw_rate_radps * self.latency_s
        if abs(predicted) <= self.tolerance_rad or predicted * error < 0:
            # inside the band, or what is already under way carries it there: stop now
            self.done = True
            self._direction = 0.0
            return (0.0, True)
        if abs(error) > self.lock_rad and not self._direction:
            self._direction = math.copysign(1.0, error)
        remaining = max(0.0, abs(predicted) - 0.5 * self.tolerance_rad)
        rate = math.sqrt(2.0 * self.yaw_decel_radps2 * remaining)
        rate = max(self.min_yaw_rate_radps, min(self.max_yaw_rate_radps, rate))
        return (math.copysign(rate, predicted), False)

    def reset(self) -> None:
        """Forget the target: the next command starts a new turn."""
        self.done = True
        self._direction = 0.0
        self._target_rad = None
