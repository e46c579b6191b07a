"""Micromouse maze files: parsing real contest mazes, round trips, errors, geometry."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mazebot.sim.maze_file import (
    MazeFileError,
    load_maze,
    maze_to_text,
    packaged_maze_names,
    packaged_maze_path,
    parse_maze,
    read_maze_layout,
)
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import cast_rays
from mazebot.sim.world import SIDE_HEADING_RAD, MazeLayout, world_from_layout
from tests.data_paths import MAZES, needs_mazes

# Contest mazes from different decades and a training maze in a mostly empty frame.
SAMPLE_FILES = [
    "classic/japan2013ef.txt",
    "classic/alljapan-046-2025-exp-fin.txt",
    "classic/boston.txt",
    "classic/kor92.txt",
    "classic/empty.txt",
    "training/minimaze.txt",
    "training/training-8x8-test1.txt",
]


def _normalise(text: str) -> str:
    return "\n".join(line.rstrip() for line in text.splitlines()).strip("\n") + "\n"



@needs_mazes
@pytest.mark.parametrize("name", SAMPLE_FILES)
def test_wall_counts_match_the_text(name: str) -> None:
    text = (MAZES / name).read_text()
    layout = read_maze_layout(MAZES / name)
    horizontal = int(layout.walls_north.sum() + layout.walls_south_edge.sum())
    vertical = int(layout.walls_east.sum() + layout.walls_west_edge.sum())
    assert horizontal == text.count("---")
    assert vertical == text.count("|")
    assert layout.wall_count() == horizontal + vertical


@needs_mazes
@pytest.mark.parametrize("path", sorted(MAZES.glob("*/*.txt")), ids=lambda p: p.name)
def test_every_shared_maze_round_trips(path: Path) -> None:
    text = path.read_text()
    layout = read_maze_layout(path)
    assert _normalise(maze_to_text(layout, mark_start="S" in text)) == _normalise(text)
    assert parse_maze(maze_to_text(layout)) == layout


@needs_mazes
def test_classic_mazes_are_closed_16x16_with_start_and_goal() -> None:
    for path in sorted((MAZES / "classic").glob("*.txt")):
        layout = read_maze_layout(path)
        assert (layout.width, layout.height) == (16, 16), path.name
        assert layout.walls_west_edge.all(), path.name
        assert layout.walls_south_edge.all(), path.name
        assert layout.walls_east[:, -1].all(), path.name
        assert layout.walls_north[-1, :].all(), path.name
        assert layout.start_cell == (0, 0), path.name
        assert len(layout.goal_cells) == 4, path.name


@needs_mazes
def test_japan2013_start_goal_and_pose() -> None:
    world = load_maze(MAZES / "classic" / "japan2013ef.txt")
    layout = world.maze
    assert layout is not None
    assert layout.start_cell == (0, 0)
    assert layout.goal_cells == ((7, 7), (8, 7), (7, 8), (8, 8))
    # the text's first cell row is the north row: "|       |" -> cells (0,15), (1,15) joined
    assert not layout.has_wall((0, 15), "E")
    assert layout.has_wall((1, 15), "E")
    x, y, theta = world.start_pose
    assert (x, y) == pytest.approx((0.1524, 0.1524))
    assert theta == pytest.approx(math.pi / 2)  # the start cell opens to the north only
    assert len(layout.reachable()) == 256
    assert 100 < world.segments.shape[0] < 600  # merged runs: a few hundred, not thousands


@needs_mazes
def test_training_maze_without_s_starts_in_the_south_west_corner() -> None:
    world = load_maze(MAZES / "training" / "minimaze.txt")
    assert world.maze is not None
    assert world.maze.start_cell == (0, 0)
    assert world.maze.goal_cells == ()
    assert world.start_pose[2] == pytest.approx(math.pi / 2)
    # the 5x5 active area is walled off from the open frame around it
    assert len(world.maze.reachable((0, 0))) == 25


@needs_mazes
def test_walls_are_where_rays_from_cell_centres_stop() -> None:
    # Ties the text, the layout and the wall geometry together: from each cell centre a
    # ray towards a walled side stops at the wall face, half a cell minus half a wall.
    world = load_maze(MAZES / "classic" / "kor92.txt", wall_thickness_m=0.012)
    layout = world.maze
    assert layout is not None
    face_m = 0.3048 / 2 - 0.006
    for row in range(layout.height):
        for col in range(layout.width):
            centre = np.array(layout.cell_center_m((col, row)))
            angles = np.array([SIDE_HEADING_RAD[s] for s in "NESW"])
            d = cast_rays(centre, angles, world.segments, world.circles, 12.0)
            for side, dist in zip("NESW", d, strict=True):
                if layout.has_wall((col, row), side):
                    assert dist == pytest.approx(face_m), (col, row, side)
                else:
                    assert dist > 0.3048 + face_m - 1e-9, (col, row, side)


def test_corners_are_closed() -> None:
    # One closed cell: the four walls reach half a thickness past the post centres, so
    # the solid is a square ring and its outline is exactly two squares.
    world = world_from_layout(MazeLayout.closed(1, 1, 0.3), wall_thickness_m=0.02)
    corners = {(round(x, 9), round(y, 9)) for x, y in world.segments.reshape(-1, 2)}
    assert world.segments.shape == (8, 4)
    assert corners == {
        (-0.01, -0.01), (0.31, -0.01), (0.31, 0.31), (-0.01, 0.31),
        (0.01, 0.01), (0.29, 0.01), (0.29, 0.29), (0.01, 0.29),
    }  # fmt: skip
    # rays aimed at the corners hit them, from outside and from inside
    d = cast_rays(np.array([-0.11, -0.11]), np.array([math.pi / 4]), world.segments, world.circles, 5.0)
    assert d[0] == pytest.approx(0.1 * math.sqrt(2.0))
    d = cast_rays(np.array([0.15, 0.15]), np.array([3 * math.pi / 4]), world.segments, world.circles, 5.0)
    assert d[0] == pytest.approx(0.14 * math.sqrt(2.0))


def test_segments_have_the_solid_on_their_left() -> None:
    layout = generate_maze(7, 5, seed=4, kind="rooms")
    world = world_from_layout(layout, wall_thickness_m=0.012)
    rects = layout.wall_rectangles_m(0.012)
    segs = world.segments
    mid = (segs[:, :2] + segs[:, 2:]) / 2
    direction = segs[:, 2:] - segs[:, :2]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    left = np.column_stack([-direction[:, 1], direction[:, 0]])

    def inside_any(points: np.ndarray) -> np.ndarray:
        x, y = points[:, :1], points[:, 1:]
        return ((x > rects[:, 0]) & (x < rects[:, 2]) & (y > rects[:, 1]) & (y < rects[:, 3])).any(1)

    assert inside_any(mid + 1e-4 * left).all()
    assert not inside_any(mid - 1e-4 * left).any()


def test_crlf_trailing_whitespace_and_blank_lines_are_tolerated() -> None:
    text = "o---o---o\n| S   G |\no---o---o\n"
    messy = "\r\n" + "o---o---o   \r\n| S   G |\t\r\no---o---o\r\n\r\n\r\n"
    assert parse_maze(messy) == parse_maze(text)
    # an open east boundary leaves only trailing spaces, which an editor may strip
    assert not parse_maze("o---o---o\n| S\no---o---o\n").has_wall((1, 0), "E")


def test_small_maze_orientation() -> None:
    text = "o---o---o\n| G     |\no   o---o\n| S |   |\no---o---o\n"
    layout = parse_maze(text)
    assert (layout.width, layout.height) == (2, 2)
    assert layout.start_cell == (0, 0)  # the bottom text row is row 0
    assert layout.goal_cells == ((0, 1),)
    assert layout.open_sides((0, 0)) == ["N"]
    assert layout.open_sides((1, 1)) == ["W"]
    assert layout.has_wall((1, 0), "N")
    assert maze_to_text(layout) == text


def test_start_faces_into_the_maze_rather_than_out_of_it() -> None:
    # the S cell is open to the north (out of the maze) and to the east (into it)
    world = world_from_layout(parse_maze("o   o---o\n| S     |\no---o---o\n"))
    assert world.start_pose[2] == pytest.approx(0.0)
    # open only to the outside: face that way rather than into a wall
    world = world_from_layout(parse_maze("o   o---o\n| S |   |\no---o---o\n"))
    assert world.start_pose[2] == pytest.approx(math.pi / 2)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("o---o\n|   |\n", "odd number"),
        ("o---o\n|   |\no-- o\n", ":3:2: expected '---'"),
        ("o---o\n|   |\nx---o\n", ":3:1: expected a post"),
        ("o---o\n| X |\no---o\n", ":2:3: expected ' ', 'S' or 'G'"),
        ("o---o\n#   |\no---o\n", ":2:1: expected '|'"),
        ("o---o\n|   |   |\no---o\n", ":2: line is 9 characters"),
        ("o---o---o\n| S   S |\no---o---o\n", "at most one start"),
        ("o--o\n|  |\no--o\n", ":1: the first post row"),
    ],
)
def test_malformed_text_is_rejected_with_file_and_line(text: str, fragment: str) -> None:
    with pytest.raises(MazeFileError) as info:
        parse_maze(text, source="bad.txt")
    message = str(info.value)
    assert message.startswith("bad.txt")
    assert fragment in message
    assert "\n" not in message


def test_missing_file_is_one_clear_line(tmp_path: Path) -> None:
    with pytest.raises(MazeFileError, match=r"maze file .*nope\.txt not found"):
        load_maze(tmp_path / "nope.txt")
    bad = tmp_path / "bad.txt"
    bad.write_text("o---o\n|   |\no-x-o\n")
    with pytest.raises(MazeFileError, match=r"bad\.txt:3:"):
        load_maze(bad)


def test_packaged_mazes_load() -> None:
    names = packaged_maze_names()
    assert {"default_6x6", "minimaze", "japan2013ef"} <= set(names)
    for name in names:
        world = load_maze(packaged_maze_path(name))
        assert world.maze is not None and world.segments.shape[0] > 0
    with pytest.raises(MazeFileError, match=r"available: .*default_6x6"):
        packaged_maze_path("no-such-maze")


def test_default_6x6_is_a_demo_maze() -> None:
    layout = load_maze(packaged_maze_path("default_6x6")).maze
    assert layout is not None
    assert (layout.width, layout.height) == (6, 6)
    assert layout.start_cell == (0, 0)
    assert layout.open_sides((0, 0)) == ["N"]
    assert layout.goal_cells == ((2, 2), (3, 2), (2, 3), (3, 3))
    assert len(layout.reachable((0, 0))) == 36
