"""The lost-robot guard on a board the map once marked and then wore free, against the board's true place."""

from __future__ import annotations

import numpy as np

from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.relocalize import scan_fit

WALL_X_M = 1.01  # a board's face, the middle of a 2 cm cell's column
WALL_Y_M = np.linspace(-0.4, 0.4, 41)  # the board's true points, 2 cm apart


def _room() -> OccupancyGrid:
    """A grid holding free space west of the board and the board itself, seen from 0.2 m (near beams)."""
    grid = OccupancyGrid(resolution_m=0.02)
    near = np.column_stack((np.full(WALL_Y_M.size, WALL_X_M), WALL_Y_M))
    for _ in range(8):  # marked to the clamp from close by
        grid.integrate(np.array([0.81, 0.0]), near, np.ones(WALL_Y_M.size, dtype=bool))
    # free space around the robot's corridor: no-return beams fanning out west of the board
    angles = np.linspace(np.pi / 2, 3 * np.pi / 2, 181)
    far = np.column_stack((0.81 + 0.7 * np.cos(angles), 0.7 * np.sin(angles)))
    for _ in range(8):
        grid.integrate(np.array([0.81, 0.0]), far, np.zeros(angles.size, dtype=bool))
    return grid


def _wear_away(grid: OccupancyGrid) -> None:
    """Beams from far south running along the board's own column of cells, returning nothing: each
    crosses every cell of the board (the grazing beams that wore the real board free)."""
    xs = WALL_X_M + np.linspace(-0.03, 0.03, 7)  # along the board and the cells each side of it
    starts = np.column_stack((xs, np.full(xs.size, -1.5)))
    ends = np.column_stack((xs, np.full(xs.size, 2.0)))
    for _ in range(30):
        grid.integrate(starts[0], ends, np.zeros(xs.size, dtype=bool), starts)


def test_hits_on_a_board_the_map_wore_free_are_no_evidence_of_being_lost() -> None:
    grid = _room()
    _wear_away(grid)
    rows, cols = grid.to_cell(np.column_stack((np.full(WALL_Y_M.size, WALL_X_M), WALL_Y_M)))
    assert (grid.log_odds[rows, cols] < grid.free_logodds).all()  # the map holds the board free now
    board = np.column_stack((np.full(WALL_Y_M.size, WALL_X_M), WALL_Y_M))  # where the lidar sees it, truly
    fit = scan_fit(grid, board)
    assert fit.known >= 30
    assert fit.contradiction <= 0.10  # the guard's max_contradiction: not lost


def test_hits_on_corridor_cells_never_marked_still_contradict_the_map() -> None:
    """A kidnapped robot's hits, seen from the wrong pose, fall in the middle of the free corridor."""
    grid = _room()
    _wear_away(grid)
    corridor = np.column_stack((np.full(21, 0.6), np.linspace(-0.3, 0.3, 21)))
    corridor = np.vstack((corridor, corridor + np.array([0.1, 0.0])))
    fit = scan_fit(grid, corridor)
    assert fit.known == corridor.shape[0]
    assert fit.contradiction > 0.9


def test_the_memory_of_a_board_moves_with_the_grid_when_it_grows() -> None:
    grid = _room()
    _wear_away(grid)
    grid.integrate(np.array([0.81, 0.0]), np.array([[6.0, 5.0]]), np.array([False]))  # a beam past the edge: regrown
    board = np.column_stack((np.full(WALL_Y_M.size, WALL_X_M), WALL_Y_M))
    rows, cols = grid.to_cell(board)
    assert grid.ever_occupied[rows, cols].all()
    assert scan_fit(grid, board).contradiction <= 0.10
