"""The motor control loop: the only writer of motor commands.

It runs at a fixed period (20 Hz by default). Each tick it measures the wheel speeds
from the encoders, takes the planner's latest body-velocity command, passes it through
the safety layer (control deadline, command age, lidar age, lidar returns in the path)
and turns it into throttles with the per-wheel PI controller. In every state other than
``exploring``/``returning`` it commands zero, so a stalled planner, a stop press or a
fault stops the wheels within one period, independently of the motor driver's own
time-to-live.

A direct throttle command (``state.throttle_command``: the benchmark's scripted tour,
tests) bypasses the wheel controller when no planner command is set.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import Self

import numpy as np

from mazebot.clock import Clock
from mazebot.config import (
    Config,
    ControlConfig,
    DriveConfig,
    LidarConfig,
    RobotConfig,
)
from mazebot.io.motors import MotorWriteError
from mazebot.io.scan import Scan
from mazebot.planner.safety import (
    CollisionGuard,
    ControlWatchdog,
    SafetyLayer,
    deskewed_points_robot,
    with_remembered,
)
from mazebot.planner.wheel_control import DriveMode, WheelController, WheelSpeedEstimator
from mazebot.state import SharedState

log = logging.getLogger(__name__)

#: A direct throttle command older than this many control periods is stale.
STALE_PERIODS = 3


class MotorControl:
    """One control tick's decisions, separate from the loop so tests can step it."""

    def __init__(
        self,
        control: ControlConfig,
        drive: DriveConfig,
        robot: RobotConfig,
        lidar: LidarConfig,
        *,
        ticks_per_rev: int,
        jog_ttl_s: float,
        period_s: float,
    ) -> None:
        """The config sections the tick reads, as they are (each default defined once, in the config):
        ``[control]`` (wheel PI, safety layer), ``[drive]`` (wheels, track), ``[robot]`` (the footprint
        the emergency stop keeps clear), ``[lidar]`` (range and mount of the returns it checks); and
        ``[encoders]`` ticks per revolution, ``[motors] command_ttl_s`` (a jog's time-to-live) and
        ``[daemon] control_period_s``. :meth:`from_config` picks them from a loaded configuration."""
        c, d = control, drive
        self.period_s = period_s
        self.jog_ttl_s = jog_ttl_s
        self.wheels = WheelController(
            track_width_m=d.track_width_m,
            max_wheel_speed_mps=d.max_wheel_speed_mps,
            deadband=c.motor_deadband,
            kp=c.wheel_kp,
            ki=c.wheel_ki,
            kd=c.wheel_kd,
            integral_limit=c.integral_limit,
            max_wheel_accel_mps2=c.max_wheel_accel_mps2,
        )
        for pid in (self.wheels.left, self.wheels.right):
            pid.latency_s = c.actuation_latency_s
        self.estimator = WheelSpeedEstimator.for_wheel(
            ticks_per_rev, d.wheel_diameter_m, diameter_ratio=d.wheel_diameter_ratio
        )
        self._faults_raised_seen = 0
        guard = CollisionGuard(
            footprint_radius_m=robot.footprint_radius_m,
            margin_m=c.stop_margin_m,
            side_margin_m=c.side_margin_m,
            brake_decel_mps2=c.brake_decel_mps2,
            latency_s=self.period_s + c.actuation_latency_s,
        )
        self.safety = SafetyLayer(
            guard,
            ControlWatchdog(c.deadline_s),
            command_ttl_ticks=c.command_ttl_ticks,
            scan_timeout_ticks=c.scan_timeout_ticks,
        )
        self.lidar_range_m = (lidar.min_range_m, lidar.max_range_m)
        self.lidar_mount_xy_m = lidar.mount_xy_m
        self._scan_cache: tuple[Scan, np.ndarray] | None = None  # held, not its id(): see Pilot's

    @classmethod
    def from_config(cls, config: Config) -> Self:
        """The control tick of a loaded configuration."""
        return cls(config.control, config.drive, config.robot, config.lidar,
                   ticks_per_rev=config.encoders.ticks_per_rev, jog_ttl_s=config.motors.command_ttl_s,
                   period_s=config.daemon.control_period_s)

    def tick(self, state: SharedState, now_s: float) -> tuple[float, float]:
        """The (left, right) throttles for this period; also updates the measured wheel speeds.

        The wheel speeds come from the odometry task's latest encoder reading (50 Hz, time-
        stamped), not from a reading of our own: the encoders have one reader, so a
        recording of their readings is exactly what the odometry integrated.
        """
        reading = state.wheel_ticks
        if reading is None:  # no encoder reading yet: no speed either (a made-up zero count would
            self.estimator.reset()  # turn the first real count into a speed spike)
            measured = (0.0, 0.0)
        else:
            stamp_s, left_ticks, right_ticks = reading
            measured = self.estimator.update(left_ticks, right_ticks, stamp_s)
        state.wheel_speeds_mps = measured
        moving = state.run_state.moving and not state.stopping
        if state.faults_raised != self._faults_raised_seen:
            # a fault since the last tick stops the wheels, even one already cleared again: a
            # kidnapped robot found again 50 ms after it was lost, between two ticks, kept
            # driving (tests/bench/test_fault_runs.py; motors zero <= 200 ms after a fault:
            # docs/design.md, "The fault suite's targets")
            self._faults_raised_seen = state.faults_raised
            moving = False
        command = state.motion_command
        if moving and command is not None:
            return self._drive(state, command, measured, now_s)
        # keep the deadline clock and the command's and the lidar's ages running while idle
        scan = state.latest_scan
        self.safety.idle(now_s, None if command is None else command.time_s, None if scan is None else scan.end_time_s)
        self.wheels.reset()
        direct = state.throttle_command
        if moving and direct is not None and now_s - direct[2] <= STALE_PERIODS * self.period_s:
            return direct[0], direct[1]
        jog = state.jog_command
        if (jog is not None and not moving and state.run_state.jog_allowed and not state.stopping
                and 0.0 <= now_s - jog[2] <= self.jog_ttl_s):
            return jog[0], jog[1]  # hold-to-run from the setup page: stale after the command time-to-live
        return 0.0, 0.0

    def _drive(self, state: SharedState, command, measured: tuple[float, float], now_s: float) -> tuple[float, float]:
        v, w, mode = command.v_mps, command.w_radps, DriveMode(command.mode)
        points, scan_time_s = self.scan_points(state)
        verdict = self.safety.check(now_s, v, w, command.time_s, points, scan_time_s)
        if verdict.stop:
            if verdict.reason != state.safety_stop:
                log.info("safety stop: %s", verdict.reason)
            state.safety_stop = verdict.reason
            state.safety_stops = self.safety.stops
            v, w, mode = 0.0, 0.0, DriveMode.STOP
        out = self.wheels.update(v, w, mode, measured, self.period_s)
        return out.left_throttle, out.right_throttle

    def scan_points(self, state: SharedState) -> tuple[np.ndarray | None, float | None]:
        """The latest revolution's returns in the robot frame of now, and its end time (None: no scan yet);
        with them the returns the planner remembers from inside the lidar's minimum range
        (``state.blind_zone_points``: a table leg or a wall the robot came too close to see).

        The control process (:mod:`mazebot.tasks.control_process`) gets them from shared
        memory instead, prepared the same way by the daemon's main process.
        """
        # imported here, not with the module: the control process (which overrides this method)
        # imports this module too, and the planner's modules bring scipy and the SLAM grid
        from mazebot.planner.pilot import moved_since_scan

        scan = state.latest_scan
        if scan is None:
            return None, None
        if self._scan_cache is None or self._scan_cache[0] is not scan:
            self._scan_cache = (
                scan,
                deskewed_points_robot(scan.angle_rad, scan.range_m, scan.valid, scan.time_s,
                                      state.odometry_history, *self.lidar_range_m, mount_xy_m=self.lidar_mount_xy_m),
            )
        odo = state.odometry
        points = moved_since_scan(self._scan_cache[1], scan.end_time_s, state)
        pose_now = None if odo is None else (odo.x_m, odo.y_m, odo.theta_rad)
        return with_remembered(points, state.blind_zone_points, pose_now), scan.end_time_s


#: While the control loop runs on its own thread, the interpreter hands the GIL to a thread
#: that asks for it after this long (Python's default is 5 ms: too long for a 50 ms period
#: on a share of a slow core, where 5 ms of wall time can be most of a throttled period).
SWITCH_INTERVAL_S = 0.001

#: How long stopping waits for the control thread's last tick, seconds.
THREAD_JOIN_S = 1.0

Post = Callable[..., object]


def call_now(fn: Callable[..., object], *args: object) -> None:
    """The ``post`` of a loop that runs on the event loop's own thread: call at once."""
    fn(*args)


def tick_once(
    motors, state: SharedState, control: MotorControl, meter, now_s: float, next_tick_s: float, post: Post
) -> float:
    """One period of the loop at ``now_s`` (due at ``next_tick_s``); returns when the next is due.

    ``post(fn, *args)`` runs ``fn`` where the shared state's notes and faults are written:
    directly on the event loop, or handed to it from the control thread.
    """
    period_s = control.period_s
    late_s = now_s - next_tick_s
    state.control_lateness_ms.append(max(0.0, late_s * 1000.0))
    if late_s > control.safety.watchdog.deadline_s:
        post(state.note, "control", f"the control loop was blocked for {late_s + period_s:.2f} s; wheels stopped",
             now_s)
        log.warning("control loop blocked for %.2f s; wheels stopped for a tick", late_s + period_s)
    with meter.measure():
        try:
            left, right = control.tick(state, now_s)
        except Exception:
            _write(motors, state, 0.0, 0.0, now_s, post)
            raise
        _write(motors, state, left, right, now_s, post)
    next_tick_s += period_s
    if next_tick_s < now_s:  # we fell behind (a stalled loop): do not try to catch up
        next_tick_s = now_s + period_s
    return next_tick_s


async def run(motors, state: SharedState, clock: Clock, control: MotorControl, *, thread: bool = False) -> None:
    """Tick ``control`` every period and write its throttles to the motors.

    ``clock`` may be the systemd watchdog's :class:`~mazebot.sdnotify.ControlHeartbeat`,
    which notes every tick's sleep; lateness of each tick beyond its period goes into
    ``state.control_lateness_ms``. A failed write to the motor HAT (I²C error: the
    driver has already told both motors to brake) is a ``motors`` fault, not a crash:
    the loop keeps ticking, writing zeros, and the fault clears once a write succeeds.

    With ``thread`` (the real clock only) the ticks run on a thread of their own, timed by
    the monotonic clock the event loop also reads: on one core the kernel then lets a due
    tick run in the middle of a revolution's SLAM or a planner tick, where on the event
    loop it waits for them to yield. This coroutine lives as long as the thread, and a
    crash of the thread is raised here, so the supervisor handles both alike.
    """
    meter = state.cpu.part("control tick")
    if thread:
        await _run_on_thread(motors, state, clock, control, meter)
        return
    next_tick_s = clock.now_s()
    while True:
        now_s = clock.now_s()
        next_tick_s = tick_once(motors, state, control, meter, now_s, next_tick_s, call_now)
        state.throttle_history.append((now_s, *state.throttles))  # what the motors have from now on
        await clock.sleep(next_tick_s - clock.now_s())


async def _run_on_thread(motors, state: SharedState, clock: Clock, control: MotorControl, meter) -> None:
    loop = asyncio.get_running_loop()
    finished: asyncio.Future[None] = loop.create_future()
    stop = threading.Event()
    beats = hasattr(clock, "last_tick_s")  # the systemd watchdog's ControlHeartbeat

    def post(fn: Callable[..., object], *args: object) -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed under us: nothing left to tell
            loop.call_soon_threadsafe(fn, *args)

    def report(error: BaseException | None) -> None:
        if finished.done():
            return
        if error is None:
            finished.set_result(None)
        else:
            finished.set_exception(error)

    def ticks() -> None:
        error: BaseException | None = None
        try:
            next_tick_s = time.monotonic()
            while not stop.is_set():
                now_s = time.monotonic()
                next_tick_s = tick_once(motors, state, control, meter, now_s, next_tick_s, post)
                state.throttle_history.append((now_s, *state.throttles))  # a deque's append: thread-safe
                if beats:
                    clock.last_tick_s = now_s  # type: ignore[attr-defined]
                stop.wait(max(0.0, next_tick_s - time.monotonic()))
        except BaseException as exc:  # handed to the supervisor on the loop
            error = exc
        post(report, error)

    previous_interval_s = sys.getswitchinterval()
    sys.setswitchinterval(min(previous_interval_s, SWITCH_INTERVAL_S))
    worker = threading.Thread(target=ticks, name="mazebot-control", daemon=True)
    worker.start()
    try:
        await asyncio.shield(finished)
    finally:
        stop.set()
        worker.join(THREAD_JOIN_S)  # wakes from its wait at once; at most one tick to finish
        sys.setswitchinterval(previous_interval_s)
        if worker.is_alive():  # a tick hung in the motor driver: brake from here
            log.error("the control thread did not stop within %.1f s; braking the motors", THREAD_JOIN_S)
            with contextlib.suppress(Exception):
                motors.stop()


def _write(motors, state: SharedState, left: float, right: float, now_s: float, post: Post = call_now) -> None:
    """Write the throttles; a HAT that fails is a fault that clears on the next good write.

    The fault's bookkeeping goes through ``post`` (see :func:`tick_once`); the throttles
    written are the control loop's own field.
    """
    try:
        if left == 0.0 and right == 0.0:
            motors.stop()
        else:
            motors.set(left, right)
    except (MotorWriteError, OSError) as exc:
        state.throttles = (0.0, 0.0)
        if not any(f.source == "motors" for f in state.faults):
            message = f"cannot write to the motor HAT ({exc}); check its I²C connection and power"
            log.error("%s", message)
            post(state.raise_fault, "motors", message, now_s)
        return
    state.throttles = (left, right)
    if any(f.source == "motors" for f in state.faults):
        post(state.clear_faults, "motors")
        post(state.note, "motors", "the motor HAT answers again", now_s)
        log.info("the motor HAT answers again")
