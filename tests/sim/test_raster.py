"""Ground-truth rasters: walls where they are, free cell centres, areas, reachability."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.sim.maze_file import load_maze
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raster import free_reachable, true_occupancy
from mazebot.sim.room import make_room
from mazebot.sim.world import MazeLayout, World, rectangles_outline, world_from_layout
from tests.data_paths import MAZES, needs_mazes

CELL_M = 0.3048
WALL_M = 0.012


def _cell_index(x: float, y: float, origin: tuple[float, float], res: float) -> tuple[int, int]:
    return math.floor((y - origin[1]) / res), math.floor((x - origin[0]) / res)


def _expected_wall_area_m2(layout: MazeLayout, c: float, t: float) -> float:
    """Area of the union of wall rectangles, counted from the layout by hand.

    Each wall piece is a (c - t) x t slab between two posts; each post touched by at
    least one wall adds a t x t square.
    """
    h = np.zeros((layout.height + 1, layout.width), dtype=bool)  # horizontal, line j
    h[0] = layout.walls_south_edge
    h[1:] = layout.walls_north
    v = np.zeros((layout.height, layout.width + 1), dtype=bool)  # vertical, line i
    v[:, 0] = layout.walls_west_edge
    v[:, 1:] = layout.walls_east
    posts = np.zeros((layout.height + 1, layout.width + 1), dtype=bool)  # [j, i]
    posts[:, :-1] |= h
    posts[:, 1:] |= h
    posts[:-1, :] |= v
    posts[1:, :] |= v
    return float((h.sum() + v.sum()) * (c - t) * t + posts.sum() * t * t)


@pytest.fixture(scope="module")
def maze_world() -> World:
    return world_from_layout(generate_maze(8, 8, seed=11, kind="braided"), WALL_M)


def test_a_known_wall_is_occupied_at_every_resolution(maze_world: World) -> None:
    layout = maze_world.maze
    assert layout is not None
    for res in (0.002, 0.01, 0.05, 0.1):
        grid, origin = true_occupancy(maze_world, res)
        # the west boundary wall x in [-t/2, t/2]: a column of occupied cells, all rows
        col = math.floor((0.0 - origin[0]) / res)
        rows = [_cell_index(0.0, y, origin, res)[0] for y in np.arange(0.01, 8 * CELL_M, res)]
        assert grid[rows, col].all(), res
        # an inner wall: every wall piece's midpoint cell is occupied
        for row in range(layout.height):
            for c in range(layout.width - 1):
                x, y = (c + 1) * CELL_M, (row + 0.5) * CELL_M
                r, k = _cell_index(x, y, origin, res)
                assert grid[r, k] == layout.walls_east[row, c] or res >= 0.05, (res, row, c)
                if layout.walls_east[row, c]:
                    assert grid[r, k], (res, row, c)


def test_maze_cell_centres_are_free(maze_world: World) -> None:
    layout = maze_world.maze
    assert layout is not None
    for res in (0.005, 0.02, 0.05):
        grid, origin = true_occupancy(maze_world, res)
        for row in range(layout.height):
            for col in range(layout.width):
                r, k = _cell_index(*layout.cell_center_m((col, row)), origin, res)
                assert not grid[r, k]


@needs_mazes
@pytest.mark.parametrize("name", ["classic/japan2013ef.txt", "training/minimaze.txt"])
def test_occupied_area_matches_wall_area(name: str) -> None:
    world = load_maze(MAZES / name, wall_thickness_m=WALL_M)
    assert world.maze is not None
    expected = _expected_wall_area_m2(world.maze, CELL_M, WALL_M)
    res = 0.002
    centre, _ = true_occupancy(world, res, rule="centre")
    touch, _ = true_occupancy(world, res)
    assert centre.sum() * res * res == pytest.approx(expected, rel=0.02)
    # touching cells add about half a cell on each side of every wall
    assert expected < touch.sum() * res * res < expected * (1 + 1.5 * res / WALL_M)
    assert (touch | centre).sum() == touch.sum()  # centre-covered cells are touched too


def test_thin_walls_survive_coarse_resolution_only_with_the_touch_rule(maze_world: World) -> None:
    touch, _ = true_occupancy(maze_world, 0.05)
    centre, _ = true_occupancy(maze_world, 0.05, rule="centre")
    assert centre.sum() < touch.sum() / 3
    with pytest.raises(ValueError, match="rule"):
        true_occupancy(maze_world, 0.05, rule="edge")  # type: ignore[arg-type]


def test_window_matches_the_full_grid(maze_world: World) -> None:
    res = 0.01
    full, origin = true_occupancy(maze_world, res)
    window_origin = (origin[0] + 37 * res, origin[1] + 12 * res)
    window, got_origin = true_occupancy(maze_world, res, origin_m=window_origin, shape=(50, 80))
    assert got_origin == window_origin
    assert window.shape == (50, 80)
    np.testing.assert_array_equal(window, full[12:62, 37:117])
    # a window reaching beyond the world is free there
    beyond, _ = true_occupancy(maze_world, res, origin_m=(-1.0, -1.0), shape=(50, 50))
    assert not beyond[:40, :40].any()


def test_cylinders_are_occupied_with_their_area() -> None:
    room = make_room(cylinders=4, cylinder_diameter_m=0.08, seed=3)
    res = 0.002
    centre, origin = true_occupancy(room, res, rule="centre")
    touch, _ = true_occupancy(room, res)
    wall_area = (2.0 + 2 * WALL_M) * (1.2 + 2 * WALL_M) - 2.0 * 1.2
    cylinder_area = 4 * math.pi * 0.04**2
    assert centre.sum() * res * res == pytest.approx(wall_area + cylinder_area, rel=0.02)
    for cx, cy, radius in room.circles:
        assert touch[_cell_index(cx, cy, origin, res)]
        assert touch[_cell_index(cx + radius * 0.99, cy, origin, res)]
        assert not touch[_cell_index(cx + radius + 2 * res, cy, origin, res)]


def test_free_reachable_covers_the_maze_and_nothing_else(maze_world: World) -> None:
    layout = maze_world.maze
    assert layout is not None
    res = 0.01
    reach, origin = free_reachable(maze_world, res, footprint_radius_m=0.09)
    occupied, _ = true_occupancy(maze_world, res)
    assert not (reach & occupied).any()
    for row in range(layout.height):
        for col in range(layout.width):
            assert reach[_cell_index(*layout.cell_center_m((col, row)), origin, res)]
    # every free cell of a closed maze is visible from somewhere the robot can go,
    # except a few grid cells right at the boundary of the raster
    free = ~occupied
    assert reach.sum() >= 0.99 * free[1:-1, 1:-1].sum()


@needs_mazes
def test_free_reachable_stops_at_walls() -> None:
    # minimaze: a walled 5x5 maze in the corner of an open 16x16 frame
    world = load_maze(MAZES / "training" / "minimaze.txt")
    res = 0.01
    reach, origin = free_reachable(world, res, footprint_radius_m=0.09)
    inside = 5 * CELL_M
    assert reach[_cell_index(0.5 * CELL_M, 4.5 * CELL_M, origin, res)]
    assert not reach[_cell_index(8 * CELL_M, 8 * CELL_M, origin, res)]
    ys, xs = np.nonzero(reach)
    assert origin[0] + (xs.max() + 1) * res <= inside
    assert origin[1] + (ys.max() + 1) * res <= inside


def test_free_reachable_keeps_narrow_gaps_shut() -> None:
    # two 1 m x 1 m rooms side by side; the wall between them has a gap of width `gap`
    t = 0.02

    def two_rooms(gap: float) -> World:
        walls = [
            (-t, -t, 2 + 2 * t, 0),
            (-t, 1, 2 + 2 * t, 1 + t),
            (-t, -t, 0, 1 + t),
            (2 + t, -t, 2 + 2 * t, 1 + t),
            (1, 0, 1 + t, 0.5 - gap / 2),
            (1, 0.5 + gap / 2, 1 + t, 1),
        ]
        return World(
            name=f"two-rooms-{gap}",
            segments=rectangles_outline(np.array(walls)),
            circles=np.zeros((0, 3)),
            start_pose=(0.5, 0.5, 0.0),
            bounds_m=(-t, -t, 2 + 2 * t, 1 + t),
        )

    res = 0.01
    narrow, origin = free_reachable(two_rooms(0.15), res, footprint_radius_m=0.09)
    wide, _ = free_reachable(two_rooms(0.25), res, footprint_radius_m=0.09)
    far_side = _cell_index(1.5, 0.5, origin, res)
    assert not narrow[far_side]
    assert wide[far_side]
    assert narrow.sum() * res * res == pytest.approx(1.0, rel=0.08)
    assert wide.sum() * res * res == pytest.approx(2.0, rel=0.08)


def test_room_floor_is_reachable_around_cylinders() -> None:
    room = make_room(cylinders=4, seed=0)
    res = 0.01
    reach, _ = free_reachable(room, res, footprint_radius_m=0.1)
    floor = 2.0 * 1.2 - 4 * math.pi * 0.04**2
    assert reach.sum() * res * res == pytest.approx(floor, rel=0.03)


def test_start_in_collision_is_an_error(maze_world: World) -> None:
    with pytest.raises(ValueError, match="cannot be put down"):
        free_reachable(maze_world, 0.01, footprint_radius_m=0.2)


def test_room_cylinders_leave_robot_sized_passages() -> None:
    for seed in range(5):
        room = make_room(width_m=2.0, height_m=1.2, cylinders=4, seed=seed, footprint_radius_m=0.1)
        c = room.circles
        assert c.shape == (4, 3)
        gaps = np.hypot(c[:, None, 0] - c[None, :, 0], c[:, None, 1] - c[None, :, 1])
        gaps = gaps - c[:, None, 2] - c[None, :, 2]
        assert gaps[~np.eye(4, dtype=bool)].min() >= 0.2
        wall_gap = np.minimum.reduce(
            [c[:, 0] - c[:, 2], 2.0 - c[:, 0] - c[:, 2], c[:, 1] - c[:, 2], 1.2 - c[:, 1] - c[:, 2]]
        )
        assert wall_gap.min() >= 0.2
        x, y, _ = room.start_pose
        assert x < 0.5 and y < 0.5  # near the south-west corner
        np.testing.assert_array_equal(c, make_room(seed=seed).circles)  # seeded
    with pytest.raises(ValueError, match="could place only"):
        make_room(width_m=1.0, height_m=1.0, cylinders=10)
