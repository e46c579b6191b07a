"""The maze graph builder on hand-made maps: frame, links, cell kinds, incremental updates.

Maps are drawn as micromouse text, turned into walls by the simulator and rasterised at
2 cm (a perfect map); everything outside the maze, or hidden on purpose, is unknown.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from mazebot.planner.maze_graph import (
    CellKind,
    Direction,
    LinkState,
    MazeFrame,
    MazeGraph,
    estimate_frame,
)
from mazebot.sim.maze_file import parse_maze
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raster import true_occupancy
from mazebot.sim.raycast import distance_to_segments
from mazebot.sim.room import make_room
from mazebot.sim.world import MazeLayout, World, world_from_layout
from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN

RES = 0.02
CELL = 0.3048

# 3 x 2 cells, row 0 south. Cell (0,0) is the start, a dead end open to the north;
# (0,1)-(1,1)-(2,1) a corridor along the top, (2,1)-(2,0) down into a dead end; (1,0) is
# closed on all sides.
SMALL = """
o---o---o---o
|           |
o   o---o   o
| S |   |   |
o---o---o---o
"""

# 3 x 3 with an open 2 x 2 room in the north-east and a junction at (1, 1).
ROOM = """
o---o---o---o
|   |       |
o   o   o   o
|           |
o   o---o   o
| S |       |
o---o---o---o
"""


def rotate_world(world: World, angle_rad: float, shift_m: tuple[float, float]) -> World:
    """The same world turned by ``angle_rad`` about the origin and moved by ``shift_m``."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)

    def tf(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return c * x - s * y + shift_m[0], s * x + c * y + shift_m[1]

    seg = world.segments
    ax, ay = tf(seg[:, 0], seg[:, 1])
    bx, by = tf(seg[:, 2], seg[:, 3])
    sx, sy = tf(np.array(world.start_pose[0]), np.array(world.start_pose[1]))
    xs, ys = np.concatenate((ax, bx)), np.concatenate((ay, by))
    return World(
        world.name,
        np.column_stack((ax, ay, bx, by)),
        world.circles,
        (float(sx), float(sy), world.start_pose[2] + angle_rad),
        (float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())),
        world.maze,
    )


def perfect_map(world: World, margin_m: float = 0.3) -> tuple[np.ndarray, tuple[float, float]]:
    """Three-state raster of a world: walls occupied, inside free, outside the walls unknown."""
    xmin, ymin, _, _ = world.bounds_m
    origin = (math.floor((xmin - margin_m) / RES) * RES, math.floor((ymin - margin_m) / RES) * RES)
    xmax, ymax = world.bounds_m[2] + margin_m, world.bounds_m[3] + margin_m
    shape = (math.ceil((ymax - origin[1]) / RES), math.ceil((xmax - origin[0]) / RES))
    occupied, _ = true_occupancy(world, RES, origin, shape)
    # free = the connected free space around the start; the rest (outside the maze) unknown
    labels, _ = ndimage.label(~occupied)
    x0, y0, _ = world.start_pose
    start_label = labels[int((y0 - origin[1]) / RES), int((x0 - origin[0]) / RES)]
    grid = np.full(shape, -1, dtype=np.int8)
    grid[labels == start_label] = 0
    grid[occupied] = 100
    return grid, origin


def layout_world(text: str) -> tuple[MazeLayout, World]:
    layout = parse_maze(text, CELL)
    return layout, world_from_layout(layout, 0.012)


def assert_links_match(graph: MazeGraph, layout: MazeLayout) -> None:
    for col in range(layout.width):
        for row in range(layout.height):
            for side, direction in zip("ENWS", (Direction.E, Direction.N, Direction.W, Direction.S), strict=True):
                want = LinkState.WALL if layout.has_wall((col, row), side) else LinkState.OPEN
                assert graph.link((col, row), direction) is want, f"cell {(col, row)} side {side}"


def test_links_and_kinds_of_a_hand_made_maze() -> None:
    layout, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    graph.update(grid, origin, RES)

    assert graph.ready and graph.fit > 0.99
    assert_links_match(graph, layout)
    assert graph.open_neighbours((0, 0)) == [(0, 1)]
    assert sorted(graph.open_neighbours((1, 1))) == [(0, 1), (2, 1)]
    assert graph.kind((0, 0)) is CellKind.DEAD_END
    assert graph.kind((2, 0)) is CellKind.DEAD_END
    assert graph.kind((1, 1)) is CellKind.CORRIDOR
    assert graph.kind((0, 1)) is CellKind.CORRIDOR  # a corner is a corridor
    assert graph.kind((2, 1)) is CellKind.CORRIDOR
    assert graph.reachable((0, 0)) == {(0, 0), (0, 1), (1, 1), (2, 1), (2, 0)}  # (1, 0) is sealed
    # the sealed cell was never looked into: its inside is unknown, so it is not explored
    assert graph.kind((1, 0)) is CellKind.UNEXPLORED
    assert graph.frontier_links((0, 0)) == []  # nothing reachable is left to see


def test_cell_centres_are_the_waypoints() -> None:
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    graph.update(grid, origin, RES)
    assert graph.frame is not None
    for col, row in ((0, 0), (2, 1), (1, 1)):
        x, y = graph.frame.cell_center_m((col, row))
        assert x == pytest.approx((col + 0.5) * CELL, abs=0.01)
        assert y == pytest.approx((row + 0.5) * CELL, abs=0.01)


def test_open_areas_and_junctions() -> None:
    layout, world = layout_world(ROOM)
    grid, origin = perfect_map(world)
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    graph.update(grid, origin, RES)
    assert_links_match(graph, layout)
    for cell in ((1, 1), (2, 1), (1, 2), (2, 2)):
        assert graph.kind(cell) is CellKind.OPEN_AREA
    assert graph.kind((0, 1)) is CellKind.JUNCTION  # open N, E, S
    assert graph.kind((0, 0)) is CellKind.DEAD_END
    assert graph.kind((0, 2)) is CellKind.DEAD_END


def test_unknown_parts_of_the_map_give_unknown_links_never_guesses() -> None:
    layout, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    hidden = grid.copy()
    # hide everything east of x = 1.5 cells (the middle of column 1)
    cut = int((1.5 * CELL - origin[0]) / RES)
    hidden[:, cut:] = -1
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    graph.update(hidden, origin, RES)
    assert graph.link((0, 0), Direction.N) is LinkState.OPEN
    assert graph.link((0, 1), Direction.E) is LinkState.OPEN
    for cell, direction in (((1, 1), Direction.E), ((2, 1), Direction.S), ((2, 1), Direction.E)):
        assert graph.link(cell, direction) is LinkState.UNKNOWN
    assert graph.kind((1, 1)) is CellKind.UNEXPLORED
    assert ((1, 1), Direction.E) in graph.frontier_links((0, 0))
    for cell, direction, state in graph.links():  # whatever is known agrees with the truth
        if state is LinkState.UNKNOWN or not layout.contains(cell):
            continue
        side = "E" if direction is Direction.E else "N"
        if not layout.contains((cell[0] + direction.step[0], cell[1] + direction.step[1])):
            continue
        assert (state is LinkState.WALL) == layout.has_wall(cell, side), (cell, side)


def test_incremental_update_reports_what_changed() -> None:
    layout, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    partial = grid.copy()
    cut = int((1.5 * CELL - origin[0]) / RES)
    partial[:, cut:] = -1
    graph.update(partial, origin, RES)
    before = {(cell, d): s for cell, d, s in graph.links()}

    update = graph.update(grid, origin, RES)
    changed = {(cell, d): s for cell, d, s in update.changed_links}
    assert changed  # the east half appeared
    assert changed[((1, 1), Direction.E)] is LinkState.OPEN
    assert changed[((2, 0), Direction.N)] is LinkState.OPEN
    for (cell, d), state in changed.items():
        assert before.get((cell, d), LinkState.UNKNOWN) is not state
    assert graph.update(grid, origin, RES).changed_links == []  # nothing new: nothing reported
    assert_links_match(graph, layout)


@pytest.mark.parametrize("angle_deg", [0.0, 7.0, 17.3, -30.0, 44.0, -12.5])
def test_a_maze_placed_at_an_angle(angle_deg: float) -> None:
    layout = generate_maze(6, 6, seed=int(abs(angle_deg) * 10) % 97, kind="braided")
    world = rotate_world(world_from_layout(layout, 0.012), math.radians(angle_deg), (0.37, -0.21))
    grid, origin = perfect_map(world)
    estimate = estimate_frame(grid, origin, RES, CELL, anchor_xy_m=world.start_pose[:2])
    assert estimate is not None
    error_deg = math.degrees(math.remainder(estimate.frame.angle_rad - math.radians(angle_deg), math.pi / 2))
    assert abs(error_deg) < 0.2
    assert estimate.fit > 0.99
    # every cell centre within 1 cm of the truth, including the far corner
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    for cell in ((0, 0), (5, 5), (5, 0), (0, 5)):
        tx, ty = (cell[0] + 0.5) * CELL, (cell[1] + 0.5) * CELL
        truth = (c * tx - s * ty + 0.37, s * tx + c * ty - 0.21)
        found = estimate.frame.cell_center_m(estimate.frame.cell_of(*truth))
        assert math.dist(found, truth) < 0.01
    if angle_deg == 17.3:  # and the graph built on it is the maze
        graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
        graph.update(grid, origin, RES)
        assert graph.frame is not None and graph.frame.cell_of(*world.start_pose[:2]) == (0, 0)
        assert_links_match(graph, layout)


def test_a_room_with_cylinders_does_not_fit_a_lattice() -> None:
    room = make_room(2.0, 1.2, cylinders=4, seed=0, footprint_radius_m=0.09)
    grid, origin = perfect_map(room)
    room_fit = estimate_frame(grid, origin, RES, CELL, room.start_pose[:2])
    maze = world_from_layout(generate_maze(6, 6, 1, "rooms"), 0.012)
    grid, origin = perfect_map(maze)
    maze_fit = estimate_frame(grid, origin, RES, CELL, maze.start_pose[:2])
    assert room_fit is not None and maze_fit is not None
    assert room_fit.fit < 0.9 < 0.99 < maze_fit.fit


def test_no_frame_without_walls() -> None:
    grid = np.zeros((50, 50), dtype=np.int8)
    graph = MazeGraph()
    update = graph.update(grid, (0.0, 0.0), RES)
    assert not graph.ready and update.changed_links == []
    assert estimate_frame(grid, (0.0, 0.0), RES) is None


def test_a_fixed_frame_is_kept() -> None:
    layout, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    frame = MazeFrame(0.0, (0.0, 0.0), CELL)
    graph = MazeGraph(frame=frame)
    assert graph.update(grid, origin, RES).frame_changed is False
    assert graph.frame is frame
    assert_links_match(graph, layout)


def test_frame_round_trip_and_headings() -> None:
    frame = MazeFrame(math.radians(30), (1.0, -2.0), CELL)
    pts = np.array([[0.3, 0.4], [-1.0, 2.5]])
    assert np.allclose(frame.to_map(frame.to_maze(pts)), pts)
    assert frame.heading_rad(Direction.N) == pytest.approx(math.radians(120))
    assert frame.heading_rad(Direction.S) == pytest.approx(math.radians(-60))
    assert Direction.between((2, 3), (2, 2)) is Direction.S
    with pytest.raises(ValueError, match="not neighbours"):
        Direction.between((0, 0), (1, 1))


def test_wall_points_trace_the_known_walls_posts_included() -> None:
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    # a log-odds map loses wall ends seen edge-on: free the cells around every post
    posts = [(i * CELL, j * CELL) for i in range(4) for j in range(3)]
    for x, y in posts:
        c, r = int((x - origin[0]) / RES), int((y - origin[1]) / RES)
        window = grid[r - 1 : r + 2, c - 1 : c + 2]
        window[window == 100] = 0
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    graph.update(grid, origin, RES)
    points = graph.wall_points_m((0.45, 0.3), radius_m=2.0)
    # every point lies on (or inside) a real wall ...
    assert distance_to_segments(points, world.segments).max() < 0.008
    # ... and every real wall surface, post ends included, has a point within a centimetre
    seg = world.segments
    t = np.linspace(0.0, 1.0, 40)[:, None]
    surface = np.concatenate([a + t * (b - a) for a, b in zip(seg[:, :2], seg[:, 2:], strict=True)])
    nearest = np.min(
        np.hypot(surface[:, None, 0] - points[None, :, 0], surface[:, None, 1] - points[None, :, 1]), axis=1
    )
    assert nearest.max() < 0.012
    assert len(graph.wall_points_m((0.45, 0.3), radius_m=0.1)) < len(points)  # only walls near the robot


def test_a_cell_once_seen_stays_seen_when_the_map_forgets_part_of_it() -> None:
    # A log-odds map lets cells next to a wall drift back to unknown; the cell must not
    # turn into a frontier again (the robot dithered between two such cells on noloop2).
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    graph.update(grid, origin, RES)
    assert not graph.needs_look((2, 1))
    forgetful = grid.copy()
    c0, c1 = int((2 * CELL - origin[0]) / RES), int((3 * CELL - origin[0]) / RES)
    r0, r1 = int((1 * CELL - origin[1]) / RES), int((2 * CELL - origin[1]) / RES)
    forgetful[r0 + 2 : r1 - 2, c0 + 2 : c1 - 2] = -1  # the inside of (2, 1) unknown again
    graph.update(forgetful, origin, RES)
    assert graph.interior_seen((2, 1)) == pytest.approx(1.0)
    assert not graph.needs_look((2, 1))
    # a cell never seen is still unseen: the latch only keeps what was known
    fresh = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    fresh.update(forgetful, origin, RES)
    assert fresh.needs_look((2, 1))


def test_a_refined_frame_keeps_what_was_seen_of_the_cells() -> None:
    # The frame is re-estimated whenever the walls grow; the estimate wanders by
    # millimetres. The cells stay where they were, and so must their seen shares: a reset
    # brought back cells seen long ago as "look inside" targets across the maze.
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    west = grid.copy()
    west[:, int((1.5 * CELL - origin[0]) / RES) :] = -1  # the east cells not seen yet
    graph.update(west, origin, RES)
    assert graph.frame is not None and not graph.needs_look((0, 1))
    first = graph.frame
    forgetful = grid.copy()
    c0, c1 = int((0 * CELL - origin[0]) / RES), int((1 * CELL - origin[0]) / RES)
    r0, r1 = int((1 * CELL - origin[1]) / RES), int((2 * CELL - origin[1]) / RES)
    forgetful[r0 + 2 : r1 - 2, c0 + 2 : c1 - 2] = -1  # the inside of (0, 1) unknown again
    shifted = (origin[0] + 0.004, origin[1] - 0.003)  # the whole map a few millimetres off
    update = graph.update(forgetful, shifted, RES)
    assert update.frame_changed
    moved_m = math.dist(first.origin_m, graph.frame.origin_m)
    assert 0.001 < moved_m < 0.02
    assert not graph.needs_look((0, 1))
    assert not graph.needs_look((2, 0))  # seen for the first time: the new map counts


def test_a_cell_marked_as_looked_into_stays_seen() -> None:
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    c0 = int((2 * CELL - origin[0]) / RES)
    r0, r1 = int((0 * CELL - origin[1]) / RES), int((1 * CELL - origin[1]) / RES)
    blurred = grid.copy()
    blurred[r0 + 1 : r1 - 1, c0 + 1 : c0 + 4] = -1  # a strip along its west wall never filled in
    graph = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    graph.update(blurred, origin, RES)
    assert graph.needs_look((2, 0))
    graph.mark_looked_into((2, 0))
    graph.update(blurred, origin, RES)
    assert not graph.needs_look((2, 0)) and graph.is_explored((2, 0))
    assert graph.needs_look((1, 0))  # the closed cell next to it is untouched


def test_open_neighbours_agree_with_the_links_everywhere() -> None:
    # open_neighbours answers from a table built once per update: it must say what the
    # links say, for every cell in range and the ring just outside it
    layout = generate_maze(6, 5, seed=3, cell_size_m=CELL)
    world = world_from_layout(layout, 0.012)
    grid, origin = perfect_map(world)
    grid[:, int((3.5 * CELL - origin[0]) / RES) :] = -1  # a partly seen maze: unknown links too
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    graph.update(grid, origin, RES)
    irange, jrange = graph.cell_range()
    for i in range(irange.start - 1, irange.stop + 1):
        for j in range(jrange.start - 1, jrange.stop + 1):
            want = [(i + d.step[0], j + d.step[1]) for d in Direction if graph.link((i, j), d) is LinkState.OPEN]
            assert graph.open_neighbours((i, j)) == want, (i, j)
    assert sum(len(graph.open_neighbours(c)) for c in graph.cells()) > 10


def test_a_known_link_is_not_forgotten_when_its_wall_fades_but_changes_when_the_map_disagrees() -> None:
    # A thin wall between two corridors loses hits to the beams grazing it; each time it
    # fell back to unknown it was a frontier again (test-zigzag-a: minutes of shuttling).
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    graph.update(grid, origin, RES)
    assert graph.link((1, 1), Direction.S) is LinkState.WALL
    faded = grid.copy()
    r = int((1 * CELL - origin[1]) / RES)
    c0, c1 = int((1 * CELL - origin[0]) / RES), int((2 * CELL - origin[0]) / RES)
    faded[r - 2 : r + 2, c0 + 1 : c1 - 1] = -1  # the wall south of (1, 1) unknown again
    fresh = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    fresh.update(faded, origin, RES)
    assert fresh.link((1, 1), Direction.S) is LinkState.UNKNOWN  # what the faded map alone says
    graph.update(faded, origin, RES)
    assert graph.link((1, 1), Direction.S) is LinkState.WALL
    assert (1, 1) not in [cell for cell, _ in graph.frontier_links((0, 0))]
    opened = grid.copy()
    opened[r - 2 : r + 2, c0 + 1 : c1 - 1] = 0  # the map now sees through it: believe that
    graph.update(opened, origin, RES)
    assert graph.link((1, 1), Direction.S) is LinkState.OPEN


def test_what_is_read_off_the_links_follows_a_link_that_changes_and_is_kept_while_none_does() -> None:
    # unknown sides, reachable cells, neighbours and wall outlines are kept per state of the
    # links: an update to the same links keeps them, one that opens a wall must refresh them all
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    graph.update(grid, origin, RES)
    version = graph.links_version
    centre = (1.5 * CELL, 1.0 * CELL)  # on the wall south of (1, 1)
    walls_before = graph.wall_points_m(centre, 0.05)
    assert walls_before.shape[0] > 0
    assert graph.reachable((0, 0)) == {(0, 0), (0, 1), (1, 1), (2, 1), (2, 0)}
    sides = {cell: graph.unknown_sides(cell) for cell in graph.cells()}
    graph.update(grid.copy(), origin, RES)  # the same map again
    assert graph.links_version == version
    assert {cell: graph.unknown_sides(cell) for cell in graph.cells()} == sides
    opened = grid.copy()
    r = int((1 * CELL - origin[1]) / RES)
    c0, c1 = int((1 * CELL - origin[0]) / RES), int((2 * CELL - origin[0]) / RES)
    opened[r - 2 : r + 2, c0 + 1 : c1 - 1] = 0  # the wall between (1, 0) and (1, 1) is gone
    graph.update(opened, origin, RES)
    assert graph.links_version > version
    assert graph.link((1, 1), Direction.S) is LinkState.OPEN
    assert (1, 0) in graph.open_neighbours((1, 1))
    assert (1, 0) in graph.reachable((0, 0))
    fresh = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    fresh.update(opened, origin, RES)
    assert {cell: graph.unknown_sides(cell) for cell in graph.cells()} == {
        cell: fresh.unknown_sides(cell) for cell in fresh.cells()
    }
    assert graph.wall_points_m(centre, 0.05).shape[0] < walls_before.shape[0]
    assert np.array_equal(graph.wall_points_m(centre, 0.3), fresh.wall_points_m(centre, 0.3))


def test_sample_cells_follow_the_grid_values_and_refresh_when_the_grid_moves() -> None:
    """The kept sample indices read what a fresh lookup reads, on new values and on a moved or grown grid."""
    from mazebot.planner.maze_graph import _SampleCells

    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.2, 1.2, (500, 2))

    def direct(grid: np.ndarray, origin_m: tuple[float, float], res_m: float) -> np.ndarray:
        c = np.floor((xy[:, 0] - origin_m[0]) / res_m).astype(int)
        r = np.floor((xy[:, 1] - origin_m[1]) / res_m).astype(int)
        ok = (r >= 0) & (r < grid.shape[0]) & (c >= 0) & (c < grid.shape[1])
        out = np.full(len(xy), UNKNOWN, dtype=np.int8)
        out[ok] = grid[r[ok], c[ok]]
        return out

    cells = _SampleCells()
    calls = []

    def sample_xy() -> np.ndarray:
        calls.append(1)
        return xy

    for grid_shape, origin_m in (((50, 50), (0.0, 0.0)), ((50, 50), (0.0, 0.0)), ((60, 55), (-0.1, -0.04))):
        for _ in range(3):  # the values change every revolution; the indices stay
            grid = rng.choice(np.array([UNKNOWN, FREE, OCCUPIED], dtype=np.int8), size=grid_shape)
            got = cells.lookup(("e", "frame"), grid, origin_m, 0.02, sample_xy)
            assert np.array_equal(got, direct(grid, origin_m, 0.02))
    assert len(calls) == 2  # worked out once per placement of the grid


def test_points_on_the_line_of_a_wall_link_are_told_from_open_links_and_cell_insides() -> None:
    _layout, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    graph = MazeGraph(anchor_xy_m=world.start_pose[:2])
    graph.update(grid, origin, RES)
    assert graph.link((1, 1), Direction.S) is LinkState.WALL and graph.link((1, 1), Direction.W) is LinkState.OPEN
    points = np.array([
        (1.5 * CELL, CELL),  # on the wall between (1, 1) and the sealed (1, 0)
        (1.5 * CELL, CELL + 0.04),  # 4 cm off it, in (1, 1)
        (1.5 * CELL, CELL + 0.08),  # 8 cm off it
        (CELL, 1.5 * CELL),  # on the open link between (0, 1) and (1, 1)
        (1.5 * CELL, 1.5 * CELL),  # the middle of (1, 1)
        (3 * CELL, 0.5 * CELL),  # the maze's outer east wall
    ])
    assert graph.on_walls(points, 0.046).tolist() == [True, True, False, False, False, True]
    assert not MazeGraph().on_walls(points, 0.046).any()  # no lattice yet: no wall known


def test_the_explored_share_counts_the_reachable_cells_is_explored_says_are_explored() -> None:
    _, world = layout_world(SMALL)
    grid, origin = perfect_map(world)
    blurred = grid.copy()
    c0 = int((2 * CELL - origin[0]) / RES)
    r0, r1 = int((0 * CELL - origin[1]) / RES), int((1 * CELL - origin[1]) / RES)
    blurred[r0 + 1 : r1 - 1, c0 + 1 : c0 + 4] = -1  # (2, 0)'s inside not all seen
    half = grid.copy()
    half[: grid.shape[0] // 2] = -1  # the south half unknown: links unknown too
    graph = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    for step, (g, look) in enumerate(((half, False), (blurred, False), (blurred, True), (grid, False))):
        if look:
            graph.mark_looked_into((2, 0))  # in place, between two updates
        else:
            graph.update(g, origin, RES)
        for start in ((0, 0), (1, 1), (2, 0)):
            reachable = graph.reachable(start)
            by_cell = sum(1 for cell in reachable if graph.is_explored(cell)) / len(reachable) if reachable else None
            assert graph.explored_share(start) == by_cell, (step, start)
    assert graph.explored_share((0, 0)) == 1.0


def test_an_update_that_reads_only_the_changed_cells_leaves_what_reading_every_link_leaves() -> None:
    """A few grid cells changing between updates (one revolution's worth) are read incrementally:
    links, seen shares, the version and the changes reported are those of a graph that reads every
    link each time, through reveals, fading walls, cells marked as looked into and a growing range."""
    layout = generate_maze(6, 6, np.random.default_rng(3))
    world = world_from_layout(layout, 0.012)
    truth, origin = perfect_map(world)
    rng = np.random.default_rng(11)
    grid = np.where(rng.random(truth.shape) < 0.5, truth, UNKNOWN).astype(np.int8)
    incremental = MazeGraph(anchor_xy_m=world.start_pose[:2])
    full = MazeGraph(anchor_xy_m=world.start_pose[:2])
    full._update_changed = lambda *args: None  # type: ignore[method-assign]  # always the whole update
    read_changed = 0
    real_changed = incremental._update_changed

    def counted(*args: object) -> object:
        nonlocal read_changed
        result = real_changed(*args)  # type: ignore[arg-type]
        read_changed += result is not None
        return result

    incremental._update_changed = counted  # type: ignore[method-assign]
    for step in range(120):
        if step % 10 == 5:  # a wall fades: a few of its cells back to unknown, some free
            walls = np.flatnonzero(grid.reshape(-1) == OCCUPIED)
            grid.reshape(-1)[rng.choice(walls, 6)] = rng.choice(np.array([UNKNOWN, FREE], dtype=np.int8), 6)
        else:  # a revolution paints a few cells as they truly are
            grid.reshape(-1)[rng.choice(grid.size, 12)] = truth.reshape(-1)[rng.choice(grid.size, 12)]
            hidden = np.flatnonzero(grid.reshape(-1) != truth.reshape(-1))
            grid.reshape(-1)[hidden[:40]] = truth.reshape(-1)[hidden[:40]]
        a = incremental.update(grid.copy(), origin, RES)
        b = full.update(grid.copy(), origin, RES)
        assert a.changed_links == b.changed_links and a.frame_changed == b.frame_changed
        assert incremental.frame == full.frame and incremental.links_version == full.links_version
        assert (incremental._i0, incremental._j0) == (full._i0, full._j0)
        assert np.array_equal(incremental._east, full._east) and np.array_equal(incremental._north, full._north)
        assert np.array_equal(incremental._seen, full._seen)
        if incremental.frame is not None and step % 7 == 0:
            cell = incremental.frame.cell_of(*world.start_pose[:2])
            incremental.mark_looked_into((cell[0] + step % 3, cell[1]))
            full.mark_looked_into((cell[0] + step % 3, cell[1]))
    assert read_changed > 60  # most updates took the incremental path
    incremental.update(truth, origin, RES)
    assert_links_match(incremental, layout)


def test_the_open_links_and_the_walls_have_versions_of_their_own() -> None:
    # a wall coming into view changes no route (the open links stay) and an opening no wall
    # outline: what is kept per open links or per walls stays, and follows when they change
    _, world = layout_world(SMALL)
    truth, origin = perfect_map(world)
    graph = MazeGraph(frame=MazeFrame(0.0, (0.0, 0.0), CELL))
    r = int((1 * CELL - origin[1]) / RES)
    c0, c1 = int((1 * CELL - origin[0]) / RES), int((2 * CELL - origin[0]) / RES)
    hidden = truth.copy()
    hidden[r - 2 : r + 2, c0 + 1 : c1 - 1] = UNKNOWN  # the wall between (1, 0) and (1, 1) not seen yet
    graph.update(hidden, origin, RES)
    assert graph.link((1, 1), Direction.S) is LinkState.UNKNOWN
    links, opened, walls = graph.links_version, graph.open_version, graph.walls_version
    graph.update(truth, origin, RES)  # the wall comes into view
    assert graph.link((1, 1), Direction.S) is LinkState.WALL
    assert graph.links_version > links and graph.open_version == opened and graph.walls_version > walls
    links, walls = graph.links_version, graph.walls_version
    gone = truth.copy()
    gone[r - 2 : r + 2, c0 + 1 : c1 - 1] = FREE  # the wall turns out to be an opening
    graph.update(gone, origin, RES)
    assert graph.link((1, 1), Direction.S) is LinkState.OPEN
    assert graph.links_version > links and graph.open_version > opened and graph.walls_version > walls
