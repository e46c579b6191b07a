"""The map metrics of the benchmark against hand-made grids of a known world."""

from __future__ import annotations

import numpy as np

from mazebot.bench.metrics import map_metrics
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.world import world_from_layout
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
