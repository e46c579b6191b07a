"""Dead reckoning at the configured rate from the wheel encoders."""

from __future__ import annotations

from mazebot.clock import Clock
from mazebot.config import DriveConfig, EncodersConfig
from mazebot.slam.odometry import DiffDriveOdometry
from mazebot.state import SharedState


async def run(
    encoders, state: SharedState, clock: Clock, enc_cfg: EncodersConfig, drive: DriveConfig
) -> None:
    """Read the tick counters every ``1 / odometry_rate_hz`` s and integrate the pose.

    Until SLAM corrects it, the dead-reckoned pose is the robot's pose estimate.
    """
    odometry = DiffDriveOdometry(enc_cfg.ticks_per_rev, drive.wheel_diameter_m, drive.track_width_m)
    period_s = 1.0 / enc_cfg.odometry_rate_hz
    while True:
        reading = encoders.read()
        odometry.update(reading.left_ticks, reading.right_ticks)
        stats = state.sensors
        stats.encoder_ticks_left = reading.left_ticks
        stats.encoder_ticks_right = reading.right_ticks
        stats.encoder_invalid_transitions = reading.invalid_transitions
        state.odometry = odometry.pose
        state.pose.x_m = odometry.pose.x_m
        state.pose.y_m = odometry.pose.y_m
        state.pose.theta_rad = odometry.pose.theta_rad
        await clock.sleep(period_s)
