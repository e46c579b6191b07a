"""Robot physics against closed-form differential-drive motion and wall contact.

The expected values are computed here from the model the module documents (deadband,
battery sag, first-order motor lag, arc kinematics), not from the module's own helpers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.sim.physics import PhysicsParams, RobotPhysics
from mazebot.sim.world import World


def make_world(segments: object = (), circles: object = ()) -> World:
    return World(
        name="test",
        segments=np.asarray(segments, dtype=np.float64).reshape(-1, 4),
        circles=np.asarray(circles, dtype=np.float64).reshape(-1, 3),
        start_pose=(0.0, 0.0, 0.0),
        bounds_m=(-5.0, -5.0, 5.0, 5.0),
    )


def make_robot(
    params: PhysicsParams | None = None,
    world: World | None = None,
    start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    seed: int = 0,
) -> RobotPhysics:
    return RobotPhysics(
        params if params is not None else PhysicsParams.ideal(),
        world if world is not None else make_world(),
        start_pose,
        np.random.default_rng(seed),
    )


def steady_speed_mps(p: PhysicsParams, throttle: float, mean_demand: float) -> float:
    """Wheel surface speed the documented model settles at (nominal wheel, gain 1)."""
    effective = (abs(throttle) - p.deadband) / (1.0 - p.deadband)
    return math.copysign(
        p.max_wheel_speed_mps * effective * (1.0 - p.battery_sag * mean_demand), throttle
    )


def lag_distance_m(speed_mps: float, t_s: float, tau_s: float) -> float:
    """∫ v(1 − e^(−t/τ)) dt from rest: the first-order lag response."""
    return speed_mps * (t_s - tau_s * (1.0 - math.exp(-t_s / tau_s)))


def clearance_m(x_m: float, y_m: float, world: World) -> float:
    """Independent point-to-wall/post surface distance, for no-penetration checks."""
    best = math.inf
    for x1, y1, x2, y2 in world.segments:
        dx, dy = x2 - x1, y2 - y1
        t = min(1.0, max(0.0, ((x_m - x1) * dx + (y_m - y1) * dy) / (dx * dx + dy * dy)))
        best = min(best, math.hypot(x_m - x1 - t * dx, y_m - y1 - t * dy))
    for cx, cy, r in world.circles:
        best = min(best, math.hypot(x_m - cx, y_m - cy) - r)
    return best


# -- free motion against closed forms ----------------------------------------------------


def test_equal_throttles_drive_the_first_order_lag_integral_in_a_straight_line() -> None:
    p = PhysicsParams.ideal()
    robot = make_robot(p)
    robot.set_throttle(0.5, 0.5)
    speed = steady_speed_mps(p, 0.5, mean_demand=0.5)
    t_s = 0.0
    for dt_s in (0.01, 0.04, 0.05, 0.2, 0.7, 1.0):
        robot.step(dt_s)
        t_s += dt_s
        expected = lag_distance_m(speed, t_s, p.motor_time_constant_s)
        assert robot.x_m == pytest.approx(expected, abs=1e-9)
        assert robot.y_m == 0.0
        assert robot.theta_rad == 0.0
    # After the transient the distance grows at v: x ≈ v·(t − τ).
    assert robot.x_m == pytest.approx(speed * (t_s - p.motor_time_constant_s), abs=1e-6)
    assert robot.wheel_speed_mps == pytest.approx((speed, speed), abs=1e-9)
    assert robot.body_velocity == pytest.approx((speed, 0.0), abs=1e-9)
    assert robot.time_s == pytest.approx(t_s)


def test_unequal_throttles_drive_a_circle_of_radius_l_half_sum_over_difference() -> None:
    p = PhysicsParams.ideal()
    robot = make_robot(p)
    robot.set_throttle(0.3, 0.6)
    v_l = steady_speed_mps(p, 0.3, mean_demand=0.45)
    v_r = steady_speed_mps(p, 0.6, mean_demand=0.45)
    radius_m = 0.5 * p.track_width_m * (v_r + v_l) / (v_r - v_l)
    # Both wheels share the lag, so their speed ratio (and the curvature) is constant
    # from the start: every pose lies on the circle centred left of the start.
    for _ in range(300):
        robot.step(0.01)
        x_m, y_m, theta_rad = robot.pose
        assert math.hypot(x_m, y_m - radius_m) == pytest.approx(radius_m, abs=1e-9)
        expected_heading = math.remainder(robot.odometer_m / radius_m, math.tau)
        assert math.remainder(theta_rad - expected_heading, math.tau) == pytest.approx(
            0.0, abs=1e-9
        )
    v_mps, omega_rad_s = robot.body_velocity
    assert v_mps / omega_rad_s == pytest.approx(radius_m, rel=1e-6)


def test_opposite_throttles_spin_in_place() -> None:
    p = PhysicsParams.ideal()
    robot = make_robot(p)
    robot.set_throttle(-0.5, 0.5)
    robot.step(0.5)
    wheel_m = lag_distance_m(steady_speed_mps(p, 0.5, mean_demand=0.5), 0.5, 0.08)
    assert robot.x_m == 0.0
    assert robot.y_m == 0.0
    assert robot.odometer_m == 0.0
    assert robot.theta_rad == pytest.approx(2.0 * wheel_m / p.track_width_m, abs=1e-9)
    left_m, right_m = robot.true_wheel_travel_m()
    assert (left_m, right_m) == pytest.approx((-wheel_m, wheel_m), abs=1e-12)


def test_throttle_inside_the_deadband_does_not_move_the_robot() -> None:
    p = PhysicsParams.ideal()
    robot = make_robot(p)
    robot.set_throttle(0.05, -0.07)
    robot.step(2.0)
    assert robot.pose == (0.0, 0.0, 0.0)
    assert robot.wheel_angle_rad == (0.0, 0.0)
    robot.set_throttle(0.1, 0.1)
    robot.step(1.0)
    assert robot.x_m > 0.0


@pytest.mark.parametrize(
    ("overrides", "turns_left"),
    [
        ({"gain_right": 0.97}, False),
        ({"gain_left": 0.97}, True),
        ({"wheel_diameter_right_scale": 1.004}, True),
        ({"wheel_diameter_left_scale": 1.004}, False),
    ],
)
def test_mismatched_sides_curve_a_straight_command_towards_the_slower_wheel(
    overrides: dict[str, float], turns_left: bool
) -> None:
    robot = make_robot(PhysicsParams.ideal(**overrides))
    robot.set_throttle(0.6, 0.6)
    robot.step(2.0)
    sign = 1.0 if turns_left else -1.0
    assert sign * robot.theta_rad > 0.01
    assert sign * robot.y_m > 0.0


def test_unequal_wheels_curve_the_path_while_the_encoders_see_equal_rotation() -> None:
    robot = make_robot(PhysicsParams.ideal(wheel_diameter_right_scale=1.004))
    robot.set_throttle(0.6, 0.6)
    robot.step(2.0)
    left_rad, right_rad = robot.wheel_angle_rad
    assert left_rad == right_rad
    assert robot.theta_rad > 0.0


def test_without_slip_wheel_angle_times_radius_is_the_distance_travelled() -> None:
    p = PhysicsParams.ideal()
    robot = make_robot(p)
    robot.set_throttle(0.8, 0.8)
    robot.step(1.5)
    radius_m = 0.5 * p.wheel_diameter_m
    left_rad, right_rad = robot.wheel_angle_rad
    assert left_rad * radius_m == pytest.approx(robot.x_m, abs=1e-12)
    assert right_rad * radius_m == pytest.approx(robot.x_m, abs=1e-12)
    assert robot.odometer_m == pytest.approx(robot.x_m, abs=1e-12)
    assert robot.true_wheel_travel_m() == pytest.approx((robot.x_m, robot.x_m), abs=1e-12)


def test_slip_moves_the_body_but_not_the_wheels() -> None:
    slipping = PhysicsParams.ideal(slip_std=0.05)
    exact = make_robot(PhysicsParams.ideal())
    robots = [make_robot(slipping, seed=3), make_robot(slipping, seed=3), exact]
    for robot in robots:
        robot.set_throttle(0.8, 0.8)
        robot.step(2.0)
    first, again, _ = robots
    # The encoders count the same rotation with or without slip ...
    assert first.wheel_angle_rad == exact.wheel_angle_rad
    # ... but the body went elsewhere, by a little, and reproducibly for one seed.
    assert first.pose != exact.pose
    assert first.x_m == pytest.approx(exact.x_m, rel=0.02)
    assert abs(first.theta_rad) < 0.1
    assert again.pose == first.pose


def test_coasting_decays_with_the_motor_lag_and_braking_faster() -> None:
    p = PhysicsParams.ideal()
    coast, brake = make_robot(p), make_robot(p)
    for robot, command in ((coast, None), (brake, 0.0)):
        robot.set_throttle(0.7, 0.7)
        robot.step(1.5)
        speed0_mps = robot.wheel_speed_mps[0]
        x0_m = robot.x_m
        robot.set_throttle(command, command)
        robot.step(0.08)
        tau_s = p.motor_time_constant_s if command is None else p.brake_time_constant_s
        assert robot.wheel_speed_mps[0] == pytest.approx(speed0_mps * math.exp(-0.08 / tau_s))
        assert robot.x_m - x0_m == pytest.approx(
            speed0_mps * tau_s * (1.0 - math.exp(-0.08 / tau_s)), abs=1e-9
        )
        robot.step(2.0)
    assert coast.x_m > brake.x_m


def test_sub_stepping_does_not_change_the_motion() -> None:
    params = PhysicsParams(slip_std=0.0)  # mismatched sides and wheels, no noise
    world = make_world(segments=[[0.5, -2.0, 0.5, 2.0]])
    coarse, fine = make_robot(params, world), make_robot(params, world)
    for throttle in ((0.9, 0.8), (0.9, 1.0), (-0.3, 0.2)):  # hits the wall, then backs off
        coarse.set_throttle(*throttle)
        fine.set_throttle(*throttle)
        for _ in range(10):
            coarse.step(0.1)
            for _ in range(10):
                fine.step(0.01)
        assert fine.pose == pytest.approx(coarse.pose, abs=1e-12)
        assert fine.wheel_angle_rad == pytest.approx(coarse.wheel_angle_rad, abs=1e-12)
    assert coarse.collisions == fine.collisions == 1


# -- walls and posts -----------------------------------------------------------------------


def test_driving_into_a_wall_stops_one_footprint_radius_from_it() -> None:
    p = PhysicsParams.ideal()
    world = make_world(segments=[[1.0, -1.0, 1.0, 1.0]])
    robot = make_robot(p, world)
    robot.set_throttle(1.0, 1.0)
    for _ in range(300):
        robot.step(0.01)
        assert 1.0 - robot.x_m >= p.footprint_radius_m - 1e-12
    gap_m = 1.0 - robot.x_m - p.footprint_radius_m
    assert 0.0 <= gap_m < 1e-3
    assert robot.collisions == 1
    assert robot.in_contact
    assert robot.body_velocity[0] == 0.0
    # The wheels keep turning against the wall: encoders count, the pose does not move.
    angle_before = robot.wheel_angle_rad
    x_before = robot.x_m
    robot.step(0.5)
    assert robot.x_m == x_before
    assert robot.wheel_angle_rad[0] > angle_before[0] + 1.0
    assert robot.collisions == 1


def test_each_contact_episode_counts_once() -> None:
    world = make_world(segments=[[1.0, -1.0, 1.0, 1.0]])
    robot = make_robot(PhysicsParams.ideal(), world)
    robot.set_throttle(0.6, 0.6)
    robot.step(4.0)
    assert (robot.collisions, robot.in_contact) == (1, True)
    robot.set_throttle(-0.6, -0.6)
    robot.step(1.0)
    assert (robot.collisions, robot.in_contact) == (1, False)
    robot.set_throttle(0.6, 0.6)
    robot.step(2.0)
    assert (robot.collisions, robot.in_contact) == (2, True)


def test_a_robot_touching_a_wall_can_turn_and_drive_away() -> None:
    world = make_world(segments=[[1.0, -1.0, 1.0, 1.0]])
    robot = make_robot(PhysicsParams.ideal(), world)
    robot.set_throttle(0.6, 0.6)
    robot.step(3.0)
    robot.set_throttle(-0.5, 0.5)
    robot.step(0.5)  # spin in place against the wall: the round body may turn
    assert robot.theta_rad > 1.0
    robot.set_throttle(0.6, 0.6)
    robot.step(1.0)
    assert robot.y_m > 0.1
    assert not robot.in_contact
    assert robot.collisions == 1


def test_driving_into_a_post_stops_at_the_sum_of_the_radii() -> None:
    p = PhysicsParams.ideal()
    world = make_world(circles=[[1.0, 0.0, 0.05]])
    robot = make_robot(p, world)
    robot.set_throttle(0.8, 0.8)
    robot.step(4.0)
    gap_m = math.hypot(1.0 - robot.x_m, robot.y_m) - 0.05 - p.footprint_radius_m
    assert 0.0 <= gap_m < 1e-3
    assert robot.collisions == 1


def test_a_noisy_robot_never_penetrates_the_walls_of_a_box() -> None:
    box = [[-0.5, -0.5, 0.5, -0.5], [0.5, -0.5, 0.5, 0.5], [0.5, 0.5, -0.5, 0.5]]
    box.append([-0.5, 0.5, -0.5, -0.5])
    world = make_world(segments=box, circles=[[0.2, 0.2, 0.03]])
    p = PhysicsParams(slip_std=0.03)
    robot = make_robot(p, world, start_pose=(-0.2, -0.2, 0.3), seed=11)
    commands = np.random.default_rng(5).uniform(-1.0, 1.0, size=(40, 2))
    for left, right in commands:
        robot.set_throttle(float(left), float(right))
        for _ in range(25):
            robot.step(0.02)
            assert clearance_m(robot.x_m, robot.y_m, world) >= p.footprint_radius_m - 1e-12
    assert robot.collisions >= 1


# -- contract --------------------------------------------------------------------------------


def test_invalid_commands_and_parameters_are_rejected_with_the_value() -> None:
    robot = make_robot()
    with pytest.raises(ValueError, match=r"left throttle .* got 1\.5"):
        robot.set_throttle(1.5, 0.0)
    with pytest.raises(ValueError, match="dt_s"):
        robot.step(-0.1)
    with pytest.raises(ValueError, match="rate_hz"):
        PhysicsParams(rate_hz=100.0)
    with pytest.raises(ValueError, match="deadband"):
        PhysicsParams(deadband=1.0)
    with pytest.raises(ValueError, match="footprint"):
        make_robot(world=make_world(segments=[[0.05, -1.0, 0.05, 1.0]]))


def test_scrubbing_tyres_lose_their_share_of_an_in_place_turn_and_none_of_a_straight_run() -> None:
    exact, scrub = make_robot(PhysicsParams.ideal()), make_robot(PhysicsParams.ideal(turn_slip=0.05))
    for robot in (exact, scrub):
        robot.set_throttle(-0.5, 0.5)
        robot.step(0.5)
    assert scrub.wheel_angle_rad == exact.wheel_angle_rad  # the encoders count the same
    assert scrub.theta_rad == pytest.approx(0.95 * exact.theta_rad, rel=1e-9)
    straight = make_robot(PhysicsParams.ideal(turn_slip=0.05))
    straight.set_throttle(0.5, 0.5)
    straight.step(0.5)
    assert straight.theta_rad == 0.0 and straight.x_m > 0.05


def test_backlash_counts_play_the_wheel_never_turned_after_a_reversal() -> None:
    play_rad = math.radians(3.0)
    p = PhysicsParams.ideal(backlash_rad=play_rad)
    robot, exact = make_robot(p), make_robot(PhysicsParams.ideal())
    for throttle in (0.5, -0.5):
        for r in (robot, exact):
            r.set_throttle(throttle, throttle)
            r.step(0.6)
            r.set_throttle(0.0, 0.0)
            r.step(1.0)
    # the same shaft rotations; the wheels lost the play once at the start (half) and once at the reversal
    assert robot.wheel_angle_rad == pytest.approx(exact.wheel_angle_rad, abs=1e-12)
    radius_m = 0.5 * p.wheel_diameter_m
    assert robot.x_m - exact.x_m == pytest.approx(-0.5 * play_rad * radius_m + play_rad * radius_m, abs=1e-9)
