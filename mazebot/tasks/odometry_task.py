"""Dead reckoning at the configured rate from the wheel encoders, and the robot's map pose."""

from __future__ import annotations

import math

from mazebot.clock import Clock
from mazebot.config import DriveConfig, EncodersConfig
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.odometry import DiffDriveOdometry
from mazebot.state import SharedState


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
    while True:
        with meter.measure():
            reading = encoders.read()
            odometry.update(reading.left_ticks, reading.right_ticks)
            odo = odometry.pose
            now_s = reading.time_s if getattr(reading, "time_s", None) is not None else clock.now_s()
            history.append(now_s, odo.x_m, odo.y_m, odo.theta_rad)
            stats = state.sensors
            stats.encoder_ticks_left = reading.left_ticks
            stats.encoder_ticks_right = reading.right_ticks
            stats.encoder_invalid_transitions = reading.invalid_transitions
            state.odometry = odo
            x, y, th = _compose(state.map_from_odom, odo.x_m, odo.y_m, odo.theta_rad)
            state.pose.x_m = x
            state.pose.y_m = y
            state.pose.theta_rad = th
            state.pose_time_s = now_s
            state.wheel_ticks = (now_s, reading.left_ticks, reading.right_ticks)
        await clock.sleep(period_s)


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
