"""Wheel control on the simulated motors: step response, anti-windup, mode resets, in-place turns.

The plant is :class:`RobotPhysics` with its default imperfections (deadband 0.08, first-order
lag 80 ms, right motor 3 % weak, battery sag, slip); the speed feedback is what the encoders
would give: wheel angles quantised to 840 ticks per turn, differenced at 20 Hz. Figures are
read from the simulated wheel speeds, not from the controller's own beliefs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.planner.wheel_control import (
    DiffDriveKinematics,
    DriveMode,
    HeadingAligner,
    WheelController,
    WheelGainEstimator,
    WheelPid,
    WheelSpeedEstimator,
)
from mazebot.sim.physics import PhysicsParams, RobotPhysics
from mazebot.sim.world import World

DT = 0.05
TICKS = 840


def open_floor() -> World:
    return World("floor", np.zeros((0, 4)), np.zeros((0, 3)), (0.0, 0.0, 0.0), (-50.0, -50.0, 50.0, 50.0))


class Bench:
    """The simulated robot, its encoders and a wheel controller, stepped at 20 Hz.

    ``latency_periods`` delays every throttle by that many control periods (an actuator
    that answers late); the controller is told about it through ``latency_s``.
    """

    def __init__(self, latency_periods: int = 0, seed: int = 0, start_heading: float = 0.0) -> None:
        self.robot = RobotPhysics(PhysicsParams(), open_floor(), (0.0, 0.0, start_heading), np.random.default_rng(seed))
        self.ctl = WheelController(track_width_m=0.15, max_wheel_speed_mps=0.6, deadband=0.08)
        for pid in (self.ctl.left, self.ctl.right):
            pid.latency_s = latency_periods * DT
        self.est = WheelSpeedEstimator.for_wheel(TICKS, 0.065)
        self.queue = [(0.0, 0.0)] * latency_periods
        self.t = 0.0
        self.measured = (0.0, 0.0)

    def step(self, v: float, w: float, mode: DriveMode = DriveMode.DRIVE) -> tuple[float, float]:
        left, right = self.robot.wheel_angle_rad
        self.measured = self.est.update(
            math.floor(left / math.tau * TICKS), math.floor(right / math.tau * TICKS), self.t
        )
        cmd = self.ctl.update(v, w, mode, self.measured, DT)
        self.queue.append((cmd.left_throttle, cmd.right_throttle))
        self.robot.set_throttle(*self.queue.pop(0))
        self.robot.step(DT)
        self.t += DT
        return self.robot.wheel_speed_mps


def step_response(target: float, latency_periods: int, seconds: float = 2.5) -> np.ndarray:
    bench = Bench(latency_periods)
    rows = [(bench.t, *bench.step(target, 0.0)) for _ in range(int(seconds / DT))]
    return np.array(rows)


@pytest.mark.parametrize("latency_periods", [0, 1, 2])
@pytest.mark.parametrize("target", [0.1, 0.2, 0.3])
def test_speed_step_response_on_the_simulated_motor(target: float, latency_periods: int) -> None:
    h = step_response(target, latency_periods)
    t = h[:, 0] + DT
    for col in (1, 2):  # both wheels, the weak right one included
        v = h[:, col]
        t10 = t[np.argmax(v >= 0.1 * target)]
        t90 = t[np.argmax(v >= 0.9 * target)]
        assert t90 - t10 <= 0.35  # rise time
        assert v.max() <= 1.10 * target  # overshoot at most 10 %
        steady = v[t >= 1.5]
        assert abs(steady.mean() - target) <= 0.02 * target  # the integral removes the motor mismatch
        assert steady.std() <= 0.03 * target


def test_both_wheels_end_up_matched_so_the_robot_drives_straight() -> None:
    bench = Bench()
    for _ in range(int(4.0 / DT)):
        bench.step(0.2, 0.0)
    x, _y, th = bench.robot.pose
    assert x > 0.6
    assert abs(math.degrees(th)) < 3.0  # an open-loop 3 % weaker motor would curve it far more


def test_anti_windup_recovers_quickly_after_saturation() -> None:
    bench = Bench()
    for _ in range(int(2.0 / DT)):  # ask for more than the motors can give: the output saturates
        bench.step(0.8, 0.0)
    assert abs(bench.ctl.left.integral) <= bench.ctl.left.integral_limit + 1e-12
    speeds = [bench.step(0.2, 0.0) for _ in range(int(1.5 / DT))]
    left = np.array([s[0] for s in speeds])
    assert left[-10:].mean() == pytest.approx(0.2, rel=0.03)
    assert left[int(0.6 / DT) :].min() >= 0.18  # no long undershoot from a wound-up integral


def test_integral_is_reset_when_the_mode_changes() -> None:
    bench = Bench()
    for _ in range(40):
        bench.step(0.2, 0.0, DriveMode.DRIVE)
    assert bench.ctl.right.integral != 0.0
    bench.step(0.0, 0.6, DriveMode.TURN)
    # the first TURN tick starts from a clean integral (only its own step in it)
    assert abs(bench.ctl.right.integral) <= bench.ctl.right.ki * 0.2 * DT + 1e-9
    cmd = bench.ctl.update(0.0, 0.0, DriveMode.STOP, bench.measured, DT)
    assert (cmd.left_throttle, cmd.right_throttle) == (0.0, 0.0)
    assert bench.ctl.left.integral == bench.ctl.right.integral == 0.0


def test_feed_forward_compensates_the_deadband() -> None:
    pid = WheelPid(max_wheel_speed_mps=0.6, deadband=0.08)
    assert pid.feed_forward(0.0) == 0.0
    assert pid.feed_forward(0.3) == pytest.approx(0.08 + 0.92 * 0.5)
    assert pid.feed_forward(-0.6) == pytest.approx(-1.0)
    assert pid.feed_forward(0.01) > 0.08  # even a crawl gets past the deadband
    assert pid.update(0.0, 0.1, DT) == 0.0  # a stop is a brake, whatever the wheel does


def test_kinematics_keeps_the_curvature_when_saturating() -> None:
    k = DiffDriveKinematics(track_width_m=0.15, max_wheel_speed_mps=0.3)
    left, right = k.wheel_speeds(0.3, 2.0)
    assert max(abs(left), abs(right)) == pytest.approx(0.3)
    v, w = k.body_velocity(left, right)
    assert w / v == pytest.approx(2.0 / 0.3)
    assert k.body_velocity(*k.wheel_speeds(0.1, -0.5)) == pytest.approx((0.1, -0.5))


def test_speed_estimator_from_ticks() -> None:
    est = WheelSpeedEstimator.for_wheel(840, 0.065, smoothing=0.0)
    assert est.update(0, 0, 0.0) == (0.0, 0.0)
    per_tick = math.pi * 0.065 / 840
    left, right = est.update(84, -42, 0.1)
    assert left == pytest.approx(84 * per_tick / 0.1)
    assert right == pytest.approx(-42 * per_tick / 0.1)


def turn(target_rad: float, latency_periods: int = 0, start_heading: float = 0.0) -> tuple[list[float], list[float]]:
    """Turn the simulated robot in place; returns (heading errors, commanded rates) per tick."""
    bench = Bench(latency_periods, start_heading=start_heading)
    aligner = HeadingAligner(latency_s=0.05 + latency_periods * DT)
    errors, rates = [], []
    for _ in range(int(6.0 / DT)):
        _, w_meas = bench.ctl.kinematics.body_velocity(*bench.measured)
        w, done = aligner.command(bench.robot.theta_rad, target_rad, w_meas)
        bench.step(0.0, w, DriveMode.STOP if done else DriveMode.TURN)
        errors.append(math.remainder(target_rad - bench.robot.theta_rad, math.tau))
        rates.append(w)
    return errors, rates


@pytest.mark.parametrize("latency_periods", [0, 1, 2])
@pytest.mark.parametrize("target_deg", [90, -90, 179, -179, 180, 45, 10, 135])
def test_in_place_turn_stops_in_the_band_without_oscillating(target_deg: float, latency_periods: int) -> None:
    errors, rates = turn(math.radians(target_deg), latency_periods)
    tolerance = math.radians(4.0)
    assert abs(errors[-1]) <= tolerance  # settled inside the band
    assert max(abs(e) for e in errors[-20:]) <= tolerance  # and stays there, not hunting
    signs = [math.copysign(1, r) for r in rates if r != 0.0]
    assert all(s == signs[0] for s in signs)  # never reverses: no oscillation
    if abs(target_deg) < 179:  # shortest way round
        assert signs[0] == math.copysign(1, target_deg)


def test_a_turn_near_180_degrees_keeps_its_direction() -> None:
    aligner = HeadingAligner()
    w, done = aligner.command(0.0, math.radians(179.0))
    assert not done and w > 0
    # halfway round, noise puts the error just past 180 degrees the other way: keep going
    w, _ = aligner.command(math.radians(-2.0), math.radians(179.0), 1.0)
    assert w > 0
    aligner.reset()
    w, _ = aligner.command(math.radians(-2.0), math.radians(179.0))
    assert w < 0  # a fresh turn takes the shortest way again


def test_aligner_holds_a_reached_heading() -> None:
    aligner = HeadingAligner()
    assert aligner.command(0.0, math.radians(2.0)) == (0.0, True)
    assert aligner.command(math.radians(-1.5), math.radians(2.0), yaw_rate_radps=0.0) == (0.0, True)
    # 6 degrees off while still coasting: wait for it to settle rather than hunt
    assert aligner.command(math.radians(-4.0), math.radians(2.0), yaw_rate_radps=-0.3) == (0.0, True)
    w, done = aligner.command(math.radians(-4.0), math.radians(2.0), yaw_rate_radps=0.0)
    assert not done and 0 < w < 0.7  # settled outside the band: a slow correction


def test_the_gain_fit_explains_a_nominal_motors_lag_and_sees_a_weak_ones_share() -> None:
    # wheels that follow the nominal motor through its lag (left) and at 40 % of it (right):
    # gains 1 and 0.4 at every full window, through a start from rest and a reversal
    est = WheelGainEstimator(0.6, 0.08, 0.05, latency_s=0.0, time_constant_s=0.12, brake_time_constant_s=0.12)
    keep = 1.0 - math.exp(-0.05 / 0.12)
    speed_mps = 0.0
    for throttle in [0.0] * 5 + [0.4] * 10 + [-0.3] * 10:
        speed_mps += (est.nominal_speed_mps(throttle) - speed_mps) * keep
        left, right = est.update((throttle, throttle), (speed_mps, 0.4 * speed_mps))
        if left is not None and right is not None:
            assert (left, right) == (pytest.approx(1.0), pytest.approx(0.4))
    assert est.gains == (pytest.approx(1.0), pytest.approx(0.4))


def test_a_window_that_barely_moves_tells_nothing() -> None:
    est = WheelGainEstimator(0.6, 0.08, 0.05, min_speed_mps=0.03)
    for _ in range(20):
        est.update((0.085, 0.1), (0.0, 0.01))  # inside the deadband, and 1.3 cm/s above it
    assert est.gains == (None, None)


def test_a_wheel_whose_encoder_went_silent_gives_no_gain() -> None:
    # the fault suite's encoder-dead: the window still holds the speeds from before the cut, so
    # a fit would say "weak" for a few periods before the dead-encoder check says what it is
    est = WheelGainEstimator(0.6, 0.08, 0.05)
    for _ in range(10):
        est.update((0.4, 0.4), (0.19, 0.19))
    assert est.gains[0] == pytest.approx(0.9, abs=0.1)
    speed_mps = 0.19
    for _ in range(3):
        speed_mps *= 0.3  # the speed estimate's smoothing decaying to 0
        est.update((0.4, 0.4), (speed_mps, 0.19))
    assert est.gains[0] is None and est.gains[1] is not None


def test_a_late_update_starts_the_window_again() -> None:
    # a blocked event loop: the model cannot know what the wheels did meanwhile
    est = WheelGainEstimator(0.6, 0.08, 0.05)
    for _ in range(10):
        est.update((0.4, 0.4), (0.19, 0.19), 0.05)
    assert est.gains[0] is not None
    est.update((0.4, 0.4), (0.0, 0.0), 0.5)
    assert est.gains == (None, None)


def test_speed_estimator_takes_the_calibrated_diameter_ratio() -> None:
    """Unequal wheels: the larger one turns fewer ticks for the same rim speed."""
    ratio = 1.04
    est = WheelSpeedEstimator.for_wheel(840, 0.065, smoothing=0.0, diameter_ratio=ratio)
    est.update(0, 0, 0.0)
    left, right = est.update(round(840 * ratio), 840, 1.0)  # rims at one speed: the left (smaller) counts more
    assert left == pytest.approx(right, rel=2e-3)
    from mazebot.slam.odometry import DiffDriveOdometry

    odo = DiffDriveOdometry(840, 0.065, 0.15, ratio)
    assert est.metres_per_tick == pytest.approx((odo.metres_per_tick_left, odo.metres_per_tick_right))


@pytest.mark.parametrize("told", [False, True])
def test_unequal_wheels_drive_straight_once_the_ratio_is_known(told: bool) -> None:
    """True right wheel 4 % larger than the left: equal tick rates curve the robot left.

    Told the ratio (what ``mazebot calibrate`` writes), the speed loop drives equal rim
    speeds: once the wheels are up to speed (the first second; holding the heading is
    the planner's job) the heading stays put. Not told, the robot keeps turning by the
    ratio's arc, d_theta/dt = v (ratio - 1) / track (~0.05 rad/s here).
    """
    ratio = 1.04
    params = PhysicsParams.ideal(
        wheel_diameter_left_scale=2.0 / (1.0 + ratio), wheel_diameter_right_scale=2.0 * ratio / (1.0 + ratio)
    )
    bench = Bench()
    bench.robot = RobotPhysics(params, open_floor(), (0.0, 0.0, 0.0), np.random.default_rng(0))
    bench.est = WheelSpeedEstimator.for_wheel(TICKS, 0.065, diameter_ratio=ratio if told else 1.0)
    headings = []
    for _ in range(int(3.0 / DT)):
        bench.step(0.2, 0.0)
        headings.append(bench.robot.theta_rad)
    turned_rad = headings[-1] - headings[int(1.0 / DT)]  # over the last 2 s
    if told:
        assert abs(turned_rad) < 0.005
    else:
        assert turned_rad > 0.08


@pytest.mark.parametrize("stop_ticks", [0, 1, 2])
@pytest.mark.parametrize("v0", [0.1, 0.27])
def test_a_turn_in_place_begun_while_driving_backs_the_robot_up_by_little(v0: float, stop_ticks: int) -> None:
    """Driving at ``v0``, then (after ``stop_ticks`` of braking) told to turn in place: the body coasts
    forward within a stopping distance and backs up by little.

    The speed controllers' reference model used to restart from rest at the mode change; the
    wheel that keeps turning forwards then read as far too fast and was held back while the other
    reversed, and the body backed up by 14-35 mm (0.1-0.27 m/s, no braking first) while it turned
    (a 16x16 contest maze under a Pi 4's share: 0.095 m/s, into the corridor's side wall, with a
    turn in place the only command). The wheel that must reverse still starts from rest (its
    hard push tells a weak motor early), and its overshoot leaves 5-14 mm.
    """
    bench = Bench(latency_periods=1)
    for _ in range(40):
        bench.step(v0, -0.3)
    for _ in range(stop_ticks):
        bench.step(0.0, 0.0, DriveMode.STOP)
    forward = backward = 0.0
    for _ in range(40):
        x0, y0, th0 = bench.robot.pose
        bench.step(0.0, -1.2, DriveMode.TURN)
        x1, y1, _ = bench.robot.pose
        along = math.cos(th0) * (x1 - x0) + math.sin(th0) * (y1 - y0)
        forward, backward = forward + max(along, 0.0), backward - min(along, 0.0)
    assert backward <= 0.06 * v0  # metres: 6 mm at 0.1 m/s, 16 mm at 0.27 m/s
    assert forward <= v0 * 0.1 + v0 * v0 / (2 * 0.6)  # the guard's stopping distance at v0
    assert math.degrees(bench.robot.theta_rad) < -60.0  # and it did turn
