"""The odometry task's one-pose composition gives exactly ``posegraph.compose``'s numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.geometry import compose
from mazebot.tasks.odometry_task import _compose


def test_scalar_compose_is_bit_identical_to_posegraph_compose() -> None:
    rng = np.random.default_rng(7)
    poses = rng.normal(0.0, 3.0, size=(5_000, 6))
    # headings on and around the wrap points, and exact zeros
    poses[:200, 2] = rng.choice([math.pi, -math.pi, 0.0, math.pi / 2, 2 * math.pi], 200)
    poses[200:400, 5] = -poses[200:400, 2] + rng.choice([math.pi, -math.pi, 0.0], 200)
    poses[400:500, :] = 0.0
    for a in poses:
        want = tuple(float(v) for v in compose(a[:3], a[3:]))
        got = _compose((a[0], a[1], a[2]), float(a[3]), float(a[4]), float(a[5]))
        assert got == want, (a, got, want)


def test_the_speed_loop_and_the_odometry_measure_a_tick_alike() -> None:
    """A calibrated wheel diameter ratio reaches the control loop's wheel speeds as well as the odometry."""
    from mazebot.config import Config
    from mazebot.slam.odometry import DiffDriveOdometry
    from mazebot.tasks.control_task import MotorControl

    config = Config()
    config.drive.wheel_diameter_ratio = 1.03
    d = config.drive
    odo = DiffDriveOdometry(config.encoders.ticks_per_rev, d.wheel_diameter_m, d.track_width_m, d.wheel_diameter_ratio)
    estimator = MotorControl.from_config(config).estimator
    assert estimator.metres_per_tick == (odo.metres_per_tick_left, odo.metres_per_tick_right)


def test_no_encoder_reading_yet_is_no_speed_not_a_zero_count() -> None:
    """Encoders that already counted (a restarted task) must not read as a jump from zero ticks."""
    from mazebot.config import Config
    from mazebot.state import SharedState
    from mazebot.tasks.control_task import MotorControl

    control = MotorControl.from_config(Config())
    state = SharedState()
    control.tick(state, 1.00)  # no reading yet
    state.wheel_ticks = (1.05, 5000, 5000)
    control.tick(state, 1.05)
    assert state.wheel_speeds_mps == (0.0, 0.0)
    state.wheel_ticks = (1.10, 5010, 5020)
    control.tick(state, 1.10)
    per_tick_m = control.estimator.metres_per_tick[0]
    smoothing = control.estimator.smoothing
    want = ((1 - smoothing) * 10 * per_tick_m / 0.05, (1 - smoothing) * 20 * per_tick_m / 0.05)
    assert state.wheel_speeds_mps == pytest.approx(want)
