"""The Dynamic Window Approach and the local planner around it.

The central property is checked on random scenes with exact geometry, independently of
the planner's own k-d tree: whatever (v, w) the DWA picks, driving that arc for the
latency and then braking along it never brings the robot's centre within the footprint
radius of any obstacle point.
"""

from __future__ import annotations

import math
from collections.abc import Generator

import numpy as np
import pytest

from mazebot.planner.dwa import (
    DynamicWindowPlanner,
    LocalCostmap,
    LocalPlanner,
    LocalStatus,
    PathTrack,
    map_points_robot,
    scan_points_robot,
)
from mazebot.planner.wheel_control import DriveMode
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raster import true_occupancy
from mazebot.sim.raycast import RayCaster, distance_to_obstacles
from mazebot.sim.world import world_from_layout

FOOTPRINT = 0.09


def arc_points(v: float, w: float, length_m: float, step_m: float = 0.002) -> np.ndarray:
    """Robot-frame points (dense, exact) along the path of constant (v, w) for ``length_m`` of travel."""
    t = np.linspace(0.0, length_m / abs(v), max(2, math.ceil(length_m / step_m) + 1))
    if abs(w) < 1e-9:
        return np.column_stack((v * t, np.zeros_like(t)))
    return np.column_stack((v / w * np.sin(w * t), v / w * (1.0 - np.cos(w * t))))


def min_distance(points: np.ndarray, obstacles: np.ndarray) -> float:
    if obstacles.shape[0] == 0:
        return math.inf
    d = np.hypot(points[:, None, 0] - obstacles[None, :, 0], points[:, None, 1] - obstacles[None, :, 1])
    return float(d.min())


def random_scene(rng: np.random.Generator) -> np.ndarray:
    """Obstacle points around the origin: wall pieces and posts, none closer than 0.1 m to it."""
    pts = []
    for _ in range(rng.integers(1, 6)):  # straight walls, densely sampled like a lidar sees them
        a = rng.uniform(-0.8, 0.8, 2)
        angle = rng.uniform(0, math.pi)
        length = rng.uniform(0.05, 0.8)
        t = np.arange(0.0, length, 0.01)
        pts.append(np.column_stack((a[0] + t * math.cos(angle), a[1] + t * math.sin(angle))))
    for _ in range(rng.integers(0, 8)):  # isolated points (posts, noise)
        pts.append(rng.uniform(-0.6, 0.6, (1, 2)))
    obstacles = np.concatenate(pts)
    return obstacles[np.hypot(obstacles[:, 0], obstacles[:, 1]) >= 0.1]


def test_the_chosen_velocity_never_leads_into_an_obstacle() -> None:
    rng = np.random.default_rng(2024)
    dwa = DynamicWindowPlanner()
    chosen_moving = 0
    for _ in range(400):
        obstacles = random_scene(rng)
        v0 = float(rng.uniform(0.0, dwa.max_speed_mps))
        w0 = float(rng.uniform(-dwa.max_yaw_rate_radps, dwa.max_yaw_rate_radps))
        heading = rng.uniform(-math.pi, math.pi)
        path = PathTrack([(0.0, 0.0), (0.6 * math.cos(heading), 0.6 * math.sin(heading)), tuple(rng.uniform(-1, 1, 2))])
        costmap = LocalCostmap(obstacles, footprint_radius_m=FOOTPRINT)
        choice = dwa.plan((0.0, 0.0, 0.0), (v0, w0), costmap, path)
        # inside the dynamic window and the limits
        assert 0.0 <= choice.v_mps <= dwa.max_speed_mps + 1e-12
        assert abs(choice.w_radps) <= dwa.max_yaw_rate_radps + 1e-12
        if choice.blocked:
            assert (choice.v_mps, choice.w_radps) == (0.0, 0.0)
            continue
        assert choice.v_mps >= v0 - dwa.brake_decel_mps2 * dwa.window_s - 1e-9
        assert choice.v_mps <= v0 + dwa.max_accel_mps2 * dwa.window_s + 1e-9
        assert abs(choice.w_radps - w0) <= dwa.max_yaw_accel_radps2 * dwa.window_s + 1e-9
        if choice.v_mps > 1e-6:
            chosen_moving += 1
            stop = choice.v_mps * dwa.latency_s + choice.v_mps**2 / (2 * dwa.brake_decel_mps2)
            swept = arc_points(choice.v_mps, choice.w_radps, stop)
            assert min_distance(swept, obstacles) >= FOOTPRINT
    assert chosen_moving > 150  # the property was exercised, not dodged by standing still


def test_every_admissible_rollout_is_collision_free_for_its_stopping_distance() -> None:
    rng = np.random.default_rng(7)
    dwa = DynamicWindowPlanner()
    for _ in range(60):
        obstacles = random_scene(rng)
        costmap = LocalCostmap(obstacles, footprint_radius_m=FOOTPRINT)
        v0 = float(rng.uniform(0.0, 0.3))
        choice = dwa.plan((0.0, 0.0, 0.0), (v0, 0.0), costmap, PathTrack([(0.0, 0.0), (1.0, 0.0)]))
        r = choice.rollouts
        for v, w, ok in zip(r.v_mps, r.w_radps, r.admissible, strict=True):
            if ok and v > 1e-6:
                stop = v * dwa.latency_s + v * v / (2 * dwa.brake_decel_mps2)
                assert min_distance(arc_points(v, w, stop), obstacles) >= FOOTPRINT


def _clearance_of_every_point(
    dwa: DynamicWindowPlanner, pts: np.ndarray, costmap: LocalCostmap, start_clear_m: float | None = None
) -> Generator[None, None, tuple[np.ndarray, float]]:
    """The unsliced reference: every rollout point asked at once."""
    clear = costmap.clearance_m(pts.reshape(-1, 2), upper_bound_m=dwa.clearance_cap_m + dwa.contact_m)
    clear = clear.reshape(pts.shape[:2])
    return clear, min(dwa.contact_m, float(clear[0, 0]) - 1e-4)
    yield  # a generator, like the method it stands in for


def test_asking_only_the_points_before_contact_scores_every_rollout_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(99)
    dwa = DynamicWindowPlanner()
    scenes = [random_scene(rng) for _ in range(80)]
    scenes += [corridor(half_width_m=h) for h in (0.146, 0.12, 0.1)]  # walls close on both sides
    scenes += [np.array([[0.095, 0.0], [0.3, 0.2]])]  # already inside the contact distance
    cases = []
    for obstacles in scenes:
        v0 = float(rng.uniform(0.0, dwa.max_speed_mps))
        w0 = float(rng.uniform(-dwa.max_yaw_rate_radps, dwa.max_yaw_rate_radps))
        heading = rng.uniform(-math.pi, math.pi)
        waypoints = [(0.0, 0.0), (0.6 * math.cos(heading), 0.6 * math.sin(heading))]
        cases.append((LocalCostmap(obstacles, footprint_radius_m=FOOTPRINT), (v0, w0), waypoints))

    def plan_all(cases):
        return [dwa.plan((0.0, 0.0, 0.0), vel, costmap, PathTrack(wp)) for costmap, vel, wp in cases]

    sliced = plan_all(cases)
    monkeypatch.setattr(DynamicWindowPlanner, "_clearance_until_contact", _clearance_of_every_point)
    reference = plan_all(cases)
    blocked_rollouts = 0
    for a, b in zip(sliced, reference, strict=True):
        assert (a.v_mps, a.w_radps, a.blocked) == (b.v_mps, b.w_radps, b.blocked)
        np.testing.assert_array_equal(a.rollouts.score, b.rollouts.score)
        np.testing.assert_array_equal(a.rollouts.free_m, b.rollouts.free_m)
        np.testing.assert_array_equal(a.rollouts.admissible, b.rollouts.admissible)
        blocked_rollouts += int(np.isfinite(a.rollouts.free_m).sum())
    assert blocked_rollouts > 1000  # most scenes cut rollouts short, so the slicing was exercised


def corridor(length_m: float = 3.0, half_width_m: float = 0.146) -> np.ndarray:
    x = np.arange(-0.5, length_m, 0.01)
    return np.concatenate(
        (np.column_stack((x, np.full_like(x, half_width_m))), np.column_stack((x, -np.full_like(x, half_width_m))))
    )


def drive(
    dwa: DynamicWindowPlanner,
    world_points: np.ndarray,
    path: list[tuple[float, float]],
    pose: tuple[float, float, float],
    steps: int,
    dt_s: float = 0.1,
) -> tuple[list[tuple[float, float, float]], list[tuple[float, float]]]:
    """Kinematic closed loop: plan, move along the chosen arc for dt, repeat (velocities tracked exactly)."""
    track = PathTrack(path)
    v = w = 0.0
    poses, cmds = [pose], []
    for _ in range(steps):
        x, y, th = pose
        c, s = math.cos(th), math.sin(th)
        robot_pts = to_robot_frame(world_points, pose)
        sproj, _ = track.project(np.array([[x, y]]), track.progress_m - 0.1, track.progress_m + 0.5)
        track.progress_m = max(track.progress_m, float(sproj[0]))
        choice = dwa.plan(pose, (v, w), LocalCostmap(robot_pts, footprint_radius_m=FOOTPRINT), track)
        v, w = choice.v_mps, choice.w_radps
        cmds.append((v, w))
        if abs(w) < 1e-9:
            pose = (x + v * dt_s * c, y + v * dt_s * s, th)
        else:
            pose = (x + v / w * (math.sin(th + w * dt_s) - s), y - v / w * (math.cos(th + w * dt_s) - c), th + w * dt_s)
        poses.append(pose)
    return poses, cmds


def test_follows_a_corridor_centre_at_speed() -> None:
    dwa = DynamicWindowPlanner(window_s=0.1)
    walls = corridor()
    poses, cmds = drive(dwa, walls, [(0.0, 0.0), (2.5, 0.0)], (0.0, 0.02, 0.0), steps=60)
    assert max(v for v, _ in cmds) >= 0.29  # reaches the speed limit on the straight
    xy = np.array([p[:2] for p in poses])
    assert xy[-1, 0] > 1.2
    assert np.abs(xy[10:, 1]).max() < 0.03  # stays near the centre line
    assert min_distance(xy, walls) > 0.095


def test_stops_before_a_wall_at_the_end_of_a_dead_end() -> None:
    dwa = DynamicWindowPlanner(window_s=0.1)
    walls = np.concatenate((corridor(0.6), np.column_stack((np.full(30, 0.6), np.linspace(-0.15, 0.15, 30)))))
    poses, cmds = drive(dwa, walls, [(0.0, 0.0), (1.0, 0.0)], (0.0, 0.0, 0.0), steps=80)
    xy = np.array([p[:2] for p in poses])
    assert min_distance(xy, walls) >= FOOTPRINT + dwa.safety_margin_m - 1e-9
    assert cmds[-1][0] == pytest.approx(0.0, abs=1e-9)  # standing, not pushing
    assert xy[-1, 0] > 0.35  # and it did drive up to the wall


def test_costmap_clearance_is_exact_and_counts_map_cells_by_their_extent() -> None:
    rng = np.random.default_rng(3)
    scan = rng.uniform(-1, 1, (200, 2))
    cells = rng.uniform(-1, 1, (100, 2))
    costmap = LocalCostmap(scan, cells, map_point_radius_m=0.014)
    q = rng.uniform(-0.5, 0.5, (50, 2))
    want = np.minimum(
        np.min(np.hypot(q[:, None, 0] - scan[None, :, 0], q[:, None, 1] - scan[None, :, 1]), axis=1),
        np.min(np.hypot(q[:, None, 0] - cells[None, :, 0], q[:, None, 1] - cells[None, :, 1]), axis=1) - 0.014,
    )
    assert np.allclose(costmap.clearance_m(q), want)
    cost = costmap.cost(np.array([[0.0, 0.0], [5.0, 5.0]]))
    assert cost[1] == 0.0


def test_scan_and_map_points_in_the_robot_frame() -> None:
    pts = scan_points_robot(
        np.array([0.0, math.pi / 2, math.pi, 0.1]), np.array([1.0, 0.5, 0.1, 0.0]), np.array([True, True, True, False])
    )
    assert pts == pytest.approx(np.array([[1.0, 0.0], [0.0, 0.5]]), abs=1e-12)  # 0.1 m is under the min range
    grid = np.zeros((10, 10), dtype=np.int8)
    grid[5, 7] = 100  # centre at (0.15, 0.11) with 2 cm cells at the origin
    robot = map_points_robot(grid, (0.0, 0.0), 0.02, (0.11, 0.11, math.pi / 2), radius_m=0.5)
    assert robot == pytest.approx(np.array([[0.0, -0.04]]), abs=1e-12)


def test_path_track_projection_is_windowed() -> None:
    # out along y = 0 and back along y = 0.3: a point between must not jump to the way back
    track = PathTrack([(0.0, 0.0), (1.0, 0.0), (1.0, 0.3), (0.0, 0.3)])
    s, d = track.project(np.array([[0.5, 0.16]]), 0.0, 0.8)
    assert s[0] == pytest.approx(0.5) and d[0] == pytest.approx(0.16)
    s, _ = track.project(np.array([[0.5, 0.16]]))
    assert s[0] == pytest.approx(1.8)  # without the window the later leg is nearer
    assert track.point_at(1.15) == pytest.approx((1.0, 0.15))
    assert track.length_m == pytest.approx(2.3)


def test_local_planner_turns_in_place_the_short_way_to_a_path_behind() -> None:
    local = LocalPlanner()
    local.set_path([(0.0, 0.0), (0.0, -0.6)])  # straight "south" of a robot facing "east"
    cmd = local.step((0.0, 0.0, 0.0), (0.0, 0.0), np.zeros((0, 2)), None, 0.0, now_s=0.0)
    assert cmd.status is LocalStatus.ALIGNING and cmd.mode is DriveMode.TURN
    assert cmd.v_mps == 0.0 and cmd.w_radps < 0  # clockwise: -90 degrees, not +270
    local.set_path([(0.0, 0.0), (0.0, 0.6)])
    cmd = local.step((0.0, 0.0, 0.0), (0.0, 0.0), np.zeros((0, 2)), None, 0.0, now_s=0.1)
    assert cmd.w_radps > 0


def test_local_planner_stops_at_the_goal() -> None:
    local = LocalPlanner()
    local.set_path([(0.0, 0.0), (0.5, 0.0)])
    cmd = local.step((0.49, 0.005, 0.0), (0.05, 0.0), np.zeros((0, 2)), None, 0.0, now_s=0.0)
    assert cmd.status is LocalStatus.REACHED and cmd.mode is DriveMode.STOP
    assert (cmd.v_mps, cmd.w_radps) == (0.0, 0.0)


@pytest.mark.parametrize("per_place", [False, True])
def test_local_planner_recovers_then_gives_up_when_walled_in(per_place: bool) -> None:
    # a box around the robot, open nowhere; the goal lies beyond its east wall
    t = np.linspace(-0.15, 0.15, 31)
    box = np.concatenate(
        [np.column_stack((np.full(31, e), t)) for e in (-0.15, 0.15)]
        + [np.column_stack((t, np.full(31, e))) for e in (-0.15, 0.15)]
    )
    local = LocalPlanner(stuck_timeout_s=2.0, blocked_timeout_s=0.5, max_recoveries=2, recoveries_per_place=per_place)
    local.set_path([(0.0, 0.0), (1.0, 0.0)])
    statuses = []
    x = y = heading = 0.0
    for k in range(600):
        pts = to_robot_frame(box, (x, y, heading))
        cmd = local.step((x, y, heading), (0.0, 0.0), pts, None, 0.0, 0.1 * k)
        statuses.append(cmd.status)
        if cmd.give_up:
            break
        # an ideal robot that does as it is told
        x += cmd.v_mps * 0.1 * math.cos(heading)
        y += cmd.v_mps * 0.1 * math.sin(heading)
        heading += cmd.w_radps * 0.1
        assert min_distance(np.array([[x, y]]), box) >= FOOTPRINT
    assert LocalStatus.RECOVERING in statuses
    # counted per path the give-up stops; counted per place its recovery move is the next count's first
    assert cmd.give_up and cmd.mode is (DriveMode.RECOVER if per_place else DriveMode.STOP)


def to_robot_frame(points_world: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rel = points_world - pose[:2]
    return np.column_stack((c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]))


def test_invalid_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="half of step_m"):
        DynamicWindowPlanner(step_m=0.02, safety_margin_m=0.005)
    with pytest.raises(ValueError, match="positive"):
        DynamicWindowPlanner(max_speed_mps=0.0)
    with pytest.raises(ValueError, match="at least one waypoint"):
        PathTrack([])


def test_a_robot_that_ended_up_too_close_backs_out_instead_of_freezing() -> None:
    """A pose met in a closed-loop run: cutting a corner, 11 cm from a post, which the map's
    pessimistic cell extent puts at 9 cm, inside the contact distance. Every forward arc
    closes in on the post; the robot must back out and carry on, not stand there."""
    world = world_from_layout(generate_maze(6, 6, 30, "braided"), 0.012)
    occupied, origin = true_occupancy(world, 0.02)
    grid = np.where(occupied, 100, 0).astype(np.int8)
    caster = RayCaster.for_world(world)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    pose = [0.969, 1.114, math.radians(67.8)]
    local = LocalPlanner()
    local.set_path([(1.067, 1.066), (1.069, 1.371), (1.678, 1.368)])
    start_clearance = float(distance_to_obstacles(np.array([pose[:2]]), world)[0])
    for k in range(200):
        scan = scan_points_robot(angles, caster.cast(np.array(pose[:2]), angles + pose[2], 12.0))
        cells = map_points_robot(grid, origin, 0.02, (pose[0], pose[1], pose[2]), 0.8)
        cmd = local.step((pose[0], pose[1], pose[2]), (0.0, 0.0), scan, cells, 0.02 * math.sqrt(0.5), 0.2 * k)
        assert not cmd.give_up
        if cmd.status is LocalStatus.REACHED:
            break
        pose[0] += cmd.v_mps * 0.2 * math.cos(pose[2])  # an ideal robot that does as it is told
        pose[1] += cmd.v_mps * 0.2 * math.sin(pose[2])
        pose[2] += cmd.w_radps * 0.2
        assert float(distance_to_obstacles(np.array([pose[:2]]), world)[0]) >= min(start_clearance, 0.095) - 1e-3
    assert local.status is LocalStatus.REACHED


def test_points_at_is_point_at_for_every_arc_length() -> None:
    """The carrots of all rollouts at once are, to the bit, the ones asked one by one."""
    rng = np.random.default_rng(3)
    for waypoints in ([(0.0, 0.0)], [(0.0, 0.0), (0.3, 0.0)], rng.uniform(-1, 1, (9, 2)).tolist()):
        path = PathTrack(waypoints)
        s = np.concatenate((rng.uniform(-0.5, path.length_m + 0.5, 200), [0.0, path.length_m, *path.cum]))
        want = np.array([path.point_at(float(v)) for v in s])
        assert np.array_equal(path.points_at(s), want)


def test_the_coarse_to_fine_search_scores_what_it_tries_as_the_full_search_and_ends_on_a_local_best() -> None:
    rng = np.random.default_rng(5)
    fine = DynamicWindowPlanner(coarse_step=1)
    coarse = DynamicWindowPlanner()  # the default: every second speed and turn rate first
    assert coarse.coarse_step == 2
    scenes = [random_scene(rng) for _ in range(80)] + [corridor(half_width_m=h) for h in (0.146, 0.12, 0.1)]
    tried_share = []
    same_choice = 0
    for obstacles in scenes:
        v0 = float(rng.uniform(0.0, fine.max_speed_mps))
        w0 = float(rng.uniform(-fine.max_yaw_rate_radps, fine.max_yaw_rate_radps))
        heading = rng.uniform(-math.pi, math.pi)
        path = [(0.0, 0.0), (0.6 * math.cos(heading), 0.6 * math.sin(heading))]
        costmap = LocalCostmap(obstacles, footprint_radius_m=FOOTPRINT)
        a = fine.plan((0.0, 0.0, 0.0), (v0, w0), costmap, PathTrack(path))
        b = coarse.plan((0.0, 0.0, 0.0), (v0, w0), costmap, PathTrack(path))
        np.testing.assert_array_equal(a.rollouts.v_mps, b.rollouts.v_mps)
        np.testing.assert_array_equal(a.rollouts.w_radps, b.rollouts.w_radps)
        tried = ~np.isnan(b.rollouts.free_m)
        tried_share.append(tried.mean())
        # every arc tried is judged as the full search judges it; the others are never chosen
        np.testing.assert_array_equal(a.rollouts.free_m[tried], b.rollouts.free_m[tried])
        np.testing.assert_array_equal(a.rollouts.score[tried], b.rollouts.score[tried])
        np.testing.assert_array_equal(a.rollouts.admissible[tried], b.rollouts.admissible[tried])
        assert not b.rollouts.admissible[~tried].any()
        # blocked only when no arc of the window is admissible, as before
        assert a.blocked == b.blocked
        if b.blocked:
            continue
        same_choice += (a.v_mps, a.w_radps) == (b.v_mps, b.w_radps)
        # the choice is a local best of the fine grid: none of its neighbours scores higher
        vs, ws = np.unique(a.rollouts.v_mps), np.unique(a.rollouts.w_radps)
        grid = a.rollouts.score.reshape(vs.size, ws.size)
        r, c = int(np.searchsorted(vs, b.v_mps)), int(np.searchsorted(ws, b.w_radps))
        assert grid[r, c] >= grid[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2].max()
    assert np.mean(tried_share) < 0.6  # the search tried about half the arcs or fewer
    assert same_choice > 0.8 * len(scenes)  # and found the full search's best in most scenes


def test_reverse_arcs_are_judged_on_the_footprint_they_sweep() -> None:
    """A planner allowed to reverse rolls its reverse arcs out backwards: one that swings the body's
    side into a wall beside and behind is not admissible, straight back and the other way are."""
    wall = np.column_stack((np.arange(-0.4, 0.05, 0.005), np.full(90, FOOTPRINT + 0.018)))
    dwa = DynamicWindowPlanner(min_speed_mps=-0.1, coarse_step=1)
    costmap = LocalCostmap(wall, footprint_radius_m=FOOTPRINT)
    choice = dwa.plan((0.0, 0.0, 0.0), (-0.1, 0.0), costmap, PathTrack([(0.0, 0.0), (-1.0, 0.0)]))
    r = choice.rollouts
    back = r.v_mps == r.v_mps.min()
    assert r.v_mps.min() == pytest.approx(-0.1)
    clockwise = back & (r.w_radps == r.w_radps.min())
    straight = back & (r.w_radps == 0.0)
    counter = back & (r.w_radps == r.w_radps.max())
    assert r.points[clockwise][0, -1, 0] < 0.0 and r.points[clockwise][0, -1, 1] > 0.0  # back and to the left
    assert not r.admissible[clockwise].any()
    assert r.admissible[straight].all() and r.admissible[counter].all()
    for v, w, ok in zip(r.v_mps, r.w_radps, r.admissible, strict=True):
        if ok and abs(v) > 1e-6:  # every admissible arc, reverse ones too, keeps the footprint off the wall
            stop = abs(v) * dwa.latency_s + v * v / (2 * dwa.brake_decel_mps2)
            assert min_distance(arc_points(v, w, stop), wall) >= FOOTPRINT


def test_the_recovery_s_back_off_ends_before_the_emergency_stop_would_refuse_it() -> None:
    """A dead end 22 cm wide, the robot 9.5 cm from its end wall: it backs out, and stops backing
    where the control loop's guard still lets it move (a wall behind, beyond the back-off's length)."""
    from mazebot.config import Config
    from mazebot.tasks.control_task import MotorControl

    guard = MotorControl.from_config(Config()).safety.guard
    xs = np.arange(-0.4, 0.3, 0.005)
    ys = np.arange(-0.11, 0.11, 0.005)
    dead_end = np.concatenate((
        np.column_stack((xs, np.full(xs.size, 0.11))), np.column_stack((xs, np.full(xs.size, -0.11))),
        np.column_stack((np.full(ys.size, 0.095), ys)), np.column_stack((np.full(ys.size, -0.185), ys)),
    ))
    local = LocalPlanner(stuck_timeout_s=1.0, blocked_timeout_s=0.4)
    local.set_path([(0.0, 0.0), (1.0, 0.0)])
    x = y = heading = 0.0
    backed = 0
    for k in range(60):
        pts = to_robot_frame(dead_end, (x, y, heading))
        cmd = local.step((x, y, heading), (0.0, 0.0), pts, None, 0.0, 0.2 * k)
        if cmd.give_up:
            break
        verdict = guard.check(pts, cmd.v_mps, cmd.w_radps)
        assert not verdict.stop, (k, cmd, verdict.reason)
        backed += cmd.v_mps < 0
        x += cmd.v_mps * 0.2 * math.cos(heading)  # an ideal robot that does as it is told
        y += cmd.v_mps * 0.2 * math.sin(heading)
        heading += cmd.w_radps * 0.2
    assert backed > 0 and x < -0.02  # it did back out
