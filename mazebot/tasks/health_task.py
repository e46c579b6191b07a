"""Watches the sensors for the faults a task cannot see from inside: silence and dead wires.

- **Lidar silence**: no revolution for ``lidar_silence_s`` (a revolution takes 0.18 s) means
  the robot no longer knows what is in front of it: a ``lidar`` fault, so the control task
  stops the wheels within one control period. The driver reconnects by itself; the
  fault clears with the first new revolution. The silence counts the checks that ran, not
  the wall time between them: a check that comes late because the event loop was blocked
  (heavy work, a slow core) adds one period, not the time the lidar's reader could not
  run either, and it never raises the fault itself: the reader gets its turn first. Nor
  is the lidar silent while bytes from it wait to be decoded (``lidar.bytes_waiting()``) or
  arrived since the last check; bytes that never make a revolution are a fault after
  ``GARBLED_SILENCE_FACTOR`` times as long.
- **Dead encoder**: a wheel whose motor has been driven well above the deadband for
  ``encoder_dead_s`` in all while its tick count did not move, and the other wheel's did:
  a cut encoder wire. The driven time adds up over the pauses of the control (under
  ``IDLE_RESET_S`` each): a dead encoder makes the odometry wrong at once, and the robot's
  reaction to that (braking, backing off, stopping because it is lost) cuts the drive
  into short stretches, none of them as long as ``encoder_dead_s``. A wheel that was
  turning and falls silent while still driven and while the other one counts is dead
  after ``SUDDEN_SILENCE_S`` already (it cannot stop that fast). Odometry is then
  wrong, so this is a fault too; it is latched (the evidence only exists while driving)
  and the user's next start gives it another try. A silence while the other wheel counts
  is measured on the edges' own stamps (``sensors.encoder_edge_time_s``: the other wheel's
  edges say how far the wheels' time went while this one counted nothing), not on the
  checks' clock: under a starved CPU the edges reach the counts tens to hundreds of
  milliseconds late and in bursts, and checks that ran meanwhile saw nothing new on
  either wheel; counted as silence, that time made a slow wheel "silent" for 0.2 s once
  a burst brought the other wheel's edges and none of its own. Only with the other wheel
  idle too (no edge at all comes) does the silence count the checks that ran.

- **Bouncing encoders**: impossible transitions (a contact bouncing, an edge lost) are
  counted by the decoders; new ones are said in ``/api/status`` (an ``encoders``
  event, at most every ``NOTE_EVERY_S``). The wheels go on: SLAM corrects the odometry.
- **Weak motor**: each wheel's speed in each control period (from one throttle write to the
  next, ``state.throttle_history``) is its travel in that period, from the encoder counts
  dated by their edges (``state.wheel_travel``); those speeds are fitted to the ones the
  feed-forward's nominal motor model gives for the throttles written, over 0.2 s
  (:class:`WheelTravelGains`, ``WheelGainEstimator``); a motor whose gain is below
  ``weak_ratio`` of the other's is said (a ``motors`` event): the wheel controller makes
  up for it, but a gearbox or a motor is failing. A period is judged once the edges up
  to its end have been counted: under a CPU quota the thread that counts them runs 80-270 ms
  late, and speeds measured by the wall clock at the control tick then paired each throttle
  with another interval's motion (a false "gives only 8-59 %" on every quota run).

All are plain checks on ``SharedState`` at 10 Hz (the dead-encoder and weak-motor ones at
20 Hz, the control rate); they never touch a device.
"""

from __future__ import annotations

import bisect
import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from mazebot.clock import Clock
from mazebot.config import Config
from mazebot.planner.wheel_control import LATE_PERIODS, WheelGainEstimator
from mazebot.state import SharedState

log = logging.getLogger(__name__)

#: How often the checks run.
PERIOD_S = 0.1
#: How often the weak-motor check runs: at the control rate, where the control task publishes
#: the wheel gains. Read at 10 Hz, every other gain was lost and a weak motor was said 0-50 ms
#: later (the fault suite's motor-weak replayed: 300-350 ms instead of 300).
MOTOR_PERIOD_S = 0.05
#: Ticks the other wheel must have counted for a silent encoder to be suspicious.
OTHER_WHEEL_TICKS = 40
#: A silent encoder on a driven wheel while the other wheel idles (a pivot about it) is a fault
#: after this long, without the other wheel's ticks: the idle wheel took 1.1 s to count 40 in the
#: fault suite's encoder-dead run (said after 1.2 s; the fault suite wants 0.5, docs/design.md). A driven wheel starting
#: from rest counts within ~0.1 s (the motor's 0.09 s lag); a wheel pushed against a wall has the
#: other one driven too, which keeps the old rule.
OTHER_IDLE_DEAD_S = 0.3
#: A silent wheel's driven time starts again from nothing after this long without being driven.
IDLE_RESET_S = 0.5
#: A wheel that counted this many ticks in the check interval before it fell silent was turning
#: (at 0.1 m/s a wheel counts ~40 ticks in 50 ms). Turning and still driven the same way, it
#: cannot stop within ``SUDDEN_SILENCE_S`` (the motor's lag is 0.09 s) unless its encoder died or
#: the wheel is blocked while the other turns: in the fault suite's encoder-dead run of seed 4 the
#: robot, misled by the dead encoder, braked 0.1 s after the cut (one silent check) and drove
#: again only 0.8 s later, and the driven-time rule said it after 1.1 s.
MOVING_TICKS = 10
SUDDEN_SILENCE_S = 0.05
#: While any fault is active, and this long after the last one cleared, the wheels are held
#: or starting again from rest (the motors' lag, half-failed throttle writes): their speeds
#: tell nothing about a motor's strength. Without it the fault suite said a weak motor in
#: the runs of lidar-motor-stop, motor-i2c and slam-raise.
FAULT_SETTLE_S = 1.0
#: A wheel the other cannot be compared with at the moment (the other barely turns: the
#: inner wheel of a tight arc sat in the deadband for 1.1 s when the fault suite's weak motor
#: came, and main said it after 1.3 s) is judged against the other's last gain, if it had
#: one this recently; the strength of a motor does not change from one turn to the next.
REFERENCE_AGE_S = 5.0
#: Events about the same trouble (bouncing encoders, a weak motor) at most this often.
NOTE_EVERY_S = 5.0
#: A lidar check that comes more than this many periods after the previous one was held up
#: by a blocked loop: it counts one period of silence and judges nothing.
LATE_CHECK_PERIODS = 1.5
#: Bytes keep arriving but no revolution is made of them (a garbled line, a wrong baud rate):
#: a fault once the silence is this many times ``lidar_silence_s``.
GARBLED_SILENCE_FACTOR = 3.0


class LidarActivity(Protocol):
    """What the health monitor reads of the lidar driver (:class:`mazebot.io.rplidar.RPLidar`)."""

    @property
    def stats(self) -> Any: ...  # ``bytes_received``: scan bytes read so far

    def bytes_waiting(self) -> int: ...


@dataclass
class _Wheel:
    driven_s: float = 0.0  # how long the motor was driven since the tick count last moved, in the edges' time
    driven_checks_s: float = 0.0  # ... in the checks' time (the silence with the other wheel idle too)
    driven_at_s: float | None = None  # the last check that saw it driven (None: a new stretch)
    ticks: int = 0  # the tick count at the stretch's start
    other_ticks: int = 0
    other_idle: bool = True  # the other wheel was not driven at any driven check of the stretch
    moving: int = 0  # it was turning this way (+1 forward, -1 back, 0 not) just before the silence began


def wheel_gains_from_config(config: Config) -> WheelGainEstimator:
    """The weak-motor check's nominal motor: the feed-forward's (``[drive]``, ``[control]``) at the
    control rate, judged only over travel its encoders resolve (``[encoders]``: a tick's travel)."""
    tick_m = config.wheel_circumference_m / config.encoders.ticks_per_rev
    return WheelGainEstimator(config.drive.max_wheel_speed_mps, config.control.motor_deadband,
                              config.daemon.control_period_s, latency_s=0.0, tick_m=tick_m)


class WheelTravelGains:
    """Each motor's gain (``WheelGainEstimator``) from what the wheels did between two throttle writes.

    Example (the health monitor, each check)::

        travel_gains = WheelTravelGains(WheelGainEstimator(latency_s=0.0))
        left, right = travel_gains.update(state.throttle_history, state.wheel_travel)

    Each control period runs from one throttle write (``throttle_history``: time, left,
    right) to the next. The estimator's model gives the nominal motor's speed at the end of
    the period, so the wheel's speed there is measured: its travel over a period's length
    centred on that end, over that length (a mean over the period itself lagged the model by
    half a period: healthy wheels reversing in a turn with late edges fitted 0.75 instead of
    0.84). The travel is read from ``wheel_travel`` (time, left_m, right_m), whose dates are
    the encoder edges' own, interpolated between two entries. A period is judged once the
    travel's dates reach half a period past its end, in the order of the periods, however
    late the edges arrived: speeds and throttles are then of the same interval, as on an
    idle CPU. The estimator's latency is 0: the speeds are no estimate that lags the wheel.
    A period the travel no longer reaches back to, one whose travel is interpolated over
    more than ``LATE_PERIODS`` control periods (the edges were not read in between: the
    wheel may have reversed there), or one longer than that (the loop blocked: the motors'
    time-to-live may have stopped the wheels) starts the window again.
    """

    def __init__(self, estimator: WheelGainEstimator) -> None:
        self.estimator = estimator
        self.judged_s: float | None = None  # the start of the last period judged
        self.judged_until_s: float | None = None  # its end: the gains describe the wheels up to then

    def update(self, throttles: Sequence[tuple[float, float, float]],
               travel: Sequence[tuple[float, float, float]]) -> tuple[float | None, float | None]:
        """The gains after every period that can be judged now (``estimator.gains``).

        Looks only at the writes after the last period judged (from the newest back), and
        finds the travel around a time by bisection: a few microseconds a check.
        """
        # a copy of the writes not judged yet and the last one judged (the control loop's thread may
        # append meanwhile: _tail), not of all of them; the travel is the odometry task's, on this
        # loop: read where it is (a deque's index, by bisection)
        writes, dated = _tail(throttles, self.judged_s), travel
        if len(dated) < 2 or len(writes) < 2:
            return self.estimator.gains
        first = len(writes)
        while first > 0 and (self.judged_s is None or writes[first - 1][0] > self.judged_s):
            first -= 1
        covered_s = dated[-1][0]
        max_period_s = LATE_PERIODS * self.estimator.period_s
        for k in range(first, len(writes) - 1):
            (start_s, left, right), end_s = writes[k], writes[k + 1][0]
            half_s = 0.5 * (end_s - start_s)
            if end_s + half_s > covered_s:
                break  # the edges up to half a period past this period's end have not been counted yet
            previous_s, self.judged_s, self.judged_until_s = self.judged_s, start_s, end_s
            if start_s < dated[0][0] or end_s - start_s > max_period_s:
                self.estimator.reset()
                continue
            late = previous_s is not None and start_s - previous_s > max_period_s
            begin, begin_gap_s = _travel_at(dated, end_s - half_s)
            end, end_gap_s = _travel_at(dated, end_s + half_s)
            if max(begin_gap_s, end_gap_s) > max_period_s + 1e-6:  # (times are sums of float periods)
                # the edge thread did not run for that long: the travel in between is a straight
                # line, whatever the wheel did there (reversed in a turn, started, braked)
                self.estimator.reset()
                continue
            span_s = end_s - start_s
            speeds = ((end[0] - begin[0]) / span_s, (end[1] - begin[1]) / span_s)
            self.estimator.update((left, right), speeds, max_period_s * 2 if late else None)
        return self.estimator.gains


def _tail(history: Sequence[tuple[float, float, float]], since_s: float | None) -> Sequence[tuple[float, float, float]]:
    """The entries of ``history`` (time first, oldest first) dated after ``since_s``, and the one
    before them, oldest first: what a check that looked up to ``since_s`` last has not seen.

    Copied from the newest back, entry by entry, instead of the whole history (200 throttle
    writes: each one's reference count touched, a cache miss apiece in a process whose caches
    the other tasks have filled, twice a check). The control loop's thread may append while the
    copy runs (a control thread instead of a process): the iteration then fails and the whole
    history is copied at once (C speed, under the interpreter lock). All of it when ``since_s``
    is None.
    """
    if since_s is None:
        return tuple(history)
    try:
        out = []
        for entry in reversed(history):
            out.append(entry)
            if entry[0] <= since_s:
                break
    except RuntimeError:  # appended to meanwhile ("deque mutated during iteration")
        return tuple(history)
    out.reverse()
    return out


def _travel_at(travel: Sequence[tuple[float, float, float]], time_s: float) -> tuple[tuple[float, float], float]:
    """((left_m, right_m) at ``time_s``, between the two entries of ``travel`` around it (linear);
    the time between those two entries, seconds: how far the straight line reaches)."""
    k = bisect.bisect_left(travel, time_s, key=_entry_time)
    if k >= len(travel):  # not covered: the callers judge only covered periods
        return (travel[-1][1], travel[-1][2]), math.inf
    t1, l1, r1 = travel[k]
    if k == 0 or t1 == time_s:
        return (l1, r1), (0.0 if t1 == time_s else math.inf)
    t0, l0, r0 = travel[k - 1]
    share = (time_s - t0) / (t1 - t0)
    return (l0 + share * (l1 - l0), r0 + share * (r1 - r0)), t1 - t0


def _driven_throughout(writes: Sequence[tuple[float, float, float]], side: int, since_s: float,
                       throttle: float, driven_throttle: float) -> bool:
    """Whether every throttle the ``side`` motor had from ``since_s`` on drove it the way of
    ``throttle`` at ``driven_throttle`` or more (``writes``: the control loop's (time, left,
    right) writes, oldest first).

    A check sees only the throttle of its own moment; under a starved CPU checks run late and
    the wheel may have been braked in between (the control loop stops the motors when the
    planner's command grows stale) and driven again, which a dead encoder's silence must not
    be confused with. True when the writes do not reach back that far: nothing is known
    against the throttle seen.
    """
    for time_s, left, right in reversed(writes):
        value = left if side == 0 else right
        if abs(value) < driven_throttle or (value > 0) != (throttle > 0):
            return False
        if time_s <= since_s:
            return True
    return True


def _entry_time(entry: tuple[float, float, float]) -> float:
    return entry[0]


class HealthMonitor:
    """The checks, one call per period (see the module docstring).

    ``wheel_gains`` fits the wheels' speeds to the nominal motor (built from the config's
    ``[drive]``, ``[control]`` and ``[daemon]`` sections by ``main``; the defaults here).
    """

    def __init__(
        self,
        lidar_silence_s: float = 0.4,
        startup_grace_s: float = 5.0,
        encoder_dead_s: float = 0.2,
        driven_throttle: float = 0.15,
        weak_ratio: float = 0.6,
        weak_checks: int = 1,
        lidar: LidarActivity | None = None,
        wheel_gains: WheelGainEstimator | None = None,
    ) -> None:
        self.lidar_silence_s = float(lidar_silence_s)
        self.lidar = lidar
        self._lidar_checked_s: float | None = None  # the last lidar check
        self._lidar_scan: object = None  # the revolution that check saw
        self._lidar_silent_s = 0.0  # checks-run time since the last new revolution (or since the start)
        self._lidar_bytes = 0  # the driver's bytes_received at that check
        self.startup_grace_s = float(startup_grace_s)
        self.encoder_dead_s = float(encoder_dead_s)
        self.driven_throttle = float(driven_throttle)
        self.weak_ratio = float(weak_ratio)
        self.weak_checks = int(weak_checks)
        self._started_s: float | None = None
        self._wheels = (_Wheel(), _Wheel())
        self._encoders_checked_s: float | None = None
        self._edges_judged_s: float | None = None  # the newest edge stamp the encoder check has judged up to
        self._invalid_seen = 0
        self._weak_streak = [0, 0]
        self.travel_gains = WheelTravelGains(wheel_gains or WheelGainEstimator(latency_s=0.0))
        self._last_gains: list[tuple[float, float] | None] = [None, None]  # (gain, check time) per wheel
        self._fault_seen_s: float | None = None  # the last check that saw an active fault
        self._last_note_s: dict[str, float] = {}

    def check(self, state: SharedState, now_s: float) -> None:
        """Every check: the 10 Hz call."""
        if self._started_s is None:
            self._started_s = now_s
        self._check_lidar(state, now_s)
        self._check_encoders(state, now_s)
        self._check_bounce(state, now_s)
        self._check_motor_strength(state, now_s)

    def check_motors(self, state: SharedState, now_s: float) -> None:
        """The checks at the control rate: the calls between two of :meth:`check` (``MOTOR_PERIOD_S``).

        The dead-encoder check runs here too: the control task writes a throttle every
        ``MOTOR_PERIOD_S``, so a check on time sees each throttle the wheels were given; a late
        one reads the throttles it missed from ``state.throttle_history``.
        """
        if self._started_s is None:
            self._started_s = now_s
        self._check_encoders(state, now_s)
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
        """Each motor's gain against the other's; one far below the other is a weak motor.

        The gains are the fit of the wheels' speeds in the control periods to the nominal
        motor model over 0.2 s (:class:`WheelTravelGains`): the window is the evidence that
        the motor stays weak, so one check below ``weak_ratio`` says it.
        ``weak_ratio`` 0.6 sits between the suite's weak motor (0.4) and the lowest ratio of
        healthy motors in 59 simulated runs (0.85; the 16 training mazes, ten 6x6 mazes, the
        fault suite, and 18 motor-weak runs before their fault).
        Comparing the sides keeps what both motors share (battery sag, a wrong full-throttle
        speed in the config) out of it; when the other wheel barely turns, its last gain
        (``REFERENCE_AGE_S``) stands in for it.
        """
        if state.faults or state.calibrating:  # a calibration's pulses and ramps are no weak motor either
            self._fault_seen_s = now_s
        travel = self.travel_gains
        gains = travel.update(state.throttle_history, state.wheel_travel)
        # the periods judged may be older than the check (the edges come late): the settling
        # counts from the fault to the end of the period judged, and one before it waits too
        judged_s = now_s if travel.judged_until_s is None else travel.judged_until_s
        if self._fault_seen_s is not None and judged_s - self._fault_seen_s < FAULT_SETTLE_S:
            self._weak_streak = [0, 0]
            return
        for side in (0, 1):
            gain = gains[side]
            if gain is not None:
                self._last_gains[side] = (gain, judged_s)
        for side in (0, 1):
            mine, other = gains[side], self._last_gains[1 - side]
            reference = None if other is None or judged_s - other[1] > REFERENCE_AGE_S else other[0]
            weak = mine is not None and reference is not None and reference > 0 and mine < self.weak_ratio * reference
            self._weak_streak[side] = self._weak_streak[side] + 1 if weak else 0
            if weak and self._weak_streak[side] >= self.weak_checks:
                name = ("left", "right")[side]
                share = 100 * max(0.0, mine or 0.0) / (reference or 1.0)  # both known here (weak)
                self._note(state, "motors", f"the {name} motor gives only {share:.0f} % of the other's speed for "
                           "the same throttle: the wheel control makes up for it; check that motor, its gearbox "
                           "and its wires", now_s)

    def _check_lidar(self, state: SharedState, now_s: float) -> None:
        scan = state.latest_scan
        last_s, self._lidar_checked_s = self._lidar_checked_s, now_s
        step_s = 0.0 if last_s is None else max(0.0, now_s - last_s)
        late = step_s > LATE_CHECK_PERIODS * PERIOD_S
        if scan is not self._lidar_scan:  # a new revolution: the silence since it ended (one period at most)
            self._lidar_scan = scan
            self._lidar_silent_s = 0.0 if scan is None else min(max(0.0, now_s - scan.end_time_s), PERIOD_S)
        else:
            self._lidar_silent_s += min(step_s, PERIOD_S)
        # the time allowed: at start-up the grace as well; never more than the revolution's own age
        allowed_s = self.lidar_silence_s + (self.startup_grace_s if scan is None else 0.0)
        silent_s = self._lidar_silent_s if scan is None else min(self._lidar_silent_s, now_s - scan.end_time_s)
        bytes_flow = False
        if self.lidar is not None:
            received = int(self.lidar.stats.bytes_received)
            bytes_flow = received != self._lidar_bytes or self.lidar.bytes_waiting() > 0
            self._lidar_bytes = received
        active = any(f.source == "lidar" for f in state.faults)
        if silent_s > allowed_s:
            garbled = silent_s > GARBLED_SILENCE_FACTOR * allowed_s
            if not active and not late and (garbled or not bytes_flow):
                what = "no lidar data yet" if scan is None else f"no lidar data for {silent_s:.1f} s"
                if bytes_flow:
                    what = f"lidar bytes arrive but make no revolution for {silent_s:.1f} s"
                message = f"{what}: {self._lidar_advice(scan is None)}; reconnecting by itself"
                log.warning("%s", message)
                state.raise_fault("lidar", message, now_s)
        elif active:
            state.clear_faults("lidar")
            state.note("lidar", "lidar data flows again", now_s)
            log.info("lidar data flows again")

    def _lidar_advice(self, never_scanned: bool) -> str:
        """What to check. Before the first revolution the driver's own last error is this start-up's
        and says more than a guess (a lidar of the family at another serial speed names the speed to
        set); later it may be an old outage's, so the usual causes are named instead."""
        said = self.lidar.stats.last_error if self.lidar is not None else ""
        if never_scanned and said:
            return said
        return "check the lidar's USB cable and power"

    def _edge_step(self, edge_s: float | None, step_s: float) -> tuple[float, float | None]:
        """(seconds of the wheels' own time the counts cover beyond what the last check judged, the
        stamp judged up to before this check). The newest edge's stamp (``edge_s``) moves on only as
        edges are counted, however late; no edge since: nothing (neither wheel counted, the other's
        silence is no evidence). Without stamps (None: a pin factory on another clock), the checks'
        own time ``step_s``, as the only clock there is.
        """
        judged_s = self._edges_judged_s
        if edge_s is None:
            return step_s, None
        if judged_s is None or edge_s <= judged_s:
            self._edges_judged_s = edge_s if judged_s is None else judged_s
            return 0.0, judged_s
        self._edges_judged_s = edge_s
        return edge_s - judged_s, judged_s

    def _check_encoders(self, state: SharedState, now_s: float) -> None:
        last_s, self._encoders_checked_s = self._encoders_checked_s, now_s
        if state.calibrating:
            # the wiring is what the calibration is finding out: a motor output whose encoder does not
            # count is what its pulses look for (and a failed step says so); stretches begin afresh after
            self._edge_step(state.sensors.encoder_edge_time_s, 0.0)
            for wheel in self._wheels:
                wheel.driven_at_s = None
            return
        step_s = 0.0 if last_s is None else min(max(0.0, now_s - last_s), PERIOD_S)
        edges_s, judged_s = self._edge_step(state.sensors.encoder_edge_time_s, step_s)
        ticks = (state.sensors.encoder_ticks_left, state.sensors.encoder_ticks_right)
        # the writes since the counts were last judged (_tail: a copy, the control thread may append meanwhile)
        since_s = last_s if judged_s is None or last_s is None else min(last_s, judged_s)
        writes = None if since_s is None else _tail(state.throttle_history, since_s)
        for side, (wheel, name) in enumerate(zip(self._wheels, ("left", "right"), strict=True)):
            driven = abs(state.throttles[side]) >= self.driven_throttle
            other_driven = abs(state.throttles[1 - side]) >= self.driven_throttle
            mine, other = ticks[side], ticks[1 - side]
            idle_too_long = wheel.driven_at_s is not None and now_s - wheel.driven_at_s > IDLE_RESET_S
            if mine != wheel.ticks or idle_too_long or (wheel.driven_at_s is None and driven):
                # it turned (or a new stretch begins): the silence, if any, starts now
                counted = mine - wheel.ticks
                # counting the way it is driven (a wheel still rolling forward while driven back is braking)
                turning = (driven and abs(counted) >= MOVING_TICKS and not idle_too_long
                           and (counted > 0) == (state.throttles[side] > 0))
                wheel.moving = (1 if counted > 0 else -1) if turning else 0
                wheel.driven_s = wheel.driven_checks_s = 0.0
                wheel.driven_at_s = now_s if driven else None
                wheel.ticks, wheel.other_ticks, wheel.other_idle = mine, other, not other_driven
                continue
            if not driven:
                continue  # no evidence either way; the stretch waits (IDLE_RESET_S)
            if since_s is None or writes is None or _driven_throughout(writes, side, since_s, state.throttles[side],
                                                                       self.driven_throttle):
                wheel.driven_s += edges_s
                wheel.driven_checks_s += step_s
            else:
                # a late check: between it and the last one the motor was braked or driven the other
                # way (a stale command's stop and a new command, under a starved CPU); a wheel held
                # or reversing may count nothing then: that gap is no silence, as for a brake a check
                # sees, and the wheel is no longer known to be turning
                wheel.moving = 0
            wheel.driven_at_s = now_s
            wheel.other_idle = wheel.other_idle and not other_driven
            other_counted = abs(other - wheel.other_ticks) >= OTHER_WHEEL_TICKS
            # still driven the way it was turning (not reversing: a turn-round can count nothing once)
            same_way = wheel.moving != 0 and (state.throttles[side] > 0) == (wheel.moving > 0)
            driven_s = wheel.driven_s + 1e-6  # check times are sums of float periods: 0.05 may add up to 0.0499..
            sudden = same_way and driven_s >= min(self.encoder_dead_s, SUDDEN_SILENCE_S)
            idle_dead = wheel.other_idle and wheel.driven_checks_s + 1e-6 >= max(self.encoder_dead_s, OTHER_IDLE_DEAD_S)
            if ((driven_s >= self.encoder_dead_s or sudden) and other_counted) or idle_dead:
                message = (
                    f"the {name} wheel's encoder counted nothing while its motor drove for "
                    f"{wheel.driven_checks_s if idle_dead else wheel.driven_s:.2f} s: check the encoder's "
                    "wires; press start to try again"
                )
                log.warning("%s", message)
                state.raise_fault("encoders", message, now_s, latched=True)
                wheel.driven_at_s = None


#: Waiting for the odometry's beats, a check runs on its own time after this many check periods
#: without them (the odometry stalled or restarting): the lidar's checks then come every
#: ``2 * BEAT_TIMEOUT_PERIODS * MOTOR_PERIOD_S`` = 0.125 s, under ``LATE_CHECK_PERIODS * PERIOD_S``,
#: so a stalled odometry never makes them late (a late check judges nothing). Above one, so
#: that beats a few milliseconds late (the odometry's period runs from the end of its reading)
#: still come before it.
BEAT_TIMEOUT_PERIODS = 1.25


async def run(state: SharedState, clock: Clock, monitor: HealthMonitor, beat_period_s: float | None = None) -> None:
    """Every check each ``PERIOD_S``, the weak-motor check alone each ``MOTOR_PERIOD_S`` between.

    With ``beat_period_s`` (the odometry's period, on the real clock) each check runs in the
    odometry's wake-up (:class:`mazebot.clock.Beat`) every ``MOTOR_PERIOD_S`` of its beats
    instead of on a timer of its own: up to 20 wake-ups of the event loop a second fewer
    (about 10 under the quota bench, where the others fell in another task's wake-up; each
    costs the kernel's return from ``epoll_wait`` and a pass of asyncio's machinery besides
    the check's own ~70 µs), and the checks see the encoder counts of a reading just taken.
    Without beats for ``BEAT_TIMEOUT_PERIODS`` check periods it checks on its own time.
    """
    every = max(1, round(PERIOD_S / MOTOR_PERIOD_S))
    beats = None if beat_period_s is None else max(1, round(MOTOR_PERIOD_S / beat_period_s))
    meter = state.cpu.part("health check")
    for k in itertools.count():
        with meter.measure():
            if k % every == 0:
                monitor.check(state, clock.now_s())
            else:
                monitor.check_motors(state, clock.now_s())
        if beats is None:
            await clock.sleep(MOTOR_PERIOD_S)
        else:
            await state.odometry_beat.wait(beats, timeout_s=BEAT_TIMEOUT_PERIODS * MOTOR_PERIOD_S)
