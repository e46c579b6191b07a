"""Dead reckoning at the configured rate from the wheel encoders, and the robot's map pose."""

from __future__ import annotations

import math
from collections.abc import Iterable

from mazebot.clock import Clock
from mazebot.config import DriveConfig, EncodersConfig
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.odometry import DiffDriveOdometry
from mazebot.state import OdometryStep, SharedState
from mazebot.taps import notify

#: With the motors braked (both throttles 0) and no new edge for this long, the wheels rest
#: and the odometry pose holds up to the reading's time. Until then a reading without a new
#: edge adds nothing to the history: the edges may only be late (under a 25 % quota the
#: thread that counts them waits 80 ms and more for its turn, 270 ms once on a 16x16 maze),
#: and a pose dated "now" would then be that stale. Longer than the HAT's short brake takes
#: to stop a wheel; SLAM waits for the odometry to cover a revolution (``slam_task``), so
#: one or two revolutions after a stop wait that long.
#: Time, not a count of what the loop did, is right here: what it waits for is physical (a
#: braked wheel coming to rest), and both ends are the robot's own stamps, not the times the
#: loop got to run: the brake's from the control loop's write (``BrakedSince``), the last
#: edge's from the encoder's stamp. A reading that comes late sees both ages grown by the same
#: real time the wheels had to stop in; it can never call wheels resting that were braked less
#: than this before (a count of readings or checks would, on a fast CPU, stand for less time).
REST_AFTER_S = 0.25
#: Driven but without a single edge for this long, a wheel does not turn (a throttle in the
#: motor's dead band, a jammed wheel): its pose holds, whatever the throttles say.
STILL_WHEN_DRIVEN_S = 1.0


async def run(
    encoders,
    state: SharedState,
    clock: Clock,
    enc_cfg: EncodersConfig,
    drive: DriveConfig,
    history_s: float = 3.0,
    odometry: DiffDriveOdometry | None = None,
) -> None:
    """Read the tick counters every ``1 / odometry_rate_hz`` s and integrate the pose.

    Every odometry pose goes, time-stamped, into ``state.odometry_history`` (SLAM de-skews
    each lidar sample and predicts its filter from it). ``state.pose`` is published at the
    odometry rate in the map frame: SLAM's latest correction ``state.map_from_odom``
    composed with the odometry (the ROS ``map -> odom -> base_link`` chain); before SLAM's
    first scan the correction is the identity and the pose is the dead-reckoned one.
    Pass ``odometry`` (and keep ``state.odometry_history``) so a restart continues them.
    """
    # a restarted task carries on from the same odometry and history: the pose never jumps
    odometry = odometry or DiffDriveOdometry(
        enc_cfg.ticks_per_rev, drive.wheel_diameter_m, drive.track_width_m, drive.wheel_diameter_ratio
    )
    history = state.odometry_history or OdometryHistory(history_s)
    state.odometry_history = history
    period_s = 1.0 / enc_cfg.odometry_rate_hz
    meter = state.cpu.part("odometry")
    last_counts: tuple[int, int] | None = None
    driven_s = -math.inf  # the last reading while a throttle was not 0 (without the control's write times)
    brakes = BrakedSince()
    while True:
        with meter.measure():
            reading = encoders.read()
            now_s = reading.time_s if getattr(reading, "time_s", None) is not None else clock.now_s()
            edge_age_s = getattr(reading, "edge_age_s", None)
            _between(state, odometry, history, reading, now_s, period_s)
            odometry.update(reading.left_ticks, reading.right_ticks)
            odo = odometry.pose
            counts = (reading.left_ticks, reading.right_ticks)
            if state.throttles != (0.0, 0.0):
                driven_s = now_s
            braked_since_s = brakes.update(state.throttle_history, driven_s)
            pose_s = _pose_time_s(now_s, edge_age_s, counts != last_counts, history,
                                  now_s - braked_since_s)
            if counts != last_counts and edge_age_s is not None:
                state.odometry_edge_age_ms.append(edge_age_s * 1000.0)
            last_counts = counts
            if pose_s is not None:
                history.append(pose_s, odo.x_m, odo.y_m, odo.theta_rad)
                state.pose_time_s = pose_s
                # each wheel's own travel at the same date: the health monitor's weak-motor check
                state.wheel_travel.append((pose_s, reading.left_ticks * odometry.metres_per_tick_left,
                                           reading.right_ticks * odometry.metres_per_tick_right))
            if state.odometry_listeners:
                step = OdometryStep(now_s, pose_s, int(reading.left_ticks), int(reading.right_ticks),
                                    int(reading.invalid_transitions))
                notify(state.odometry_listeners, step, "state.odometry_listeners")
            stats = state.sensors
            stats.encoder_ticks_left = reading.left_ticks
            stats.encoder_ticks_right = reading.right_ticks
            stats.encoder_edge_time_s = None if edge_age_s is None else now_s - edge_age_s
            stats.encoder_invalid_transitions = reading.invalid_transitions
            state.odometry = odo
            x, y, th = _compose(state.map_from_odom, odo.x_m, odo.y_m, odo.theta_rad)
            state.pose.x_m = x
            state.pose.y_m = y
            state.pose.theta_rad = th
            state.wheel_ticks = (now_s, reading.left_ticks, reading.right_ticks)
        state.odometry_beat.tick()  # the tasks that follow the odometry's wake-ups run next
        await clock.sleep(period_s)


def _between(state: SharedState, odometry: DiffDriveOdometry, history: OdometryHistory, reading, now_s: float,
             period_s: float) -> None:
    """Poses at the edges' own times inside a gap the readings left (``reading.steps``), into the history.

    A reading late by a few hundred milliseconds (a process starved by a CPU quota, a long
    planner stage) used to give the history one pose at each end of the gap, and SLAM
    interpolated between them: a turn that began inside the gap was smeared over all of it,
    degrees of heading off at its start (the odometry's heading error over 0.2 s: p99
    0.64-0.67° in 16x16 runs under a 25 % quota, 3.1-3.4° in earlier ones, its worst windows
    those with gaps of 0.2-0.45 s; 0.22° with these poses). The edge samples say how the
    wheels got there, so the history holds a pose at least every ``period_s`` of the edges'
    time (one sample every ``EDGE_SAMPLE_PERIOD_S``) whatever the loop did. Only inside a gap: a prompt
    reading adds nothing, and a replay of a recording (each step is given to the listeners)
    builds the same history.
    """
    steps = getattr(reading, "steps", ())
    if not steps or reading.edge_age_s is None:
        return
    newest_s = now_s - reading.edge_age_s  # the reading's own pose is dated there
    span = history.span_s
    last_s = span[1] if span is not None else -math.inf
    for age_s, left, right in steps:
        time_s = now_s - age_s
        if time_s - last_s < period_s or newest_s - time_s < period_s:
            continue
        odometry.update(left, right)
        odo = odometry.pose
        history.append(time_s, odo.x_m, odo.y_m, odo.theta_rad)
        travel = (time_s, left * odometry.metres_per_tick_left, right * odometry.metres_per_tick_right)
        state.wheel_travel.append(travel)
        if state.odometry_listeners:
            notify(state.odometry_listeners, OdometryStep(now_s, time_s, int(left), int(right),
                                                          int(reading.invalid_transitions)), "state.odometry_listeners")
        last_s = time_s


class BrakedSince:
    """Since when both motors have been braked, by the control loop's writes and their own times.

    The odometry's readings are no clock for that: a reading late by 0.3 s (a starved
    process) that finds the throttles at 0 would date the brake from the reading before it,
    and call wheels resting that were braked a moment ago and may still coast, while their
    last edges are late too. ``state.throttle_history`` holds each write with the control
    tick's time; without one (no control loop in this process, nor a control process'
    ticks read), the readings' rule stands in.
    """

    def __init__(self) -> None:
        self._seen_s = -math.inf  # the newest write looked at
        self._since_s: float | None = None  # the first write of 0, 0 after the last one that drove; None: driven

    def update(self, writes: Iterable[tuple[float, float, float]], fallback_s: float) -> float:
        """The time since which both throttles have been 0 (``writes``: time, left, right, oldest first).

        ``fallback_s`` (the last reading that saw a throttle) when there is no write yet.
        """
        fresh: list[tuple[float, float, float]] = []
        for write in reversed(tuple(writes)):  # a copy: the control thread appends
            if write[0] <= self._seen_s:
                break
            fresh.append(write)
        for time_s, left, right in reversed(fresh):
            if left == 0.0 and right == 0.0:
                if self._since_s is None:
                    self._since_s = time_s
            else:
                self._since_s = None
            self._seen_s = time_s
        if self._seen_s == -math.inf:
            return fallback_s
        return math.inf if self._since_s is None else self._since_s


def _pose_time_s(now_s: float, edge_age_s: float | None, new_edges: bool, history: OdometryHistory,
                 braked_s: float = math.inf) -> float | None:
    """The time an odometry reading's pose describes; None: nothing new to add to the history.

    The counts hold every edge up to the newest one counted, so the pose is the wheels' pose
    at that edge's stamp (``now_s - edge_age_s``), not at the time of reading: under a CPU
    quota the encoder thread gets the edges in bursts, tens of milliseconds late, and a pose
    dated by the reading time is that late too (SLAM de-skews and predicts each revolution
    from these dates). Without a new edge the counts are older than the reading only if the
    edges are late: the pose holds until now only once the wheels rest (``braked_s``, how
    long the motors have been braked, and the newest edge both ``REST_AFTER_S`` old, or no
    edge for ``STILL_WHEN_DRIVEN_S``). No usable stamp (a pin factory on another clock):
    the reading's time, as before. Never earlier than the history's newest entry.
    """
    if edge_age_s is None:
        pose_s = now_s
    elif new_edges:
        pose_s = now_s - edge_age_s
    elif (edge_age_s >= REST_AFTER_S and braked_s >= REST_AFTER_S) or edge_age_s >= STILL_WHEN_DRIVEN_S:
        pose_s = now_s
    else:
        return None
    span = history.span_s
    if span is not None and pose_s < span[1]:
        return span[1] if new_edges else None
    return pose_s


def _compose(a: tuple[float, float, float], x_m: float, y_m: float, theta_rad: float) -> tuple[float, float, float]:
    """``posegraph.compose(a, (x, y, theta))`` for one pose, in floats: the same numbers.

    The same arithmetic in the same order (libm's cos and sin, the heading wrapped to
    [-π, π) by a floored remainder, like ``np.remainder``), without the dozen numpy calls
    on 0-d arrays that cost ~40 µs, 50 times a second (``tests/tasks/test_odometry_task.py``
    compares the two).
    """
    ax, ay, at = (float(v) for v in a)
    c, s = math.cos(at), math.sin(at)
    return (ax + c * x_m - s * y_m, ay + s * x_m + c * y_m, (at + theta_rad + math.pi) % math.tau - math.pi)
