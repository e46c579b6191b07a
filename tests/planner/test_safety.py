"""The safety layer: emergency stop on lidar returns in the swept path, control deadline, stale commands."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.planner.dwa import scan_points_robot
from mazebot.planner.safety import (
    CollisionGuard,
    CommandGate,
    ControlWatchdog,
    SafetyLayer,
    arc_distance_m,
    reframe_points,
)
from mazebot.planner.wheel_control import DriveMode, WheelController, WheelSpeedEstimator
from mazebot.sim.physics import PhysicsParams, RobotPhysics
from mazebot.sim.raycast import RayCaster
from mazebot.sim.world import World, rectangles_outline


def test_a_return_ahead_inside_the_guard_stops() -> None:
    guard = CollisionGuard(footprint_radius_m=0.09, margin_m=0.03, brake_decel_mps2=0.6, latency_s=0.1)
    v = 0.2
    reach = 0.09 + 0.03 + guard.stopping_distance_m(v)  # 0.09 + 0.03 + 0.02 + 0.0333
    inside = np.array([[reach - 0.01, 0.0]])
    outside = np.array([[reach + 0.01, 0.0]])
    verdict = guard.check(inside, v, 0.0)
    assert verdict.stop and "ahead" in verdict.reason and verdict.nearest_m == pytest.approx(reach - 0.01)
    assert not guard.check(outside, v, 0.0).stop
    # the guard reaches further the faster the robot goes
    assert guard.check(outside, 0.3, 0.0).stop


def test_returns_beside_or_behind_do_not_stop_forward_motion() -> None:
    guard = CollisionGuard()
    wall_beside = np.column_stack((np.linspace(0.0, 0.5, 51), np.full(51, 0.12)))  # a corridor wall 12 cm away
    assert not guard.check(wall_beside, 0.3, 0.0).stop
    behind = np.array([[-0.16, 0.0]])
    assert not guard.check(behind, 0.2, 0.0).stop
    assert guard.check(behind, -0.2, 0.0).stop  # but reversing into it does
    assert "behind" in guard.check(behind, -0.2, 0.0).reason


def test_turning_in_place_and_standing_are_always_allowed() -> None:
    guard = CollisionGuard()
    close = np.array([[0.16, 0.0], [0.0, 0.16], [-0.16, 0.0]])
    assert not guard.check(close, 0.0, 1.2).stop
    assert not guard.check(close, 0.0, 0.0).stop
    assert not guard.check(np.zeros((0, 2)), 0.3, 0.0).stop


def test_the_guard_follows_the_arc() -> None:
    guard = CollisionGuard()
    # a return to the front-left: hit by a left turn, missed by a right turn
    point = np.array([[0.13, 0.08]])
    assert guard.check(point, 0.25, 2.0).stop
    assert not guard.check(point, 0.25, -2.0).stop


def test_watchdog_stops_after_a_missed_deadline() -> None:
    watchdog = ControlWatchdog(deadline_s=0.1)
    assert not watchdog.tick(0.0).stop
    assert not watchdog.tick(0.05).stop
    assert not watchdog.overdue(0.14)
    assert watchdog.overdue(0.2)
    verdict = watchdog.tick(0.3)
    assert verdict.stop and "deadline" in verdict.reason
    assert watchdog.misses == 1
    assert not watchdog.tick(0.35).stop


def test_stale_commands_become_stops() -> None:
    gate: CommandGate[tuple[float, float]] = CommandGate(ttl_s=0.5)
    assert gate.get(0.0) is None
    gate.put((0.2, 0.1), 1.0)
    assert gate.get(1.4) == (0.2, 0.1)
    assert gate.get(1.51) is None
    gate.clear()
    assert gate.get(1.0) is None
    with pytest.raises(ValueError, match="ttl_s"):
        CommandGate(ttl_s=0.0)


def test_safety_layer_says_why_it_stopped() -> None:
    layer = SafetyLayer(command_ttl_ticks=3, scan_timeout_ticks=4)
    clear = np.array([[2.0, 0.0]])
    assert not layer.check(0.00, 0.2, 0.0, 0.0, clear, 0.0).stop
    assert "stale command" in layer.check(0.05, 0.2, 0.0, None, clear, 0.0).reason
    assert not layer.check(0.10, 0.2, 0.0, 0.1, clear, 0.0).stop  # a new command; the scan 2 ticks old
    assert not layer.check(0.15, 0.2, 0.0, 0.1, clear, 0.0).stop
    assert "lidar silent" in layer.check(0.20, 0.2, 0.0, 0.1, clear, 0.0).reason  # 4 ticks on one revolution
    assert not layer.check(0.20, 0.0, 1.0, 0.2, clear, 0.0).stop  # turning in place needs no scan
    assert "emergency stop" in layer.check(0.25, 0.2, 0.0, 0.25, np.array([[0.16, 0.0]]), 0.25).reason
    assert "deadline" in layer.check(0.5, 0.2, 0.0, 0.5, clear, 0.5).reason
    assert not layer.check(0.55, 0.2, 0.0, 0.5, clear, 0.55).stop
    assert not layer.check(0.60, 0.2, 0.0, 0.5, clear, 0.60).stop
    assert "stale command" in layer.check(0.65, 0.2, 0.0, 0.5, clear, 0.65).reason  # 3 ticks on one command
    assert layer.stops == 5 and layer.last.stop


def test_a_blocked_loop_ages_neither_the_command_nor_the_scan_but_misses_its_deadline() -> None:
    # the loop could not run for 0.4 s: the tick after it stops the wheels (the deadline:
    # they ran unsupervised), and the command and revolution waiting then are not stale
    layer = SafetyLayer(command_ttl_ticks=10, scan_timeout_ticks=20)
    clear = np.array([[2.0, 0.0]])
    assert not layer.check(1.00, 0.2, 0.0, 0.95, clear, 0.9).stop
    assert "deadline" in layer.check(1.40, 0.2, 0.0, 1.0, clear, 0.9).reason
    assert not layer.check(1.45, 0.2, 0.0, 1.0, clear, 1.3).stop  # 0.45 s old, one tick old
    # a planner that stopped while the loop runs is caught after 10 ticks, idle ones included
    layer.idle(1.50, 1.0, 1.3)
    for k in range(7):  # ticks 3 to 9 on the command first seen at 1.40 s
        assert not layer.check(1.55 + 0.05 * k, 0.2, 0.0, 1.0, clear, 1.3 + 0.05 * k).stop, k
    assert "stale command" in layer.check(1.90, 0.2, 0.0, 1.0, clear, 1.7).reason


def test_the_safety_layer_stops_a_runaway_planner_before_the_wall() -> None:
    """A broken planner commands full speed at a wall; the layer alone keeps the robot off it."""
    wall = World(
        "wall",
        rectangles_outline(np.array([[1.0, -1.0, 1.012, 1.0]])),
        np.zeros((0, 3)),
        (0.0, 0.0, 0.0),
        (-1.0, -1.0, 1.1, 1.0),
    )
    robot = RobotPhysics(PhysicsParams(), wall, wall.start_pose, np.random.default_rng(0))
    caster = RayCaster.for_world(wall)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    ctl = WheelController()
    est = WheelSpeedEstimator.for_wheel(840, 0.065)
    layer = SafetyLayer()
    dt, t, stopped_at = 0.05, 0.0, None
    while t < 8.0:
        ranges = caster.cast(np.array(robot.pose[:2]), angles + robot.theta_rad, 12.0)
        scan = scan_points_robot(angles, ranges)  # returns under 0.15 m are invalid, as on the A1
        left, right = robot.wheel_angle_rad
        measured = est.update(math.floor(left / math.tau * 840), math.floor(right / math.tau * 840), t)
        v, w, mode = 0.3, 0.0, DriveMode.DRIVE  # the runaway command, refreshed every tick
        if layer.check(t, v, w, t, scan, t).stop:
            v, w, mode = 0.0, 0.0, DriveMode.STOP
            stopped_at = stopped_at if stopped_at is not None else robot.x_m
        out = ctl.update(v, w, mode, measured, dt)
        robot.set_throttle(out.left_throttle, out.right_throttle)
        robot.step(dt)
        t += dt
    assert stopped_at is not None
    assert robot.collisions == 0
    assert 1.0 - robot.x_m >= 0.09  # stopped with the footprint clear of the wall face
    assert robot.x_m > 0.6  # after driving most of the way: it stops late, as it should


def test_reframe_points_moves_an_old_scan_with_the_robot() -> None:
    seen = np.array([[0.5, 0.0], [0.0, 0.3]])
    moved = reframe_points(seen, (1.0, 2.0, 0.0), (1.1, 2.0, math.pi / 2))
    # 10 cm closer to the first point, and turned left by 90 degrees
    assert moved == pytest.approx(np.array([[0.0, -0.4], [0.3, 0.1]]), abs=1e-12)
    assert reframe_points(seen, (0.0, 0.0, 1.0), (0.0, 0.0, 1.0)) == pytest.approx(seen)


def _sweep_reference(guard: CollisionGuard, pts: np.ndarray, v_mps: float, w_radps: float) -> tuple[float, float]:
    """Brute force: drive a unicycle at ``(v, w)`` over the guard's length in 0.05 mm steps, keep each
    return's nearest approach of the centre, and apply the rule (within the guard radius, and closer
    than now). Returns (nearest range of a return inside the guard or inf, the smallest margin by which
    any return's verdict was decided, so scenes at a hair from the line can be told apart)."""
    length = guard.stopping_distance_m(v_mps) + guard.margin_m
    n = max(2, math.ceil(length / 5e-5) + 1)
    t = np.linspace(0.0, length / abs(v_mps), n)
    dt = t[1] - t[0]
    theta = w_radps * t
    # exact integration of the heading, the position summed in small steps (midpoint headings)
    mid = w_radps * (t[:-1] + 0.5 * dt)
    x = np.concatenate(([0.0], np.cumsum(v_mps * np.cos(mid) * dt)))
    y = np.concatenate(([0.0], np.cumsum(v_mps * np.sin(mid) * dt)))
    assert theta.shape == x.shape
    d = np.min(np.hypot(pts[:, None, 0] - x[None, :], pts[:, None, 1] - y[None, :]), axis=1)
    ranges = np.hypot(pts[:, 0], pts[:, 1])
    limit = np.minimum(guard.radius_m, ranges - 1e-4)
    inside = d < limit
    closeness = float(np.min(np.abs(d - limit))) if len(pts) else math.inf
    return (float(ranges[inside].min()) if inside.any() else math.inf), closeness


def test_the_guard_stops_exactly_when_a_return_on_the_whole_sweep_is_inside() -> None:
    """Random arcs, both ways, any curvature, and random returns around the robot against a brute-force sweep."""
    guard = CollisionGuard(side_margin_m=0.01)
    rng = np.random.default_rng(7)
    stops = beside = 0
    for _ in range(600):
        v = float(rng.choice([-1.0, 1.0]) * rng.uniform(guard.min_speed_mps, 0.3))
        w = float(rng.choice([0.0, rng.uniform(-1.2, 1.2), rng.uniform(-30.0, 30.0) * abs(v)]))
        reach = guard.stopping_distance_m(v) + guard.margin_m + guard.radius_m
        n = int(rng.integers(1, 12))
        if rng.uniform() < 0.3:  # beside the robot, just outside the guard: what a tight arc sweeps into
            r = rng.uniform(guard.radius_m, guard.radius_m + 0.03, n)
            a = rng.choice([-1.0, 1.0], n) * rng.uniform(math.radians(60.0), math.radians(120.0), n)
        else:
            r = rng.uniform(0.0, 1.5 * reach, n)
            a = rng.uniform(-math.pi, math.pi, n)
        pts = np.column_stack((r * np.cos(a), r * np.sin(a)))
        want, closeness = _sweep_reference(guard, pts, v, w)
        if closeness < 2e-6:  # within the brute force's own error of the line: either verdict is right
            continue
        verdict = guard.check(pts, v, w)
        assert verdict.stop == math.isfinite(want), (v, w, pts)
        if verdict.stop:
            stops += 1
            assert verdict.nearest_m == pytest.approx(want)
            hit = pts[np.argmin(np.abs(np.hypot(pts[:, 0], pts[:, 1]) - want))]
            beside += hit[0] * v <= 0.0  # not on the side the robot moves towards: the old guard's blind side
    assert 100 < stops < 500  # both verdicts were exercised
    assert beside > 5


def test_the_arc_distance_is_the_exact_distance_to_the_centre_s_path() -> None:
    rng = np.random.default_rng(3)
    for _ in range(100):
        direction = float(rng.choice([-1.0, 1.0]))
        curvature = float(rng.choice([0.0, 1e-4, rng.uniform(-40.0, 40.0), rng.uniform(-400.0, 400.0)]))
        length = float(rng.uniform(0.005, 0.3))
        pts = rng.uniform(-0.4, 0.4, (20, 2))
        s = np.linspace(0.0, length, 20001)
        if curvature == 0.0:
            px, py = direction * s, 0.0 * s
        else:
            px, py = direction * np.sin(curvature * s) / curvature, (1.0 - np.cos(curvature * s)) / curvature
        want = np.min(np.hypot(pts[:, None, 0] - px[None, :], pts[:, None, 1] - py[None, :]), axis=1)
        got = arc_distance_m(pts, length, direction, curvature)
        spacing = length / 20000
        straightened = abs(curvature) * length**2 / 2 if abs(curvature) < 1e-3 else 0.0  # taken as straight
        assert np.all(got <= want + 1e-12 + straightened)  # never farther than a point of the path
        assert np.all(got >= want - spacing - straightened)  # and no nearer than the samples allow


def test_a_tight_reverse_arc_does_not_back_the_robot_s_side_into_a_wall_end() -> None:
    """Reversing while turning clockwise carries the body back and to the left: the end of a wall
    beside it, level with the axle, is swept into although no return of it lies behind."""
    guard = CollisionGuard(side_margin_m=0.01)
    wall_end = np.column_stack((np.linspace(0.0, 0.3, 61), np.full(61, 0.105)))  # beside and ahead, 1.5 cm off
    v, w = -0.05, -1.2
    verdict = guard.check(wall_end, v, w)
    assert verdict.stop and "on the left" in verdict.reason and "in reverse" in verdict.reason
    assert not guard.check(wall_end, v, 1.2).stop  # the other way round it leaves the wall behind
    assert not guard.check(wall_end, v, 0.0).stop  # and straight back it slides along it


def test_the_collision_on_a_contest_maze_reversing_while_turning_clockwise_is_stopped() -> None:
    """The contact traced on alljapan-015 under a Pi 4's share (fifth session): heading −20°, 4 cm north
    of the corridor's centre line, backing at 0.1 m/s while turning clockwise; the north wall 0.158 m from
    the centre line. The guard must stop the motion before the footprint reaches the wall."""
    guard = CollisionGuard(side_margin_m=0.01)
    heading = math.radians(-20.0)
    wall_y = 0.158 - 0.045  # the north wall, world frame, from the robot centre
    xs = np.linspace(-0.4, 0.4, 161)
    c, s = math.cos(heading), math.sin(heading)
    wall_robot = np.column_stack((c * xs + s * wall_y, -s * xs + c * wall_y))
    verdict = guard.check(wall_robot, -0.1, -1.2)
    assert verdict.stop
    # the sweep reaches the wall; going forwards on the same turn takes the body away from it
    assert not guard.check(wall_robot, 0.1, -1.2).stop


def test_a_forward_arc_that_sweeps_the_body_into_a_side_wall_stops() -> None:
    """A sharp left turn forwards carries the body left: a wall beside, behind the axle, is swept."""
    guard = CollisionGuard(side_margin_m=0.01)
    wall_behind_left = np.column_stack((np.linspace(-0.3, 0.0, 61), np.full(61, 0.105)))
    assert guard.check(wall_behind_left, 0.05, 1.2).stop
    assert not guard.check(wall_behind_left, 0.05, -1.2).stop
    assert not guard.check(wall_behind_left, 0.05, 0.0).stop


def test_straight_reverse_stops_at_a_wall_behind_and_not_beside() -> None:
    guard = CollisionGuard(side_margin_m=0.01)
    v = -0.2
    reach = guard.radius_m + guard.margin_m + guard.stopping_distance_m(v)
    behind = np.column_stack((np.full(41, -(reach - 0.01)), np.linspace(-0.2, 0.2, 41)))
    assert guard.check(behind, v, 0.0).stop
    assert "behind" in guard.check(behind, v, 0.0).reason
    assert not guard.check(behind - np.array([0.02, 0.0]), v, 0.0).stop
    assert not guard.check(behind, -v, 0.0).stop
    beside = np.column_stack((np.linspace(-0.4, 0.4, 81), np.full(81, guard.radius_m + 0.005)))
    assert not guard.check(beside, v, 0.0).stop


def test_a_robot_inside_the_guard_may_move_away_and_turn_but_not_come_closer() -> None:
    """A wall 5 mm inside the guard ahead: backing off on any arc and turning in place are allowed,
    driving on is not; a wall inside the guard beside: turning in place is allowed."""
    guard = CollisionGuard(side_margin_m=0.01)
    close = guard.radius_m - 0.005
    wall_ahead = np.column_stack((np.full(81, close), np.linspace(-0.4, 0.4, 81)))
    for w in (-1.2, -0.5, 0.0, 0.5, 1.2):
        assert not guard.check(wall_ahead, -0.06, w).stop, w
        assert guard.check(wall_ahead, 0.06, w).stop, w
    assert not guard.check(wall_ahead, 0.0, 1.2).stop
    wall_left = np.column_stack((np.linspace(-0.4, 0.4, 81), np.full(81, close)))
    assert not guard.check(wall_left, 0.0, -1.2).stop
    assert guard.check(wall_left, 0.06, 1.2).stop  # a left arc into it
    assert guard.check(wall_left, -0.06, -1.2).stop  # a reverse arc into it


def _leg_returns(lidar_xy: tuple[float, float], leg_xy: tuple[float, float], min_range_m: float = 0.15) -> np.ndarray:
    """Robot-frame returns (heading 0) of a 2 cm leg's near face: none inside the minimum range."""
    dx, dy = leg_xy[0] - lidar_xy[0], leg_xy[1] - lidar_xy[1]
    d = math.hypot(dx, dy)
    if d - 0.01 < min_range_m:
        return np.zeros((0, 2))
    face = (d - 0.01) / d
    return np.array([[dx * face, dy * face]])


def test_the_blind_zone_keeps_a_leg_the_robot_came_too_close_to_see_and_forgets_it_once_it_could_see_it() -> None:
    from mazebot.planner.safety import BlindZoneMemory

    memory = BlindZoneMemory(min_range_m=0.15)
    leg = (0.3, 0.0)
    for x in (0.0, 0.05, 0.1):  # driving at it: seen at 0.29, 0.24, 0.19 m
        memory.add_scan(_leg_returns((x, 0.0), leg), (x, 0.0, 0.0))
    # within a revolution's travel of the blind zone a return is kept, though the scan shows it too
    np.testing.assert_allclose(memory.points_robot((0.1, 0.0, 0.0)), [[0.19, 0.0]], atol=1e-9)
    memory.add_scan(_leg_returns((0.18, 0.0), leg), (0.18, 0.0, 0.0))  # 0.11 m: the scan shows nothing
    for _ in range(20):  # standing there: the same return is kept once
        memory.add_scan(np.zeros((0, 2)), (0.18, 0.0, 0.0))
    ahead = memory.points_robot((0.18, 0.0, 0.0))
    np.testing.assert_allclose(ahead, [[0.11, 0.0]], atol=1e-9)
    # turned away and back, still there, in the frame of the turned robot
    memory.add_scan(np.zeros((0, 2)), (0.18, 0.0, math.pi / 2))
    np.testing.assert_allclose(memory.points_robot((0.18, 0.0, math.pi / 2)), [[0.0, -0.11]], atol=1e-9)
    # the guard, given it, stops a drive at the leg the scan no longer shows
    guard = CollisionGuard()
    assert not guard.check(np.zeros((0, 2)), v_mps=0.2, w_radps=0.0).stop
    assert guard.check(memory.points_robot((0.18, 0.0, 0.0)), v_mps=0.2, w_radps=0.0).stop
    # backed off to where a revolution sees that place again: the memory lets go
    memory.add_scan(np.zeros((0, 2)), (0.0, 0.0, 0.0))  # 0.29 m away and nothing there: the leg was moved
    assert len(memory) == 0


def test_the_blind_zone_forgets_after_so_many_revolutions_the_odometry_drifts_over() -> None:
    from mazebot.planner.safety import BlindZoneMemory

    memory = BlindZoneMemory(min_range_m=0.15, max_age_revolutions=10)
    memory.add_scan(_leg_returns((0.0, 0.0), (0.2, 0.0)), (0.0, 0.0, 0.0))  # seen at 0.19 m
    memory.add_scan(np.zeros((0, 2)), (0.08, 0.0, 0.0))  # 0.11 m: kept
    for k in range(8):  # turning beside it: still kept
        memory.add_scan(np.zeros((0, 2)), (0.08, 0.0, 0.5 * (k + 1)))
    assert len(memory) == 1
    memory.add_scan(np.zeros((0, 2)), (0.08, 0.0, 0.0))  # the tenth revolution since it was seen
    assert len(memory) == 0


def test_the_blind_zone_does_not_age_while_the_robot_stands() -> None:
    """A leg the robot stood beside for many revolutions is still known when it turns towards it."""
    from mazebot.planner.safety import BlindZoneMemory

    memory = BlindZoneMemory(min_range_m=0.15, max_age_revolutions=10)
    memory.add_scan(_leg_returns((0.0, 0.0), (0.2, 0.0)), (0.0, 0.0, 0.0))  # seen at 0.19 m
    for _ in range(50):  # standing 0.11 m from it, long past the age limit in revolutions
        memory.add_scan(np.zeros((0, 2)), (0.08, 0.0, 0.0))
    for k in range(8):  # then turning on the spot: the motion the odometry drifts over counts again
        memory.add_scan(np.zeros((0, 2)), (0.08, 0.0, 0.1 * (k + 1)))
    assert len(memory) == 1
    assert CollisionGuard().check(memory.points_robot((0.08, 0.0, 0.0)), 0.2, 0.0).stop
    memory.add_scan(np.zeros((0, 2)), (0.08, 0.0, 0.0))  # the tenth revolution of motion since it was seen
    assert len(memory) == 0


def test_the_blind_zone_refuses_negative_ranges() -> None:
    from mazebot.planner.safety import BlindZoneMemory

    with pytest.raises(ValueError, match="non-negative"):
        BlindZoneMemory(min_range_m=-0.15)


def test_a_turning_robot_s_returns_are_placed_where_each_was_seen() -> None:
    """A robot turning at -1.5 rad/s while a revolution goes round (0.18 s: 15°): the end of a
    board 0.16 m away 30° to the right, seen early in the revolution, is 4 cm off where it is when placed
    as if seen from the revolution's end, and where it is when each return is placed with
    the odometry pose of its own time."""
    from mazebot.planner.safety import deskewed_points_robot
    from mazebot.slam.ekf import OdometryHistory

    w, period = -1.5, 0.18
    times = np.linspace(0.0, period, 360)
    history = OdometryHistory(3.0)
    for t in [*times[::10].tolist(), period]:
        history.append(t, 0.2, 0.1, 0.3 + w * t)  # turning in place at (0.2, 0.1)
    end_heading = 0.3 + w * period
    # the board's end, in the robot frame at the revolution's end: 0.16 m, 30° right
    target_end = np.array([0.16 * math.cos(math.radians(-30)), 0.16 * math.sin(math.radians(-30))])
    world = np.array([0.2, 0.1]) + np.array([[math.cos(end_heading), -math.sin(end_heading)],
                                             [math.sin(end_heading), math.cos(end_heading)]]) @ target_end
    k = 20  # seen by the 21st sample, early in the revolution
    heading_then = 0.3 + w * times[k]
    bearing = math.atan2(world[1] - 0.1, world[0] - 0.2) - heading_then
    angle = np.full(360, bearing)
    rng = np.zeros(360)
    rng[k] = 0.16
    valid = rng > 0
    placed = deskewed_points_robot(angle, rng, valid, times, history, 0.15, 12.0)
    np.testing.assert_allclose(placed, [target_end], atol=1e-6)
    naive = deskewed_points_robot(angle, rng, valid, times, None, 0.15, 12.0)
    assert np.hypot(*(naive[0] - target_end)) > 0.035
    # the guard, driving straight on: stops on the placed return, would not on the naive one
    guard = CollisionGuard()
    assert guard.check(placed, 0.27, 0.0).stop and not guard.check(naive, 0.27, 0.0).stop


def test_the_memory_s_snapshot_holds_the_last_revolution_s_near_returns_too() -> None:
    """What the control loop's guard is given: every remembered near return, odometry frame,
    read-only; moved into the robot frame of now beside the scan's own points."""
    from mazebot.planner.safety import BlindZoneMemory, with_remembered

    memory = BlindZoneMemory(min_range_m=0.15)
    memory.add_scan(np.array([[0.2, 0.0], [1.0, 0.0]]), (0.0, 0.0, 0.0))  # one near return, one far
    snap = memory.snapshot()
    np.testing.assert_allclose(snap, [[0.2, 0.0]])
    assert len(memory) == 0  # the planner's own view: the scan shows it
    with pytest.raises(ValueError):
        snap[0, 0] = 1.0
    scan = np.array([[0.5, 0.5]])
    np.testing.assert_allclose(with_remembered(scan, snap, (0.1, 0.0, math.pi / 2)), [[0.5, 0.5], [0.0, -0.1]],
                               atol=1e-12)
    assert with_remembered(scan, None, (0.0, 0.0, 0.0)) is scan
    assert with_remembered(scan, snap, None) is scan


def test_a_thin_post_the_latest_revolution_missed_is_kept_one_revolution_more() -> None:
    """A lone post seen at 0.24 m, then in no sample of the next revolution (a dropout, the
    revolution's seam): the planner and the guard still have it, for that one revolution."""
    from mazebot.planner.safety import BlindZoneMemory

    memory = BlindZoneMemory(min_range_m=0.15)
    memory.add_scan(np.array([[0.24, 0.0], [1.5, 0.0]]), (0.0, 0.0, 0.0))
    assert len(memory) == 0  # the scan shows it
    memory.add_scan(np.array([[1.48, 0.0]]), (0.02, 0.0, 0.0))  # 0.22 m ahead now, missed
    np.testing.assert_allclose(memory.points_robot((0.02, 0.0, 0.0)), [[0.22, 0.0]], atol=1e-12)
    assert CollisionGuard().check(memory.points_robot((0.02, 0.0, 0.0)), 0.3, 0.0).stop
    memory.add_scan(np.array([[1.48, 0.0]]), (0.02, 0.0, 0.0))  # missed twice from where it could be seen: gone
    assert len(memory) == 0


def test_the_control_loops_guard_keeps_a_side_margin_beside_the_commanded_arc() -> None:
    """A wall 5 mm outside the footprint beside the arc stops the control loop's guard.

    The cheap robot (20-line encoders, 5 % slip in turns) drives up to ~9 mm beside the
    arc it is told over a stopping distance (97.5 % of them, 8x8 hand-built seed 10): a
    wall the commanded arc passes 0.5-1 cm outside the footprint was touched twice.
    """
    from mazebot.config import Config
    from mazebot.tasks.control_task import MotorControl

    config = Config()
    guard = MotorControl.from_config(config).safety.guard
    assert guard.side_margin_m == config.control.side_margin_m >= 0.009
    footprint = config.robot.footprint_radius_m
    v, w = 0.16, -0.58  # the command of the seed-10 contact: a right turn away from a wall on the left
    radius = v / abs(w)  # the arc's centre lies at (0, -radius)
    s = 0.6 * guard.stopping_distance_m(v)
    phi = s / radius
    on_arc = np.array([radius * math.sin(phi), -radius + radius * math.cos(phi)])
    outward = np.array([math.sin(phi), math.cos(phi)])  # away from the centre: the wall on the left
    wall = on_arc + (footprint + 0.005) * outward
    assert guard.check(wall[None, :], v, w).stop
    bare = CollisionGuard(footprint_radius_m=footprint, margin_m=guard.margin_m,
                          brake_decel_mps2=guard.brake_decel_mps2, latency_s=guard.latency_s)
    assert not bare.check(wall[None, :], v, w).stop  # the footprint alone let it run


def _fix(memory: object, end_s: float | None, before: tuple[float, float, float], odom: tuple[float, float, float],
         slam_pose: tuple[float, float, float], vouched: bool = True) -> tuple[float, float, float]:
    """SLAM's fix of one revolution, as the SLAM task publishes it: ``map_from_odom`` from ``before`` to
    the correction that takes the odometry's ``odom`` to SLAM's ``slam_pose``; returns that correction."""
    from mazebot.geometry import compose, inverse

    after = tuple(float(v) for v in compose(slam_pose, inverse(odom)))
    memory.fix(end_s, before, after, vouched)  # type: ignore[attr-defined]
    return after  # type: ignore[return-value]


def test_the_blind_zone_places_each_revolution_where_slam_has_it_so_a_slipping_tyre_smears_nothing() -> None:
    """The fault suite's slipping tyre: the robot stands between two posts while the odometry turns
    3° a revolution (the tyre spins, the robot does not). Placed by the odometry, the posts' returns
    smear round the robot and close the way between them; placed by SLAM's pose of each
    revolution (the scan matches: the robot has not moved), they stay where the posts are."""
    from mazebot.geometry import inverse, transform_points
    from mazebot.planner.safety import BlindZoneMemory

    posts = np.array([[0.12, 0.13], [0.12, -0.13]])  # 0.177 m away, 0.26 m apart: the way ahead is open
    guard = CollisionGuard()
    assert not guard.check(posts, 0.2, 0.0).stop

    def run(with_fixes: bool) -> tuple[BlindZoneMemory, tuple[float, float, float]]:
        memory = BlindZoneMemory(min_range_m=0.15)
        correction = (0.0, 0.0, 0.0)
        odom = (0.0, 0.0, 0.0)
        for k in range(20):
            odom = (0.0, 0.0, math.radians(3.0 * k))
            memory.add_scan(posts, odom, float(k))  # the robot still: the posts where they were
            if with_fixes:  # a slip: held back, but matched, so SLAM vouches for the pose
                correction = _fix(memory, float(k), correction, odom, (0.0, 0.0, 0.0))
        return memory, odom

    memory, odom = run(with_fixes=True)
    seen = memory.points_robot(odom)
    assert len(seen) > 0
    assert np.hypot(*(seen[:, None, :] - posts[None, :, :]).transpose(2, 0, 1)).min(axis=1).max() < 1e-6
    snap = transform_points(inverse(odom), memory.snapshot())
    assert np.hypot(*(snap[:, None, :] - posts[None, :, :]).transpose(2, 0, 1)).min(axis=1).max() < 1e-6
    assert not guard.check(np.concatenate((seen, snap)), 0.2, 0.0).stop
    # without SLAM's fixes (the odometry frame alone) copies lie in the way, within the body's half width
    copies = run(with_fixes=False)[0].points_robot(odom)
    ahead = copies[copies[:, 0] > 0]
    assert np.abs(ahead[:, 1]).min() < guard.footprint_radius_m


def test_the_blind_zone_drops_what_slam_did_not_place_and_keeps_what_it_did() -> None:
    from mazebot.planner.safety import BlindZoneMemory

    memory = BlindZoneMemory(min_range_m=0.15)
    leg, other, third = np.array([[0.2, 0.0]]), np.array([[0.0, 0.2]]), np.array([[0.0, -0.2]])
    c0 = (0.0, 0.0, 0.0)
    memory.add_scan(leg, (0.0, 0.0, 0.0), 1.0)
    c1 = _fix(memory, 1.0, c0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # placed
    memory.add_scan(other, (0.01, 0.0, 0.0), 2.0)  # SLAM leaves this revolution out
    memory.add_scan(third, (0.02, 0.0, 0.0), 3.0)
    assert len(memory) == 2  # the leg (placed), revolution 2's returns (the last one's own are the scan's)
    # revolution 3: held back, its match refused (its pose the distrusted odometry's); SLAM
    # corrects the odometry by 1 cm along x meanwhile
    c3 = _fix(memory, 3.0, c1, (0.02, 0.0, 0.0), (0.03, 0.0, 0.0), vouched=False)
    np.testing.assert_allclose(memory.snapshot(), [[0.19, 0.0]], atol=1e-12)  # only the leg, kept in the map
    # found again after being lost: what is placed keeps its place in the map, the rest goes
    memory.add_scan(other, (0.02, 0.0, 0.0), 4.0)
    _fix(memory, None, c3, (0.02, 0.0, 0.0), (0.0, 0.0, 0.0))
    np.testing.assert_allclose(memory.snapshot(), [[0.22, 0.0]], atol=1e-12)  # the map's 0.2 m: -0.02 + 0.22


def test_a_leg_slam_placed_is_kept_through_any_motion_beside_it_until_a_revolution_could_see_it() -> None:
    """A robot turning on the spot 0.12 m from a 20 mm leg for 60 revolutions (more than the 40 of
    motion the odometry's returns are kept for), its tyres slipping 5 % of each turn, SLAM placing
    every revolution: the leg is still where it is, and a drive at it is stopped. What only the
    odometry placed is gone after those revolutions; the leg goes once a revolution could see it."""
    from mazebot.planner.safety import BlindZoneMemory

    leg = (0.2, 0.0)

    def turn_beside_the_leg(with_fixes: bool) -> tuple[BlindZoneMemory, tuple[float, float, float]]:
        memory = BlindZoneMemory(min_range_m=0.15)
        correction = (0.0, 0.0, 0.0)
        memory.add_scan(_leg_returns((0.0, 0.0), leg), (0.0, 0.0, 0.0), 0.0)  # seen at 0.19 m
        if with_fixes:
            correction = _fix(memory, 0.0, correction, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        odom = (0.08, 0.0, 0.0)
        for k in range(61):  # driven up to 0.12 m from it, then turning: no revolution shows it
            true_heading = 0.1 * k
            odom = (0.08, 0.0, 1.05 * true_heading)  # the odometry turns 5 % more than the robot
            memory.add_scan(np.zeros((0, 2)), odom, float(k + 1))
            if with_fixes:
                correction = _fix(memory, float(k + 1), correction, odom, (0.08, 0.0, true_heading))
        return memory, odom

    memory, odom = turn_beside_the_leg(with_fixes=True)
    assert memory.revolutions > memory.max_age_revolutions + 1
    true_heading = 6.0
    c, s = math.cos(true_heading), math.sin(true_heading)
    leg_robot = [0.11 * c, -0.11 * s]  # its near face, 0.11 m ahead of the lidar, in the turned robot's frame
    np.testing.assert_allclose(memory.points_robot(odom), [leg_robot], atol=1e-9)
    facing = (odom[0], odom[1], odom[2] - true_heading)  # turned back to face it (the same correction)
    assert CollisionGuard().check(memory.points_robot(facing), 0.2, 0.0).stop
    assert len(turn_beside_the_leg(with_fixes=False)[0]) == 0  # the odometry's copy: aged out
    memory.add_scan(np.zeros((0, 2)), (-0.2, 0.0, odom[2]), 62.0)  # backed off: this revolution could see it
    assert len(memory) == 0


def test_a_robot_set_down_in_a_revolution_s_last_samples_does_not_keep_them_inside_its_body() -> None:
    """The robot is picked up and set down 0.12 m ahead in the last milliseconds of a revolution. SLAM
    matches that revolution (most of it was seen before) at the old pose, so the samples seen from the
    new place, a wall 0.17 m ahead of it, are placed 0.17 m ahead of the old one. Found again, the
    robot's body covers them: 0.05 m ahead, where no revolution can show the lidar past them. The next
    revolution drops them; a leg beside the robot, seen before the kidnap, is kept."""
    from mazebot.planner.safety import BlindZoneMemory

    def kidnapped(body_radius_m: float) -> BlindZoneMemory:
        memory = BlindZoneMemory(min_range_m=0.15, body_radius_m=body_radius_m)
        # revolution 1, at odometry (0, 0, 0): the leg at (0.12, 0.19) of the map, then, set down at
        # (0.12, 0, 0), the wall 0.17 m ahead of the new place, placed from where the odometry is
        memory.add_scan(np.array([[0.12, 0.19], [0.17, 0.0]]), (0.0, 0.0, 0.0), 1.0)
        correction = _fix(memory, 1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # SLAM vouches
        _fix(memory, None, correction, (0.0, 0.0, 0.0), (0.12, 0.0, 0.0))  # found again, 0.12 m ahead
        return memory

    at_rest = (0.0, 0.0, 0.0)  # the odometry's pose, so its frame is the robot's
    memory = kidnapped(body_radius_m=0.09)
    ahead = memory.snapshot()  # what the control loop's guard reads
    assert np.hypot(ahead[:, 0], ahead[:, 1]).min() < 0.06  # inside the body, as SLAM placed them
    creep = CollisionGuard()
    assert creep.check(ahead, 0.05, 0.0).stop
    # the next revolution, at rest: the wall 0.17 m ahead, where it is; the memory lets go of its copy
    memory.add_scan(np.array([[0.17, 0.0]]), at_rest, 2.0)
    seen = memory.snapshot()
    assert np.hypot(seen[:, 0], seen[:, 1]).min() > 0.16
    np.testing.assert_allclose(memory.points_robot(at_rest), [[0.0, 0.19]], atol=1e-9)  # the leg stays
    assert not creep.check(seen, 0.05, 0.0).stop  # creeping ahead: the wall is beyond the stopping distance
    # without a body the copy stays for as long as the robot stands there
    memory = kidnapped(body_radius_m=0.0)
    memory.add_scan(np.array([[0.17, 0.0]]), at_rest, 2.0)
    assert creep.check(memory.snapshot(), 0.05, 0.0).stop


def test_a_return_the_body_touches_is_kept() -> None:
    """A wall the robot stands against, its place a few millimetres off (SLAM's pose): not dropped."""
    from mazebot.planner.safety import BlindZoneMemory

    memory = BlindZoneMemory(min_range_m=0.15, body_radius_m=0.09)
    memory.add_scan(np.array([[0.16, 0.0]]), (0.0, 0.0, 0.0), 1.0)
    memory.add_scan(np.zeros((0, 2)), (0.075, 0.0, 0.0), 2.0)  # driven on: 0.085 m from it
    np.testing.assert_allclose(memory.points_robot((0.075, 0.0, 0.0)), [[0.085, 0.0]], atol=1e-9)
    assert CollisionGuard().check(memory.points_robot((0.075, 0.0, 0.0)), 0.05, 0.0).stop
