"""Global paths: A* on the cell graph (with turn costs), straight-run merging, grid paths on the inflated map."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable

import numpy as np
import pytest
from scipy import ndimage

from mazebot.planner.global_path import (
    GridCostmap,
    cell_costs,
    cell_waypoints,
    merge_straight,
    shortcut,
    shortest_cell_path,
)
from mazebot.slam.grid import FREE, OCCUPIED

Cell = tuple[int, int]


def grid_graph(width: int, height: int, blocked: Iterable[tuple[Cell, Cell]] = ()) -> dict[Cell, list[Cell]]:
    """Open links of a width x height grid of cells, minus the ``blocked`` pairs."""
    cut = {frozenset(pair) for pair in blocked}
    adj: dict[Cell, list[Cell]] = {}
    for i in range(width):
        for j in range(height):
            adj[(i, j)] = [
                (i + di, j + dj)
                for di, dj in ((1, 0), (0, 1), (-1, 0), (0, -1))
                if 0 <= i + di < width and 0 <= j + dj < height and frozenset({(i, j), (i + di, j + dj)}) not in cut
            ]
    return adj


def test_shortest_path_is_shortest_and_steps_between_neighbours() -> None:
    # a wall across column 1 except at the top: the way from (0, 0) to (2, 0) goes over it
    adj = grid_graph(3, 3, [((0, 0), (1, 0)), ((0, 1), (1, 1)), ((1, 0), (2, 0)), ((1, 1), (2, 1))])
    path = shortest_cell_path(adj.__getitem__, (0, 0), (2, 0))
    assert path is not None
    assert path[0] == (0, 0) and path[-1] == (2, 0)
    assert len(path) == 7  # up 2, across 2, down 2
    for a, b in itertools.pairwise(path):
        assert b in adj[a]


def test_turn_cost_prefers_fewer_turns_among_equal_lengths() -> None:
    adj = grid_graph(4, 4)
    staircase_ok = shortest_cell_path(adj.__getitem__, (0, 0), (3, 3), start_heading=0, turn_cost=0.0)
    few_turns = shortest_cell_path(adj.__getitem__, (0, 0), (3, 3), start_heading=0, turn_cost=1.0)
    assert staircase_ok is not None and few_turns is not None
    assert len(staircase_ok) == len(few_turns) == 7
    assert len(merge_straight(few_turns)) == 3  # east along the bottom, then north: one turn
    assert merge_straight(few_turns)[1] == (3, 0)  # facing east, it keeps going east first


def test_unreachable_goal_gives_none() -> None:
    adj = grid_graph(2, 1, [((0, 0), (1, 0))])
    assert shortest_cell_path(adj.__getitem__, (0, 0), (1, 0)) is None
    assert shortest_cell_path(adj.__getitem__, (0, 0), (0, 0)) == [(0, 0)]


def test_cell_costs_count_steps_and_turns() -> None:
    adj = grid_graph(3, 2)
    costs = cell_costs(adj.__getitem__, (0, 0), start_heading=1, turn_cost=0.5)
    assert costs[(0, 0)] == 0.0
    assert costs[(0, 1)] == 1.0  # straight ahead (north)
    assert costs[(1, 0)] == 1.5  # a quarter turn to the east first
    assert costs[(2, 1)] == pytest.approx(3.5)  # north, turn, east, east
    free = cell_costs(adj.__getitem__, (0, 0))
    assert free[(2, 1)] == 3.0


def test_merge_straight_and_waypoints() -> None:
    cells = [(0, 0), (0, 1), (0, 2), (1, 2), (2, 2), (2, 1)]
    merged = merge_straight(cells)
    assert merged == [(0, 0), (0, 2), (2, 2), (2, 1)]
    points = cell_waypoints(merged, lambda c: (c[0] * 0.3 + 0.15, c[1] * 0.3 + 0.15))
    assert points[1] == pytest.approx((0.15, 0.75))
    assert merge_straight([(0, 0), (1, 0)]) == [(0, 0), (1, 0)]


def room_grid() -> tuple[np.ndarray, tuple[float, float], float]:
    """A 2 x 1.2 m room at 2 cm: walls around, a block in the middle, all known."""
    res = 0.02
    grid = np.zeros((60, 100), dtype=np.int8)
    grid[0, :] = grid[-1, :] = 100
    grid[:, 0] = grid[:, -1] = 100
    grid[15:45, 45:55] = 100  # a 0.2 x 0.6 m block: the way round is above or below it
    return grid, (0.0, 0.0), res


def test_grid_plan_keeps_the_inflated_distance_from_every_wall() -> None:
    grid, origin, res = room_grid()
    costmap = GridCostmap(grid, origin, res, footprint_radius_m=0.09, clearance_m=0.02)
    path = costmap.plan((0.3, 0.6), (1.7, 0.6))
    assert path is not None
    occupied = np.column_stack(np.nonzero(grid == 100))[:, ::-1] * res + res / 2  # (x, y) of occupied centres
    pts = np.array(path)
    d = np.min(np.hypot(pts[:, None, 0] - occupied[None, :, 0], pts[:, None, 1] - occupied[None, :, 1]), axis=1)
    assert d.min() > 0.11 - 1e-9
    length = float(np.sum(np.hypot(*np.diff(pts, axis=0).T)))
    assert 1.4 < length < 2.4  # around the block, not a detour round the room


def test_grid_plan_never_crosses_unknown_space() -> None:
    grid, origin, res = room_grid()
    grid[:, 30:35] = -1  # an unseen strip from wall to wall
    costmap = GridCostmap(grid, origin, res)
    assert costmap.plan((0.3, 0.6), (1.7, 0.6)) is None
    assert costmap.plan((0.3, 0.6), (0.3, 0.9)) is not None
    optimistic = GridCostmap(grid, origin, res, unknown_is_free=True)
    assert optimistic.plan((0.3, 0.6), (1.7, 0.6)) is not None


def test_shortcut_keeps_segments_passable_and_drops_the_staircase() -> None:
    grid, origin, res = room_grid()
    costmap = GridCostmap(grid, origin, res)
    path = costmap.plan((0.3, 0.25), (1.7, 0.95))
    assert path is not None
    short = shortcut(path, costmap)
    assert len(short) < len(path) / 5
    assert short[0] == path[0] and short[-1] == path[-1]
    for a, b in itertools.pairwise(short):
        assert costmap.segment_passable(a, b)


def test_distances_from_agree_with_the_planned_length() -> None:
    grid, origin, res = room_grid()
    costmap = GridCostmap(grid, origin, res, wall_cost=0.0)
    dist = costmap.distances_from((0.3, 0.6))
    assert np.isinf(dist[grid == 100]).all()
    r, c = costmap.to_cell(1.7, 0.6)
    path = costmap.plan((0.3, 0.6), (1.7, 0.6))
    assert path is not None
    planned = float(np.sum(np.hypot(*np.diff(np.array(path), axis=0).T))) / res
    assert dist[r, c] == pytest.approx(planned, rel=1e-6)
    # and every reachable cell lies in the free space connected to the start
    labels, _ = ndimage.label(costmap.passable)
    sr, sc = costmap.to_cell(0.3, 0.6)
    assert np.array_equal(np.isfinite(dist), labels == labels[sr, sc])


def test_start_next_to_a_wall_snaps_to_the_nearest_passable_cell() -> None:
    grid, origin, res = room_grid()
    costmap = GridCostmap(grid, origin, res)
    path = costmap.plan((0.05, 0.05), (1.7, 0.6))  # closer to the corner than the inflation
    assert path is not None
    assert math.dist(path[0], (0.05, 0.05)) < 0.15


def test_grid_plan_is_a_cheapest_chain_of_passable_neighbours() -> None:
    """With the wall cost on, the path's summed step costs are the Dijkstra cost to the goal."""
    grid, origin, res = room_grid()
    costmap = GridCostmap(grid, origin, res)
    path = costmap.plan((0.3, 0.25), (1.7, 0.95))
    assert path is not None
    cells = [costmap.to_cell(x, y) for x, y in path]
    cost = 0.0
    for (r0, c0), (r1, c1) in itertools.pairwise(cells):
        assert max(abs(r1 - r0), abs(c1 - c0)) == 1 and costmap.passable[r1, c1]
        if r1 != r0 and c1 != c0:  # a diagonal step never cuts a blocked corner
            assert costmap.passable[r0, c1] and costmap.passable[r1, c0]
        cost += math.hypot(r1 - r0, c1 - c0) * costmap.step_cost[r1, c1]
    r, c = cells[-1]
    assert cost == pytest.approx(costmap.distances_from((0.3, 0.25))[r, c], rel=1e-9)


def test_the_frontiers_wall_margin_is_scipys_dilation_by_the_cross() -> None:
    from mazebot.planner.frontiers import _dilate_4

    rng = np.random.default_rng(3)
    for iterations in (1, 2, 3):
        mask = rng.random((40, 53)) < 0.03
        mask[0, 5] = mask[39, 52] = True  # at the border
        assert np.array_equal(_dilate_4(mask, iterations), ndimage.binary_dilation(mask, iterations=iterations))


def _segment_passable_one_at_a_time(costmap: GridCostmap, a: tuple[float, float], b: tuple[float, float]) -> bool:
    """The line-of-sight check as it was written first: one segment, its samples by ``np.linspace``."""
    length = math.hypot(b[0] - a[0], b[1] - a[1])
    n = max(2, math.ceil(length / (0.5 * costmap.resolution_m)) + 1)
    t = np.linspace(0.0, 1.0, n)
    c = np.floor((a[0] + t * (b[0] - a[0]) - costmap.origin_m[0]) / costmap.resolution_m).astype(np.int64)
    r = np.floor((a[1] + t * (b[1] - a[1]) - costmap.origin_m[1]) / costmap.resolution_m).astype(np.int64)
    inside = (r >= 0) & (r < costmap.shape[0]) & (c >= 0) & (c < costmap.shape[1])
    return bool(inside.all() and costmap.passable[r, c].all())


def test_all_segments_at_once_answer_as_each_segment_alone() -> None:
    rng = np.random.default_rng(7)
    grid = np.full((60, 80), FREE, dtype=np.int8)
    grid[rng.random(grid.shape) < 0.01] = OCCUPIED
    grid[20, :50] = OCCUPIED
    costmap = GridCostmap(grid, (-0.3, 0.1), 0.02, footprint_radius_m=0.02, clearance_m=0.0)
    answers: list[bool] = []
    for _ in range(20):
        a = (float(rng.uniform(-0.4, 1.4)), float(rng.uniform(0.0, 1.4)))
        xs, ys = rng.uniform(-0.4, 1.4, 50), rng.uniform(0.0, 1.4, 50)
        ends = [(float(x), float(y)) for x, y in zip(xs, ys, strict=True)]
        ends.append(a)  # a zero-length segment
        expected = [_segment_passable_one_at_a_time(costmap, a, b) for b in ends]
        assert list(costmap.segments_passable(a, ends)) == expected
        answers += expected
    assert 0.1 < np.mean(answers) < 0.9  # both answers asked
