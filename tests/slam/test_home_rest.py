"""The start seen again at rest at the end of a run turns a map turned about the start back to the truth.

Against ground truth: a 6×6 maze built by hand (boards turned by 0.7° RMS) at a known angle,
keyframes cast from known poses, the map they drew turned about the start by the amount the
bench's hand-built runs that miss on coverage were (0.42-0.64°), and anchored to the start's
faces' mean, which the start's boards put off the maze's grid. Back home, the robot's
revolutions at rest are matched against keyframe 0's.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mazebot.bench.metrics import turn_about_start
from mazebot.geometry import compose, relative_pose
from mazebot.slam.home_rest import HOME_REST_REVOLUTIONS, HomeRest, HomeRevolution
from mazebot.slam.wall_faces import quarter_turns
from tests.slam.test_lattice_fit import chain_job as lattice_chain_job
from tests.slam.test_start_anchor import (
    HOME_AGAIN,
    MAZE_DEG,
    home_again,
    rest_surface,
    turned_about,
)
from tests.slam.test_start_anchor import hand_scene as hand_scene  # the fixture
from tests.slam.test_wall_lattice import keyframe_at

TURN_DEG = 0.5  # the map's turn about the start (the bench's runs that miss on coverage: 0.42-0.64°)


def _scene(world, world_poses, truth, cast_scan):
    """The scene home again (:func:`home_again`), and the revolutions at home (robot frame)."""
    keyframes, truth, surface = home_again(world, world_poses, truth, cast_scan)
    back = world_poses[0] + HOME_AGAIN
    home = [keyframe_at(world, cast_scan, 0, back, seed=200 + k) for k in range(HOME_REST_REVOLUTIONS)]
    at_home = [(kf.match_points.astype(np.float64), kf.sensor_xy) for kf in home]
    return keyframes, truth, surface, at_home


def _home(at_home, pose: np.ndarray) -> HomeRest:
    """The revolutions at home, each at the map's ``pose`` of the robot, judged against a chain of 2 cm and 1°."""
    revolutions = tuple(HomeRevolution(points, sensor_xy, pose.copy()) for points, sensor_xy in at_home)
    return HomeRest(revolutions, np.diag([0.02**2, 0.02**2, math.radians(1.0) ** 2]))


def test_revolutions_at_rest_at_home_turn_a_map_turned_about_the_start_back(hand_scene, cast_scan) -> None:
    world, world_poses, truth = hand_scene
    keyframes, truth, surface, at_home = _scene(world, world_poses, truth, cast_scan)
    start = rest_surface(world, cast_scan, world_poses[0])
    own = float(np.average(quarter_turns(start.normal_rad - math.radians(MAZE_DEG)), weights=start.count))
    assert abs(math.degrees(own)) > 0.2  # the start's boards: their mean is off the maze's grid

    def final(turn_deg: float, with_home: bool):
        """The final job on the map turned by ``turn_deg`` about the start (its first edge carries the turn, as a
        first turn in place's error does), anchored to the start's faces' mean at 0.3° (the two-way fit's std
        on the bench's hand-built mazes); the optimized map's turn about the start against the truth (degrees)."""
        poses = truth.copy()
        poses[1:] = turned_about(truth[0], truth[1:], math.radians(turn_deg))
        for kf, pose in zip(keyframes, poses, strict=True):
            kf.pose = pose.copy()
        base = lattice_chain_job(keyframes, poses, None)
        ei, ej, z, _ = base.edges  # a sequential match's information (1 mm, 0.11°), as SLAM's edges claim
        info = np.tile(np.diag([1 / 0.001**2, 1 / 0.001**2, 1 / math.radians(0.11) ** 2]), (len(ei), 1, 1))
        # the map's pose of the robot at home: the newest keyframe's, turned with the map
        home = _home(at_home, poses[-1])
        job = replace(
            base,
            edges=(ei, ej, z, info),
            wall_reference_rad=math.radians(MAZE_DEG + turn_deg),  # the map's own grid: turned with it
            anchor_wall=(math.radians(MAZE_DEG) + own, math.radians(0.3)),
            rest_surface=surface,
            rebuild_anyway=True,
            home_rest=home if with_home else None,
        )
        result = job.run()
        assert result.poses is not None
        turned = turn_about_start(result.poses[:, :2] - result.poses[0, :2], truth[:, :2])
        assert turned is not None
        return result, math.degrees(turned[0])

    alone, home = [], []
    for turn_deg in (TURN_DEG, -TURN_DEG, 0.0):
        result, turned = final(turn_deg, with_home=False)
        assert result.home_turn is None
        alone.append(turned)
        result, turned = final(turn_deg, with_home=True)
        turn = result.home_turn
        assert turn is not None and turn.agreeing >= 3 and turn.used, turn_deg
        # the revolutions at home measure the map's turn about the start (against the truth: turn_deg) ...
        assert -math.degrees(turn.correction_rad) == pytest.approx(turn_deg, abs=0.05)
        assert 0.0 < math.degrees(turn.std_rad) < 0.2  # at rest: far tighter than the faces' 0.3°
        home.append(turned)
    # ... and the final map ends turned back within 0.1° of the truth, where the faces' anchor alone left it
    # up to 0.6° off (its boards' mean 0.6° off the maze's grid)
    assert max(abs(t) for t in home) < 0.1, home
    assert max(abs(t) for t in alone) > 0.25, alone


def test_a_robot_home_whose_heading_does_not_follow_the_grid_leaves_the_map_as_it_is(hand_scene, cast_scan) -> None:
    # Closures hold the keyframes around the start to keyframe 0; only the map beyond turns with the grid.
    # The robot home sees the start's region, not the map's turn: its heading there says nothing of the grid.
    world, world_poses, truth = hand_scene
    keyframes, truth, surface, at_home = _scene(world, world_poses, truth, cast_scan)
    poses = truth.copy()
    poses[1:-1] = turned_about(truth[0], truth[1:-1], math.radians(TURN_DEG))  # home (the last) held right
    for kf, pose in zip(keyframes, poses, strict=True):
        kf.pose = pose.copy()
    base = lattice_chain_job(keyframes, poses, None)
    ei, ej, z, info = base.edges
    last = len(poses) - 1
    held = np.diag([1 / 0.0005**2, 1 / 0.0005**2, 1 / math.radians(0.02) ** 2])[None]  # closures home, at rest
    edges = (np.append(ei, 0), np.append(ej, last), np.vstack([z, relative_pose(truth[0], truth[last])]),
             np.concatenate([info, held]))
    job = replace(base, edges=edges, wall_reference_rad=math.radians(MAZE_DEG + TURN_DEG), rest_surface=surface,
                  rebuild_anyway=True)
    without = job.run()
    result = replace(job, home_rest=_home(at_home, poses[-1])).run()
    turn = result.home_turn
    assert turn is not None and abs(math.degrees(turn.correction_rad)) < 0.1  # the robot's heading: right
    assert not turn.used and turn.follows is not None and turn.follows < 0.5
    assert result.poses is None and result.grid is None  # nothing to apply: the map stays as it is
    assert without.poses is not None  # (the same job without them optimizes and rebuilds)


def test_revolutions_at_home_that_do_not_match_the_start_leave_the_map_as_it_is(hand_scene, cast_scan) -> None:
    # the robot stopped somewhere that is not its start (a cell away): nothing verifies, nothing moves
    world, world_poses, truth = hand_scene
    keyframes, truth, surface, _ = _scene(world, world_poses, truth, cast_scan)
    elsewhere = compose(world_poses[0], np.array([0.3048, 0.0, 0.4]))
    revolutions = [keyframe_at(world, cast_scan, 0, elsewhere, seed=300 + k) for k in range(HOME_REST_REVOLUTIONS)]
    at_home = [(kf.match_points.astype(np.float64), kf.sensor_xy) for kf in revolutions]
    poses = truth.copy()
    for kf, pose in zip(keyframes, poses, strict=True):
        kf.pose = pose.copy()
    # the map thinks the robot is at the start: every revolution's walls lie a cell off
    home = _home(at_home, poses[-1])
    base = replace(lattice_chain_job(keyframes, poses, None), wall_reference_rad=math.radians(MAZE_DEG),
                   rest_surface=surface, rebuild_anyway=True)
    without = base.run()
    result = replace(base, home_rest=home).run()
    assert result.home_turn is None
    assert result.poses is None and result.grid is None  # nothing to apply: the map stays as it is
    assert without.poses is not None
