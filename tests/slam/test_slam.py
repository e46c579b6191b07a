"""The SLAM façade against ground truth: a simulated robot touring a maze, no daemon.

A :class:`SimulatedRobot` is driven by the scripted tour (the bench's driver, with the
true pose) through the real motor and encoder drivers; its lidar head's samples are cut
into revolutions (:class:`Scan`, true sample times) and its encoder odometry goes into
an :class:`OdometryHistory` at 50 Hz, as the daemon's tasks do.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
import pytest

from mazebot.bench.metrics import map_metrics
from mazebot.bench.scripted_drive import ScriptedDriver, dfs_tour, straighten
from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.geometry import compose, inverse, relative_pose, wrap_angle
from mazebot.io.encoders import WheelEncoders
from mazebot.io.motors import DifferentialMotors
from mazebot.io.scan import Scan
from mazebot.sim.lidar_samples import DeviceSamples, concat
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.robot import SimulatedRobot
from mazebot.sim.world import World, world_from_layout
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.keyframes import KeyframeSelector
from mazebot.slam.odometry import DiffDriveOdometry
from mazebot.slam.slam import Slam, SlamParams, SlamUpdate

STEP_S = 0.01


def _scan(parts: list[DeviceSamples]) -> Scan:
    s = concat(parts)
    angle = (-np.deg2rad(s.angle_deg) + math.pi) % math.tau - math.pi  # clockwise device -> CCW robot
    return Scan(angle, s.dist_mm / 1000.0, s.quality.astype(np.uint8), s.time_s, (s.dist_mm > 0) & (s.quality > 0))


def tour(
    world: World,
    config: Config,
    seed: int,
    slam: Slam,
    after_update: Callable[[SlamUpdate], None] | None = None,
    still_s: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, list[tuple[float, np.ndarray]]]:
    """Drive the whole scripted tour (after ``still_s`` at rest); returns (SLAM poses, true poses in the map
    frame, true trajectory)."""
    robot = SimulatedRobot(world, config, seed=seed)
    encoders = WheelEncoders.from_config(config.encoders, robot.pin_factory)
    motors = DifferentialMotors.from_config(config.motors, robot.kit, RealClock(), loop=None)
    drive = config.drive
    odometry = DiffDriveOdometry(config.encoders.ticks_per_rev, drive.wheel_diameter_m, drive.track_width_m)
    history = OdometryHistory(3.0)
    layout = world.maze
    assert layout is not None
    driver = ScriptedDriver(
        [layout.cell_center_m(c) for c in straighten(dfs_tour(layout))[1:]],
        robot.physics,
        speed_mps=0.8 * config.drive.max_speed_mps,
        yaw_rate_radps=0.8 * config.drive.max_yaw_rate_radps,
        track_width_m=config.drive.track_width_m,
        full_throttle_mps=config.drive.max_wheel_speed_mps,
        deadband=config.sim.deadband,
    )
    start = np.array(world.start_pose)
    estimates, truths, trajectory = [], [], []
    parts: list[DeviceSamples] = []
    started = False
    try:
        robot.step(0.0)
        reading = encoders.read()
        odometry.update(reading.left_ticks, reading.right_ticks)
        history.append(0.0, 0.0, 0.0, 0.0)
        robot.lidar_head.restart(0.0)
        k = 0
        while not driver.done and k * STEP_S < 600.0:
            k += 1
            t = k * STEP_S
            motors.set(*(driver.command() if t >= still_s else (0.0, 0.0)))
            robot.step(t)
            trajectory.append((t, np.array(robot.physics.pose)))
            if k % 2:
                continue
            reading = encoders.read()  # 50 Hz odometry, like the odometry task
            odometry.update(reading.left_ticks, reading.right_ticks)
            history.append(t, odometry.pose.x_m, odometry.pose.y_m, odometry.pose.theta_rad)
            samples = robot.lidar_head.advance(t, robot.poses)
            begin = 0
            for i in [*np.flatnonzero(samples.start).tolist(), len(samples)]:
                if i > begin and started:
                    parts.append(DeviceSamples(*(getattr(samples, f)[begin:i] for f in
                                                 ("time_s", "angle_deg", "dist_mm", "quality", "start"))))
                if i < len(samples):  # a revolution starts here: the previous one is complete
                    if parts:
                        scan = _scan(parts)
                        update = slam.update(scan, history)
                        if after_update is not None:
                            after_update(update)
                        x, y, th = robot.poses.at(np.array([scan.end_time_s]))
                        estimates.append(update.pose)
                        truths.append(relative_pose(start, np.array([x[0], y[0], th[0]])))
                    parts = []
                    started = True
                begin = i
    finally:
        motors.close()
        encoders.close()
        robot.close()
    return np.array(estimates), np.array(truths), trajectory


def _errors(est: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    err = est - truth
    dist = np.hypot(err[:, 0], err[:, 1])
    heading_rms_deg = math.degrees(math.sqrt(np.mean(wrap_angle(err[:, 2]) ** 2)))
    return float(np.sqrt(np.mean(dist**2))), float(dist.max()), heading_rms_deg


def _false_closures(slam: Slam, trajectory: list[tuple[float, np.ndarray]]) -> int:
    times = np.array([t for t, _ in trajectory])
    poses = np.array([p for _, p in trajectory])
    th = np.unwrap(poses[:, 2])

    def at(t: float) -> np.ndarray:
        return np.array([np.interp(t, times, poses[:, 0]), np.interp(t, times, poses[:, 1]), np.interp(t, times, th)])

    bad = 0
    for c in slam.closures:
        truth = relative_pose(at(c.old_time_s), at(c.new_time_s))
        off_m = math.hypot(*(truth[:2] - c.measurement[:2]))
        bad += off_m > 0.05 or abs(wrap_angle(truth[2] - c.measurement[2])) > 0.05
    return bad


@pytest.fixture(scope="module")
def loop_maze() -> World:
    """A 4x4 braided maze (it has loops), 1 ft cells, 12 mm walls."""
    return world_from_layout(generate_maze(4, 4, seed=2, kind="braided"), 0.012)


def test_maps_a_simulated_maze_to_the_centimetre(loop_maze: World) -> None:
    config = Config()
    slam = Slam(SlamParams.from_config(config.slam, config.lidar))
    est, truth, trajectory = tour(loop_maze, config, seed=2, slam=slam)
    ate_rms, ate_max, heading_rms = _errors(est, truth)
    assert ate_rms < 0.01 and ate_max < 0.03 and heading_rms < 1.0
    scores = map_metrics(slam.grid, loop_maze, loop_maze.start_pose, config.robot.footprint_radius_m)
    assert scores["map_f1"] >= 0.93 and scores["map_recall"] >= 0.98
    assert scores["coverage"] >= 0.95
    assert len(slam.closures) >= 5 and _false_closures(slam, trajectory) == 0
    # the learned odometry calibration found the simulated right wheel's +0.4 %: about +2.7e-2 rad/m
    assert slam.calibration.bias_rad_per_m == pytest.approx(0.004 / config.drive.track_width_m, abs=0.006)
    assert abs(slam.time_offset.offset_s) < 0.003  # true sample times: no offset to find
    assert len(slam.keyframes) == len(slam.graph)


def test_loop_closure_in_the_background_follows_the_keyframes_added_meanwhile(loop_maze: World) -> None:
    # The daemon's way: update() hands out a job, an executor runs it while scans keep coming,
    # and the result is applied later. Here the result is applied four scans after the job started.
    config = Config()
    slam = Slam(SlamParams.from_config(config.slam, config.lidar), background=True)
    pending: list[tuple[int, Future]] = []
    generations = []
    applied = []
    with ThreadPoolExecutor(max_workers=1) as executor:

        def after(update: SlamUpdate) -> None:
            assert update.verdicts == ()  # nothing runs inline
            for due, future in list(pending):
                if slam.scans >= due:
                    pending.remove((due, future))
                    applied.append(slam.apply(future.result()))
            if update.loop_job is not None:
                assert slam.job_running
                pending.append((slam.scans + 4, executor.submit(update.loop_job.run)))
            generations.append(slam.grid.generation)

        est, truth, _ = tour(loop_maze, config, seed=2, slam=slam, after_update=after)
    ate_rms, ate_max, heading_rms = _errors(est, truth)
    assert ate_rms < 0.012 and ate_max < 0.035 and heading_rms < 1.2
    assert len(slam.closures) >= 5
    assert generations == sorted(generations)  # a client never sees the generation go back
    if any(applied):
        assert generations[-1] > generations[0]
    # the graph and the keyframes agree after every merge
    np.testing.assert_allclose(slam.graph.vertices, slam.keyframe_poses())


def test_first_scan_sets_the_map_frame_and_the_odometry_correction() -> None:
    world = world_from_layout(generate_maze(3, 3, seed=1, kind="perfect"), 0.012)
    start = np.array([world.start_pose[0], world.start_pose[1], world.start_pose[2]])
    from mazebot.sim.raycast import cast_rays

    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    ranges = cast_rays(start[:2], angles + start[2], world.segments, world.circles, 12.0)
    valid = np.isfinite(ranges)
    scan = Scan(angles, np.where(valid, ranges, 0.0), np.full(360, 47, np.uint8), np.linspace(0.82, 1.0, 360), valid)
    history = OdometryHistory()
    odom = np.array([0.3, -0.2, 0.5])  # the encoders did not start at the origin
    history.append(0.0, *odom)
    history.append(2.0, *odom)
    slam = Slam(SlamParams(), initial_pose=np.array([1.0, 2.0, 0.0]))
    update = slam.update(scan, history)
    np.testing.assert_allclose(update.pose, compose([1.0, 2.0, 0.0], odom), atol=1e-12)
    np.testing.assert_allclose(compose(update.map_from_odom, odom), update.pose, atol=1e-12)
    np.testing.assert_allclose(slam.map_from_odom, compose(update.pose, inverse(odom)), atol=1e-12)
    assert update.keyframe == 0 and update.match is None and len(slam.graph) == 1
    # standing still: the next scans match, nothing moves, no new keyframe
    for _ in range(3):
        update = slam.update(scan, history)
        assert update.matched and update.keyframe is None
        assert np.hypot(*(update.pose[:2] - compose([1.0, 2.0, 0.0], odom)[:2])) < 0.002
    assert slam.grid.occupied_mask().sum() > 100


def test_keyframe_after_ten_centimetres_or_fifteen_hundredths_of_a_radian() -> None:
    select = KeyframeSelector(distance_m=0.10, angle_rad=0.15)
    assert select.is_keyframe(np.zeros(3))
    select.accept(np.zeros(3))
    assert not select.is_keyframe(np.array([0.09, 0.0, 0.14]))
    assert select.is_keyframe(np.array([0.0, 0.1, 0.0]))
    assert select.is_keyframe(np.array([0.0, 0.0, -0.15]))
    assert select.is_keyframe(np.array([0.0, 0.0, 2 * math.pi - 0.15]))  # across ±π


@pytest.mark.parametrize("theta", [0.0, 0.3, -1.2, 2.9])
def test_wall_direction_shows_the_maze_grid(theta: float, cast_scan) -> None:
    from mazebot.slam.keyframes import Keyframe
    from mazebot.slam.preprocess import prepare_scan

    world = world_from_layout(generate_maze(6, 6, seed=3, kind="braided"), 0.012)
    assert world.maze is not None
    x, y = world.maze.cell_center_m((2, 3))
    angles, ranges = cast_scan(world, np.array([x + 0.03, y - 0.02, theta]), noise_rel=0.01, seed=5)
    valid = np.isfinite(ranges)
    scan = Scan(angles, np.where(valid, ranges, 0.0), np.full(360, 47, np.uint8), np.zeros(360), valid)
    kf = Keyframe.from_scan(0, np.zeros(3), prepare_scan(scan, None))
    direction, strength, count = kf.wall_direction()
    # seen from a robot turned by theta, the walls (at 0 mod 90° in the world) lie at -theta
    off = (direction + theta + math.pi / 4) % (math.pi / 2) - math.pi / 4
    assert abs(math.degrees(off)) < 1.0  # one keyframe is a weak prior (its std: wall_prior_std_rad, 0.57°)
    assert strength > 0.8 and count > 100


def _map_rotation_deg(slam: Slam, trajectory: list[tuple[float, np.ndarray]], start: np.ndarray) -> float:
    """The rotation (degrees) that best fits the keyframe positions to the true ones (2D Kabsch, map frame)."""
    times = np.array([t for t, _ in trajectory])
    poses = np.array([p for _, p in trajectory])
    at = np.array([kf.time_s for kf in slam.keyframes])
    true_xy = np.column_stack((np.interp(at, times, poses[:, 0]), np.interp(at, times, poses[:, 1])))
    truth = relative_pose(start, np.column_stack((true_xy, np.zeros(len(at)))))
    est = slam.keyframe_poses()[:, :2]
    a, b = est - est.mean(axis=0), truth[:, :2] - truth[:, :2].mean(axis=0)
    return math.degrees(math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b))))


def test_a_map_started_at_rest_is_not_turned_about_the_start(loop_maze: World) -> None:
    # The first in-place turns, matched against a submap of one or two keyframes, used to
    # leave the whole map turned about the start (0.1-0.4° in the bench's 6x6 mazes, 0.16°
    # here), and the wall priors, estimating the wall grid from the keyframes alone,
    # followed the turned map. Now keyframe 0 fuses the revolutions the robot stands still
    # for and ties the wall grid to the walls it sees: the map is turned by far less. (Anchored to
    # the faces alone -0.046°; with the closure home to the start at rest counted beside them,
    # one turning keyframe's view, -0.061°.)
    config = Config()
    slam = Slam(SlamParams.from_config(config.slam, config.lidar))
    _, _, trajectory = tour(loop_maze, config, seed=2, slam=slam, still_s=4.0)
    rotation_deg = _map_rotation_deg(slam, trajectory, np.array(loop_maze.start_pose))
    assert abs(rotation_deg) < 0.07, rotation_deg
    assert slam.anchor_revolutions == config.slam.walls.anchor_revolutions


def test_keyframe_0_measures_the_walls_over_the_revolutions_at_rest(maze_world: World, cast_scan) -> None:
    # One scan's wall direction is a few tenths of a degree off (the A1's 1 % range noise);
    # while the robot stands still, keyframe 0 averages it over anchor_revolutions, and
    # the planner waits for that (Slam.anchored) before it drives.
    from mazebot.slam.keyframes import Keyframe
    from mazebot.slam.preprocess import prepare_scan

    assert maze_world.maze is not None
    x, y = maze_world.maze.cell_center_m((2, 3))
    theta = 0.3
    history = OdometryHistory()
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(100.0, 0.0, 0.0, 0.0)
    slam = Slam(SlamParams())
    revolutions = slam.params.anchor_revolutions

    def scan(k: int, pose: np.ndarray) -> Scan:
        angles, ranges = cast_scan(maze_world, pose, noise_rel=0.01, seed=k)
        valid = np.isfinite(ranges)
        times = np.linspace(0.2 * k, 0.2 * k + 0.18, 360)
        return Scan(angles, np.where(valid, ranges, 0.0), np.full(360, 47, np.uint8), times, valid)

    def off_deg(direction_rad: float) -> float:  # the walls lie at -theta (mod 90°) in the robot frame
        return math.degrees((direction_rad + theta + math.pi / 4) % (math.pi / 2) - math.pi / 4)

    single = []
    for k in range(revolutions):
        assert not slam.anchored
        one = scan(k, np.array([x, y, theta]))
        slam.update(one, history)
        single.append(off_deg(Keyframe.from_scan(0, np.zeros(3), prepare_scan(one, None)).wall_direction()[0]))
    assert slam.anchored and slam.anchor_revolutions == revolutions and len(slam.keyframes) == 1
    assert slam.anchor_wall_rad is not None
    single_rms = math.sqrt(np.mean(np.square(single)))
    assert single_rms > 0.2 and max(np.abs(single)) > 0.4  # one revolution alone
    # the average takes the noise out; what is left (0.14° here) is the normals' bias at this spot
    assert abs(off_deg(slam.anchor_wall_rad)) < 0.6 * single_rms
    assert slam.wall_reference_rad is not None
    assert abs(math.degrees(slam.wall_reference_rad - slam.anchor_wall_rad)) < 1e-9  # keyframe 0 is the map frame


def test_keyframe_0_stops_measuring_when_the_robot_moves_early(maze_world: World, cast_scan) -> None:
    assert maze_world.maze is not None
    x, y = maze_world.maze.cell_center_m((2, 3))
    history = OdometryHistory()
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(0.79, 0.0, 0.0, 0.0)
    history.append(0.8, 0.005, 0.0, 0.0)  # the robot was pushed 5 mm
    history.append(2.0, 0.005, 0.0, 0.0)
    slam = Slam(SlamParams())
    for k in range(5):
        angles, ranges = cast_scan(maze_world, np.array([x + (0.005 if k == 4 else 0.0), y, 0.0]), seed=k)
        valid = np.isfinite(ranges)
        times = np.linspace(0.2 * k, 0.2 * k + 0.18, 360)
        slam.update(Scan(angles, np.where(valid, ranges, 0.0), np.full(360, 47, np.uint8), times, valid), history)
        assert slam.anchored is (k == 4)
    assert slam.anchor_revolutions == 4 and len(slam.keyframes) == 1  # the moved revolution is no part of it


def test_wall_direction_is_estimated_with_the_poses_not_taken_from_one_keyframe(loop_maze: World) -> None:
    # The first keyframe's wall direction is one noisy scan's. Start the estimate 0.3° off
    # (twice what seed 1 gave on japan2013ef): the wall-direction vertex of the pose graph
    # must find the maze's true grid (0 mod 90° in the map frame: the robot starts aligned),
    # and the map must not turn with the wrong start value.
    config = Config()
    slam = Slam(SlamParams.from_config(config.slam, config.lidar))
    wrong_rad = math.radians(0.3)
    seeded = []

    def after(update: SlamUpdate) -> None:
        if not seeded and slam.wall_reference_rad is not None:
            slam.wall_reference_rad = wrong_rad
            seeded.append(True)

    est, truth, _ = tour(loop_maze, config, seed=2, slam=slam, after_update=after)
    assert seeded and slam.wall_reference_rad is not None
    assert abs(math.degrees(slam.wall_reference_rad)) < 0.05
    _, _, heading_rms = _errors(est, truth)
    assert heading_rms < 0.3
