"""Ties across one straight wall seen on two passes (mazebot.slam.line_ties), without the lattice."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mazebot.geometry import relative_pose
from mazebot.slam.keyframes import Keyframe
from mazebot.slam.line_ties import line_ties
from mazebot.slam.slam import LoopClosureJob, SlamParams

# a walk through the 6x6 maze fixture's cells (col, row), each a neighbour of the one before
ROUTE = [(0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (2, 1), (2, 2), (2, 3), (3, 3), (3, 2), (4, 2), (4, 3)]


def keyframe_at(world, cast_scan, index: int, pose: np.ndarray, seed: int = 0) -> Keyframe:
    """A keyframe of one revolution (1 % range noise) from ``pose``, everything in its own frame."""
    angles, ranges = cast_scan(world, pose, noise_rel=0.01, seed=seed)
    valid = np.isfinite(ranges) & (ranges > 0.15)
    hits = np.column_stack((ranges[valid] * np.cos(angles[valid]), ranges[valid] * np.sin(angles[valid])))
    return Keyframe(
        index=index,
        time_s=float(index),
        pose=np.asarray(pose, dtype=np.float64),
        hits=hits.astype(np.float32),
        match_points=hits.astype(np.float32),
        sensor_xy=np.zeros(2),
        ray_ends=hits.astype(np.float32),
        ray_hit=np.ones(len(hits), dtype=bool),
        integrated_pose=np.asarray(pose, dtype=np.float64),
    )


def route_poses(world) -> np.ndarray:
    """True poses along ROUTE: near each cell's centre (a few mm off), headings all round."""
    layout = world.maze
    rng = np.random.default_rng(4)
    rows = []
    for k, cell in enumerate(ROUTE):
        x, y = layout.cell_center_m(cell)
        rows.append((x + rng.uniform(-0.03, 0.03), y + rng.uniform(-0.03, 0.03), math.remainder(0.7 * k, math.tau)))
    return np.array(rows)


def drifted_route(world, cast_scan, per_cell: int = 1) -> tuple[np.ndarray, np.ndarray, list[Keyframe]]:
    """The truth, the chain's poses (the second half slipped 12 mm east and 8 mm south) and the keyframes.

    ``per_cell`` keyframes in each cell of the route, a few millimetres and a turn apart.
    """
    truth = np.repeat(route_poses(world), per_cell, axis=0)
    if per_cell > 1:
        truth[:, 2] += np.tile(np.linspace(0.0, 1.0, per_cell, endpoint=False), len(ROUTE))
        truth[:, :2] += np.random.default_rng(7).uniform(-0.01, 0.01, (len(truth), 2))
    keyframes = [keyframe_at(world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    drifted = truth.copy()
    drifted[len(truth) // 2 :, :2] += (0.012, -0.008)
    for kf, pose in zip(keyframes, drifted, strict=True):
        kf.pose = pose.copy()
    return truth, drifted, keyframes


@pytest.mark.parametrize("per_cell", [1, 3])
def test_a_tie_says_how_far_across_the_wall_the_second_pass_lies(maze_world, cast_scan, per_cell):
    """Each tie's measurement puts the newer keyframe where the truth has it, across the wall (with three
    keyframes a cell, enough pairs of one stretch see both sides of a board to give its thickness)."""
    truth, drifted, keyframes = drifted_route(maze_world, cast_scan, per_cell)
    i, j, z, info = line_ties(keyframes, drifted, 0.005, min_gap=2 * per_cell)
    half = len(truth) // 2
    across = (i < half) & (j >= half)
    assert across.sum() >= 2
    for a, b, meas, omega in zip(i[across], j[across], z[across], info[across], strict=True):
        true_rel = relative_pose(truth[a], truth[b])
        # the residual of the truth against the tie, in the measurement's frame, weighed by its information
        c, s = math.cos(meas[2]), math.sin(meas[2])
        d = true_rel[:2] - meas[:2]
        e = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], 0.0])
        assert math.sqrt(float(e @ omega @ e)) * 0.005 < 0.004, (a, b)  # within 4 mm across the wall


@pytest.mark.parametrize("std_m", [0.0, 0.005])
def test_an_optimization_with_line_ties_takes_out_a_slip_of_the_chain(maze_world, cast_scan, std_m):
    """The chain says keyframes 6.. are 12 mm east and 8 mm south; with no lattice, only the walls both passes saw
    say otherwise."""
    truth, drifted, keyframes = drifted_route(maze_world, cast_scan)
    count = len(truth)
    ei, ej = np.arange(count - 1), np.arange(1, count)
    z = relative_pose(drifted[ei], drifted[ej])  # the chain as its scan matches saw it
    info = np.tile(np.diag([1 / 0.005**2, 1 / 0.005**2, 1 / 0.01**2]), (count - 1, 1, 1))
    base = SlamParams(lattice=None)
    params = replace(base, line_tie_std_m=std_m, loop=replace(base.loop, min_keyframe_gap=2))
    job = LoopClosureJob(
        candidates=[],
        keyframes=keyframes,
        poses=drifted.copy(),
        integrated_poses=drifted.copy(),
        edges=(ei, ej, z, info),
        params=params,
        wall_reference_rad=0.0,
        optimize_anyway=True,
        anchor_wall=(0.0, 0.001),
    )
    result = job.run()
    assert result.poses is not None
    slip_x = result.poses[6:, 0] - truth[6:, 0]  # the walls both passes saw here face east and west
    if std_m > 0:  # the slip across them (12 mm) is mostly taken out; along them nothing says otherwise
        assert np.abs(slip_x).max() < 0.008 and np.abs(slip_x).mean() < 0.006, slip_x
    else:
        assert slip_x.min() > 0.011, slip_x
