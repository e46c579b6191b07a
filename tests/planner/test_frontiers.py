"""Grid frontiers and their viewpoints on hand-made grids: what counts as seen, where the robot looks from."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from mazebot.planner.exploration import Explorer, Phase
from mazebot.planner.frontiers import (
    Frontier,
    SweptCells,
    best_viewpoint,
    find_frontiers,
    sees,
    viewpoint_candidates,
)
from mazebot.planner.global_path import GridCostmap
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raster import true_occupancy
from mazebot.sim.world import world_from_layout

RES = 0.02
MIN_RANGE_M = 0.15  # the A1M8's minimum range
FREE, WALL, UNSEEN = 0, 100, -1


def corridor_with_side_opening() -> np.ndarray:
    """A 1 ft corridor running east (rows 1-14 free, 2 cm cells), walled north and south, 2 m long.

    The robot has seen it all but a 30 cm opening in its north wall at x 1.0-1.3 m, whose
    other side is unknown: the frontier is the free cells under the opening.
    """
    grid = np.full((40, 100), UNSEEN, dtype=np.int8)
    grid[1:15, 1:99] = FREE
    grid[0, 0:100] = grid[15, 0:100] = WALL
    grid[:16, 0] = grid[:16, 99] = WALL
    grid[15, 50:65] = UNSEEN  # the opening: not seen through yet
    grid[16:, :] = UNSEEN
    return grid


def test_frontier_cells_are_free_cells_next_to_unknown_and_carry_the_unknown_they_touch() -> None:
    grid = corridor_with_side_opening()
    frontiers = find_frontiers(grid, min_cells=4, wall_margin_cells=2)
    assert len(frontiers) == 1
    f = frontiers[0]
    assert {tuple(c) for c in f.cells} <= {(14, c) for c in range(50, 65)}  # the free row under the opening
    assert all(grid[r, c] == FREE for r, c in f.cells)
    assert all(grid[r, c] == UNSEEN for r, c in f.unknown)
    # the unknown cells are the opening's, minus those within the wall margin of its posts
    assert {tuple(c) for c in f.unknown} == {(15, c) for c in range(52, 63)}
    assert f.cells.shape[0] == 11


def test_a_target_is_seen_through_free_cells_beyond_the_minimum_range_and_not_past_a_corner() -> None:
    free = np.ones((60, 60), dtype=bool)
    free[30, 0:30] = False  # a wall from the west edge to the middle, ending in a corner at (30, 29)
    targets = np.array([[40, 20], [20, 35], [40, 45]])
    viewpoint = np.array([[20, 25]])  # south of the wall
    seen = sees(free, viewpoint, targets, MIN_RANGE_M / RES + 1, 0.9 / RES)
    assert seen.tolist() == [[False, True, True]]  # north of the wall: hidden; same side; round the corner
    # the same targets from too close: within the lidar's minimum range nothing is seen
    close = sees(free, np.array([[20, 30]]), targets[1:2], MIN_RANGE_M / RES + 1, 0.9 / RES)
    assert not close.any()
    # a ray that passes the corner less than a cell off only grazes it: a digital line slips
    # past, the strip of free cells the lidar's beam needs does not
    grazing = (np.array([[20, 18]]), np.array([[40, 43]]))  # passes the wall end half a cell off
    assert sees(free, *grazing, MIN_RANGE_M / RES + 1, 0.9 / RES, half_width_cells=0.0).all()
    assert not sees(free, *grazing, MIN_RANGE_M / RES + 1, 0.9 / RES).any()


def test_a_line_of_no_width_sees_a_target_when_its_centre_line_is_free_up_to_it() -> None:
    """``half_width_cells=0``: every half-cell sample before the target on free space (or on the
    target's own cell), the target within range; checked sample by sample on random grids."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        free = rng.random((40, 40)) < 0.85
        viewpoints = rng.integers(0, 40, (3, 2))
        targets = rng.integers(-2, 42, (25, 2))  # some off the grid
        got = sees(free, viewpoints, targets, 3.0, 25.0, half_width_cells=0.0)
        for a, v in enumerate(viewpoints):
            for b, t in enumerate(targets):
                dist = math.hypot(*(t - v))
                steps = max(math.ceil(2.0 * dist), 1)
                clear = True
                for k in range(1, steps):
                    r, c = (int(np.rint(v[i] + k / steps * (t[i] - v[i]))) for i in (0, 1))
                    on_grid = 0 <= r < 40 and 0 <= c < 40
                    clear &= (on_grid and bool(free[r, c])) or (r, c) == tuple(t)
                assert got[a, b] == (3.0 <= dist <= 25.0 and clear), (v, t)


def test_the_viewpoint_of_a_side_opening_is_in_the_corridor_middle_and_beyond_the_minimum_range() -> None:
    grid = corridor_with_side_opening()
    costmap = GridCostmap(grid, (0.0, 0.0), RES, footprint_radius_m=0.09, clearance_m=0.02)
    robot = (0.1, 0.15)
    cost = np.where(costmap.passable, costmap.distances_from(robot), np.inf)
    assert np.isfinite(cost[7, 90])  # the inflation leaves a path down a 1 ft corridor
    (frontier,) = find_frontiers(grid)
    candidates = viewpoint_candidates(frontier, cost, RES, 0.9)
    view = best_viewpoint(frontier, candidates, grid == FREE, cost, RES, MIN_RANGE_M, 0.9, 0.3)
    assert view is not None
    r, c = view.cell
    assert costmap.passable[r, c]  # the robot fits there
    nearest_unknown_m = RES * float(np.hypot(*(frontier.unknown - np.array(view.cell)).T).min())
    assert nearest_unknown_m > MIN_RANGE_M  # the lidar can see the opening from there
    assert 30 <= c < 64  # ahead of the robot, short of the opening's far post: no detour past it
    assert view.gain >= 4  # a good part of the opening (11 cells) at once
    # the viewpoint from the robot's side costs what the path planner says
    assert view.cost_m == pytest.approx(cost[r, c] * RES)


def test_a_frontier_nothing_passable_can_see_has_no_viewpoint() -> None:
    # an unknown pocket at the end of a slot narrower than the robot, bent out of sight
    grid = np.full((40, 60), WALL, dtype=np.int8)
    grid[5:35, 5:30] = FREE  # a room the robot stands in
    grid[10:14, 30:50] = FREE  # an 8 cm slot going east ...
    grid[14:30, 46:50] = FREE  # ... and bending south
    grid[30:33, 46:50] = UNSEEN  # its end, unseen
    costmap = GridCostmap(grid, (0.0, 0.0), RES)
    cost = np.where(costmap.passable, costmap.distances_from((0.3, 0.4)), np.inf)
    # (a pocket this small counts only without the sliver rule: it is what this test is about)
    (frontier,) = find_frontiers(grid, min_cells=2, wall_margin_cells=0, sliver_cells=0)
    candidates = viewpoint_candidates(frontier, cost, RES, 0.9)
    assert candidates.shape[0] > 0  # places within range exist, in the room ...
    assert best_viewpoint(frontier, candidates, grid == FREE, cost, RES, MIN_RANGE_M, 0.9, 0.3) is None  # ... blind
    explorer = Explorer(start_xy_m=(0.3, 0.4), mode="frontier", min_frontier_cells=2, frontier_wall_margin_cells=0,
                        frontier_sliver_cells=0)
    goal = explorer.update(grid, (0.0, 0.0), RES, (0.3, 0.4, 0.0), revolutions=0)
    assert goal is not None and goal.phase in (Phase.RETURNING, Phase.DONE)  # nothing left it could look at


def test_viewpoints_trade_path_cost_against_the_unknown_they_see() -> None:
    free = np.ones((50, 50), dtype=bool)
    cost = np.full(free.shape, np.inf)
    cost[25, 5:45] = np.arange(40, dtype=float)  # a line of reachable cells, cost rising eastwards
    small = Frontier(np.array([[35, 10]]), np.array([[36, 10], [36, 11]]))  # near the cheap end, 2 cells
    big = Frontier(np.array([[35, 20]]), np.array([[36, c] for c in range(14, 27)]))  # 10 cells further, 13 cells
    views = {}
    for name, f in (("small", small), ("big", big)):
        cand = viewpoint_candidates(f, cost, RES, 0.9)
        views[name] = best_viewpoint(f, cand, free, cost, RES, MIN_RANGE_M, 0.9, gain_weight_m=0.3)
    assert views["small"] is not None and views["big"] is not None
    # score = cost - 0.3 m * ln(gain): 13 cells seen are worth 0.56 m more than 2, the detour is 0.2 m
    assert views["big"].score_m < views["small"].score_m
    for name in ("small", "big"):
        v = views[name]
        assert v is not None and v.score_m == pytest.approx(v.cost_m - 0.3 * math.log(v.gain))
    # valued by path cost alone, the nearer one wins
    near_only = best_viewpoint(small, viewpoint_candidates(small, cost, RES, 0.9), free, cost, RES, MIN_RANGE_M, 0.9, 0)
    assert near_only is not None and near_only.cost_m <= views["big"].cost_m


def test_every_cell_of_a_1ft_maze_is_reachable_for_the_inflated_robot() -> None:
    """The configured footprint (0.09 m) plus clearance (0.02 m) in 0.29 m of free corridor width."""
    world = world_from_layout(generate_maze(6, 6, 1, "braided"), 0.012)
    xmin, ymin, xmax, ymax = world.bounds_m
    origin = (math.floor((xmin - 0.2) / RES) * RES, math.floor((ymin - 0.2) / RES) * RES)
    shape = (math.ceil((ymax + 0.2 - origin[1]) / RES), math.ceil((xmax + 0.2 - origin[0]) / RES))
    occupied, _ = true_occupancy(world, RES, origin, shape)
    labels, _ = ndimage.label(~occupied)
    grid = np.full(shape, UNSEEN, dtype=np.int8)
    x0, y0, _ = world.start_pose
    grid[labels == labels[int((y0 - origin[1]) / RES), int((x0 - origin[0]) / RES)]] = FREE
    grid[occupied] = WALL
    costmap = GridCostmap(grid, origin, RES, footprint_radius_m=0.09, clearance_m=0.02)
    distances = costmap.distances_from((x0, y0))
    cell_m = 0.3048
    for col in range(6):
        for row in range(6):
            r, c = costmap.to_cell((col + 0.5) * cell_m, (row + 0.5) * cell_m)
            assert np.isfinite(distances[r, c]), (col, row)


def test_an_unpainted_stretch_of_wall_between_two_seen_corridors_is_no_frontier() -> None:
    # Two 1 ft corridors side by side, both driven: the wall between them was seen only at
    # grazing angles and 30 cm of it stayed unknown, with free space on both sides (a 16x16
    # maze's long corridors). Nothing is behind it: no frontier. The same stretch in the
    # outer wall, with the unseen outside behind it, still is one.
    grid = np.full((40, 100), UNSEEN, dtype=np.int8)
    grid[1:15, 1:99] = FREE  # corridor one
    grid[16:30, 1:99] = FREE  # corridor two
    grid[0, :] = grid[15, :] = grid[30, :] = WALL
    grid[:31, 0] = grid[:31, 99] = WALL
    grid[15, 40:55] = UNSEEN  # the unpainted stretch between the corridors: a sliver
    assert find_frontiers(grid) == []
    assert len(find_frontiers(grid, sliver_cells=0)) == 2  # without the rule: a frontier on each side of it
    grid[30, 40:55] = UNSEEN  # the same in the outer wall: the outside is behind it
    (frontier,) = find_frontiers(grid)
    assert set(frontier.cells[:, 0]) == {29}


def test_swept_cells_are_counted_where_the_lidar_sees_them_and_kept_when_the_grid_grows() -> None:
    # a 2 x 1 m room known free but a 6 x 6 patch (2 cm cells); the robot 0.5 m west of it
    grid = np.zeros((50, 100), dtype=np.int8)
    grid[[0, -1], :] = 100
    grid[:, [0, -1]] = 100
    grid[22:28, 50:56] = -1
    swept = SweptCells()
    for _ in range(3):
        assert swept.count(grid, (0.0, 0.0), 0.02, (0.5, 0.5), 0.15, 0.9) == 6  # the patch's west face
    mask = swept.swept_mask(grid.shape, (0.0, 0.0), 0.02, 3)
    assert mask[22:28, 50].all() and not mask[22:28, 52:56].any()  # the face and its neighbours, not beyond
    assert not swept.swept_mask(grid.shape, (0.0, 0.0), 0.02, 4).any()
    # within the lidar's minimum range nothing is seen; beyond the view radius neither
    assert swept.count(grid, (0.0, 0.0), 0.02, (0.95, 0.5), 0.15, 0.9) == 0
    assert swept.count(grid, (0.0, 0.0), 0.02, (0.05 + 0.02, 0.5), 0.15, 0.9) == 0
    # the grid grows by 10 cells west and 5 south: the same cells of the world keep their counts
    grown = np.zeros((55, 110), dtype=np.int8)
    grown[5:, 10:] = grid
    mask = swept.swept_mask(grown.shape, (-0.2, -0.1), 0.02, 3)
    assert mask[27:33, 60].all() and int(mask.sum()) == 3 * 8
