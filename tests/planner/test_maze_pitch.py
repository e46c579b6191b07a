"""The maze graph measures the pitch of a maze built by hand, instead of assuming the configured one."""

from __future__ import annotations

import math

import pytest

from mazebot.planner.maze_graph import Direction, LinkState, MazeGraph, estimate_frame
from mazebot.sim.hand_maze import HandBuild, hand_built_world
from mazebot.sim.maze_generator import generate_maze
from tests.planner.test_maze_graph import CELL, RES, perfect_map


@pytest.mark.parametrize(("pitch_m", "angle_deg", "seed"), [(0.29, 17.0, 1), (0.32, 17.0, 2), (0.3048, 61.0, 3)])
def test_the_pitch_and_angle_are_measured_not_assumed(pitch_m: float, angle_deg: float, seed: int) -> None:
    layout = generate_maze(6, 6, seed, kind="braided", cell_size_m=pitch_m)
    build = HandBuild(pitch_error_max=0.0, maze_angle_rad=math.radians(angle_deg), clutter=0)
    world = hand_built_world(layout, build, seed)
    grid, origin = perfect_map(world)
    estimate = estimate_frame(grid, origin, RES, CELL, anchor_xy_m=world.start_pose[:2], pitch_search=0.08)
    assert estimate is not None
    # the true mean pitch: the least-squares slope of the jittered rows of posts
    assert estimate.frame.cell_size_m == pytest.approx(world.maze.cell_size_m, abs=0.002)
    assert abs(math.degrees(math.remainder(estimate.frame.angle_rad - math.radians(angle_deg), math.pi / 2))) < 0.3
    assert estimate.fit > 0.95
    # the graph on it is the maze: every link of every cell as built
    graph = MazeGraph(cell_size_m=CELL, anchor_xy_m=world.start_pose[:2], pitch_search=0.08)
    graph.update(grid, origin, RES)
    assert graph.cell_size_m == pytest.approx(world.maze.cell_size_m, abs=0.002)
    # cell (0, 0) holds the start; the maze's axes may come out turned by a multiple of 90 degrees
    found = {graph.frame.cell_of(*world.maze.cell_center_m((c, r))): (c, r)
             for c in range(6) for r in range(6)}
    assert len(found) == 36 and found[(0, 0)] == (0, 0)
    walls = sum(graph.link(cell, d) is LinkState.WALL for cell in found for d in Direction)
    opens = sum(graph.link(cell, d) is LinkState.OPEN for cell in found for d in Direction)
    assert walls + opens == 36 * 4
    assert walls == sum(layout.has_wall(cell, side) for cell in found.values() for side in "NESW")


def test_without_the_search_a_wrong_pitch_does_not_fit() -> None:
    layout = generate_maze(6, 6, 1, kind="braided", cell_size_m=0.29)
    world = hand_built_world(layout, HandBuild(pitch_error_max=0.0, maze_angle_rad=0.3, clutter=0), 1)
    grid, origin = perfect_map(world)
    assumed = estimate_frame(grid, origin, RES, CELL, anchor_xy_m=world.start_pose[:2])
    measured = estimate_frame(grid, origin, RES, CELL, anchor_xy_m=world.start_pose[:2], pitch_search=0.08)
    assert assumed is not None and measured is not None
    assert assumed.fit < 0.9 < 0.95 < measured.fit


SEARCH = 0.08  # [planner] cell_size_search


@pytest.mark.parametrize(("pitch_m", "mode"), [(0.29, "maze"), (0.32, "maze"), (0.40, "frontier")])
def test_where_the_cell_graph_does_not_fit_exploration_falls_back_to_grid_frontiers(pitch_m: float, mode: str) -> None:
    """A maze a few per cent off the configured pitch is still a cell maze; one 30 % off is not (nor a room)."""
    from mazebot.planner.exploration import Explorer
    from tests.planner.test_exploration import known_map, revs

    layout = generate_maze(6, 6, 4, kind="braided", cell_size_m=pitch_m)
    world = hand_built_world(layout, HandBuild(pitch_error_max=0.0, maze_angle_rad=0.4, clutter=0), 4)
    grid, origin = known_map(world)
    explorer = Explorer(MazeGraph(cell_size_m=CELL, anchor_xy_m=world.start_pose[:2], pitch_search=SEARCH),
                        start_xy_m=world.start_pose[:2])
    explorer.update(grid, origin, RES, world.start_pose, revolutions=revs(0.0))
    assert explorer.mode == mode


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_a_room_is_no_maze_whatever_pitch_is_looked_for(seed: int) -> None:
    from mazebot.planner.exploration import Explorer
    from mazebot.sim.room import make_room
    from tests.planner.test_exploration import known_map, revs

    room = make_room(2.0, 1.2, cylinders=4, seed=seed, footprint_radius_m=0.09)
    grid, origin = known_map(room)
    explorer = Explorer(MazeGraph(cell_size_m=CELL, anchor_xy_m=room.start_pose[:2], pitch_search=SEARCH),
                        start_xy_m=room.start_pose[:2])
    explorer.update(grid, origin, RES, room.start_pose, revolutions=revs(0.0))
    assert explorer.mode == "frontier"
    assert explorer.graph.cell_size_m == CELL  # two walls a side measure no pitch: the configured one stands
