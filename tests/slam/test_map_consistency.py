"""The map's self-consistency: each scan registered against the map the others make at their poses."""

from __future__ import annotations

import math

import numpy as np

from mazebot.geometry import compose
from mazebot.sim.world import World
from mazebot.slam.icp import IcpParams
from mazebot.slam.map_consistency import (
    Neighbourhood,
    consistency,
    first_scan_heading_deg,
    judged_scans,
    scan_corrections,
)


def _maze_scans(world: World, cast_scan, count: int, seed: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """``count`` poses near cell centres of the maze (any heading) and each one's scan, in the lidar frame."""
    assert world.maze is not None
    rng = np.random.default_rng(seed)
    poses, scans = [], []
    for _ in range(count):
        x, y = world.maze.cell_center_m((int(rng.integers(world.maze.width)), int(rng.integers(world.maze.height))))
        pose = np.array([x + rng.uniform(-0.03, 0.03), y + rng.uniform(-0.03, 0.03), rng.uniform(-math.pi, math.pi)])
        angles, ranges = cast_scan(world, pose, n=720, max_range_m=3.0)
        ok = np.isfinite(ranges) & (ranges > 0.15)
        poses.append(pose)
        scans.append(np.column_stack((ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok]))))
    return np.array(poses), scans


def _corrections(poses: np.ndarray, scans: list[np.ndarray]) -> np.ndarray:
    return scan_corrections(
        poses, scans, judged_scans(len(scans), 12), IcpParams(),
        Neighbourhood(exclude=0, voxel_m=0.01, normal_radius_m=0.1, max_scans=39),
    )


def test_scans_at_their_true_poses_need_no_correction(maze_world: World, cast_scan) -> None:
    poses, scans = _maze_scans(maze_world, cast_scan, 40, seed=5)
    figures = consistency(_corrections(poses, scans))
    assert figures["scans"] >= 10
    assert figures["heading_rms_deg"] < 0.1
    assert figures["shift_rms_m"] < 0.003


def test_a_scan_turned_off_the_map_is_asked_back_by_its_angle(maze_world: World, cast_scan) -> None:
    """The first pose turned by 1° and moved by 2 cm: the others ask it back, the others stay put."""
    poses, scans = _maze_scans(maze_world, cast_scan, 40, seed=5)
    wrong = poses.copy()
    wrong[0] = compose(poses[0], np.array([0.02, 0.0, math.radians(1.0)]))
    corrections = _corrections(wrong, scans)
    first = first_scan_heading_deg(corrections)
    assert first is not None and abs(first + 1.0) < 0.1
    row = corrections[corrections[:, 0] == 0][0]
    assert abs(row[1] + 0.02) < 0.003 and abs(row[2]) < 0.003
    others = consistency(corrections[corrections[:, 0] != 0])
    assert others["heading_rms_deg"] < 0.1


def test_judged_scans_spread_over_the_log_and_keep_the_first() -> None:
    assert judged_scans(5, 10) == [0, 1, 2, 3, 4]
    picked = judged_scans(910, 60)
    assert picked[0] == 0 and picked[-1] == 909 and len(picked) == 60


def test_nothing_judged_gives_empty_figures() -> None:
    figures = consistency(np.zeros((0, 4)))
    assert figures["scans"] == 0 and math.isnan(figures["heading_rms_deg"])
    assert first_scan_heading_deg(np.zeros((0, 4))) is None
