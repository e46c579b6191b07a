"""Dead reckoning from wheel ticks against the simulator's physics as ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.sim.physics import PhysicsParams, RobotPhysics
from mazebot.sim.world import World
from mazebot.slam.odometry import DiffDriveOdometry

TICKS_PER_REV = 4000  # fine encoders: the error left is the gearbox's play, not the counts' quantization
BACKLASH_RAD = math.radians(3.0)  # the cheap robot's gearbox ([sim] backlash_deg of the cheap preset)


def _open_floor() -> World:
    return World("floor", np.zeros((0, 4)), np.zeros((0, 3)), (0.0, 0.0, 0.0), (-50.0, -50.0, 50.0, 50.0))


def _turns_in_place_heading_errors_rad(backlash_rad: float) -> list[float]:
    """The odometry's heading error after each of eight in-place turns that alternate in direction.

    The physics' wheel angles are its encoder shafts; the wheels follow them through the play.
    """
    params = PhysicsParams.ideal(backlash_rad=BACKLASH_RAD)
    robot = RobotPhysics(params, _open_floor(), (0.0, 0.0, 0.0), np.random.default_rng(1))
    odometry = DiffDriveOdometry(TICKS_PER_REV, params.wheel_diameter_m, params.track_width_m,
                                 backlash_rad=backlash_rad)
    ticks_per_rad = TICKS_PER_REV / math.tau

    def read() -> None:
        left_rad, right_rad = robot.wheel_angle_rad
        odometry.update(round(left_rad * ticks_per_rad), round(right_rad * ticks_per_rad))

    read()
    errors_rad = []
    for turn in range(8):
        sign = 1.0 if turn % 2 == 0 else -1.0
        for throttle in (0.4 * sign, 0.0):  # turn for 0.8 s, then stand until the wheels stop
            robot.set_throttle(-throttle, throttle)
            for _ in range(40):
                robot.step(0.02)
                read()
        errors_rad.append(math.remainder(odometry.pose.theta_rad - robot.theta_rad, math.tau))
    return errors_rad


def test_the_gearbox_play_taken_up_after_each_reversal_is_not_counted_as_a_turn() -> None:
    # without the play: every reversal of both wheels counts 2 x 3 deg of wheel angle the wheels
    # never turned, a step of about 0.65 deg in heading that flips sign with the next reversal
    plain = _turns_in_place_heading_errors_rad(0.0)
    assert max(abs(e) for e in plain) > math.radians(0.4)
    with_play = _turns_in_place_heading_errors_rad(BACKLASH_RAD)
    assert max(abs(e) for e in with_play) < math.radians(0.05)


def test_a_negative_backlash_is_refused() -> None:
    with pytest.raises(ValueError, match="backlash_rad"):
        DiffDriveOdometry(80, 0.065, 0.15, backlash_rad=-0.01)
