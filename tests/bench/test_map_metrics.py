"""The map metrics of the benchmark against hand-made grids of a known world."""

from __future__ import annotations

import numpy as np

from mazebot.bench.metrics import map_metrics
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.world import World, world_from_layout
from mazebot.slam.grid import OccupancyGrid

RES_M = 0.02


def test_a_wall_cell_whose_centre_lies_outside_the_world_is_still_on_the_outer_wall() -> None:
    """Hits on the outer wall, 1 mm inside its outer face, in a map whose cells straddle that face:
    the occupied cells' centres lie 7 mm outside the world's bounds, within the one-cell tolerance
    of the wall, so precision is 1 (a truth raster ending at the bounds called them false)."""
    world = world_from_layout(generate_maze(2, 2, seed=1), 0.012)
    xmin, ymin, _, ymax = world.bounds_m
    start = (xmin + 0.003, 0.0, 0.0)  # the map frame: a cell edge 3 mm inside the outer face
    grid = OccupancyGrid(resolution_m=RES_M, occupied_prob=0.75)
    ys = np.linspace(ymin + 0.05, ymax - 0.05, 40)
    hits_world = np.column_stack((np.full_like(ys, xmin + 0.001), ys))
    sensor_world = np.array([xmin + 0.15, 0.5 * (ymin + ymax)])
    to_map = np.array(start[:2])
    for _ in range(3):
        grid.integrate(sensor_world - to_map, hits_world - to_map, np.ones(len(ys), dtype=bool))
    rows, cols = np.nonzero(grid.occupied_mask())
    centres_world = grid.to_world(rows, cols) + to_map
    assert len(rows) > 0 and np.all(centres_world[:, 0] < xmin)  # the case this test is about
    scores = map_metrics(grid, world, start, footprint_radius_m=0.09)
    assert scores["map_precision"] == 1.0, scores


def _map_of(world: World, start: tuple[float, float, float], clearance_m: float) -> OccupancyGrid:
    """A map of ``world`` in the frame of ``start``: occupied within ``clearance_m`` of a wall, free elsewhere
    inside the world's bounds, unknown outside."""
    from mazebot.bench.metrics import map_to_world
    from mazebot.sim.raycast import distance_to_obstacles

    xmin, ymin, xmax, ymax = world.bounds_m
    corners = np.array([[xmin, ymin], [xmin, ymax], [xmax, ymin], [xmax, ymax]]) - np.array(start[:2])
    c, s = np.cos(start[2]), np.sin(start[2])
    local = corners @ np.array([[c, -s], [s, c]])  # the corners in the map frame
    lo = np.floor(local.min(axis=0) / RES_M).astype(int) - 2
    hi = np.ceil(local.max(axis=0) / RES_M).astype(int) + 2
    cols, rows = np.meshgrid(np.arange(lo[0], hi[0]), np.arange(lo[1], hi[1]))
    centres = np.column_stack(((cols.ravel() + 0.5) * RES_M, (rows.ravel() + 0.5) * RES_M))
    world_xy = map_to_world(start, centres)
    inside = ((world_xy[:, 0] > xmin) & (world_xy[:, 0] < xmax) & (world_xy[:, 1] > ymin) & (world_xy[:, 1] < ymax))
    wall = distance_to_obstacles(world_xy, world) < clearance_m
    log_odds = np.where(wall, 3.0, np.where(inside, -3.0, 0.0)).reshape(rows.shape)
    like = OccupancyGrid(resolution_m=RES_M, occupied_prob=0.75)
    return like.holding(log_odds.astype(np.float32), (int(lo[0]), int(lo[1])), (0.0, 0.0))


def test_the_free_space_the_coverage_misses_is_told_apart_on_walls_and_unknown() -> None:
    """A map of a 3x3 maze, then the same map with a quarter of it unknown, then with its walls painted
    a cell thicker: the misses move to ``uncovered_unknown`` and ``uncovered_occupied`` respectively,
    and the three shares add up to 1 every time (main's map metrics had only the coverage)."""
    world = world_from_layout(generate_maze(3, 3, seed=1), 0.012)
    start = world.start_pose
    clean = map_metrics(_map_of(world, start, 0.008), world, start, footprint_radius_m=0.09)
    thick = map_metrics(_map_of(world, start, 0.035), world, start, footprint_radius_m=0.09)
    grid = _map_of(world, start, 0.008)
    half_rows, half_cols = grid.shape[0] // 2, grid.shape[1] // 2
    part = grid.log_odds[half_rows:, half_cols:]
    part[part < 0] = 0.0  # the free space of a quarter of the map never seen
    unseen = map_metrics(grid, world, start, footprint_radius_m=0.09)
    for scores in (clean, thick, unseen):
        total = scores["coverage"] + scores["uncovered_occupied"] + scores["uncovered_unknown"]
        assert abs(total - 1.0) < 3e-4, scores
    assert clean["coverage"] > 0.97 and clean["uncovered_unknown"] < 0.01, clean
    assert unseen["uncovered_unknown"] > 0.15, unseen
    assert abs(unseen["uncovered_occupied"] - clean["uncovered_occupied"]) < 1e-3, (unseen, clean)
    assert thick["uncovered_occupied"] > clean["uncovered_occupied"] + 0.05, (thick, clean)
    assert abs(thick["uncovered_unknown"] - clean["uncovered_unknown"]) < 1e-3, (thick, clean)


def test_an_estimate_turned_about_the_start_is_told_from_errors_of_its_own() -> None:
    """A trajectory 3 m out and back, its estimate turned 0.6° about the start with 2 mm of noise: the
    turn comes out within 0.01° and the RMS left is the noise's; an estimate with 15 mm of noise and no
    turn: no turn to speak of, the RMS left is the whole error."""
    from mazebot.bench.metrics import turn_about_start

    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 1.0, 400)
    true_xy = np.column_stack((2.0 * np.sin(np.pi * t), 1.5 * np.sin(2 * np.pi * t)))
    a = np.radians(0.6)
    turned = true_xy @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    result = turn_about_start(turned + rng.normal(0.0, 0.002, true_xy.shape), true_xy)
    assert result is not None
    turn, left_m = result
    assert abs(np.degrees(turn) - 0.6) < 0.01
    assert 0.0022 < left_m < 0.0035  # sqrt(2) * 2 mm
    result = turn_about_start(true_xy + rng.normal(0.0, 0.015, true_xy.shape), true_xy)
    assert result is not None
    assert abs(np.degrees(result[0])) < 0.05 and 0.019 < result[1] < 0.023
    assert turn_about_start(np.zeros((0, 2)), np.zeros((0, 2))) is None
