"""Generated mazes: spanning-tree, braid and room invariants, and determinism."""

from __future__ import annotations

import pytest

from mazebot.sim.maze_file import maze_to_text, parse_maze
from mazebot.sim.maze_generator import centre_cells, generate_maze
from mazebot.sim.world import MazeLayout

SIZES = [(2, 1), (1, 3), (5, 5), (6, 6), (16, 16), (9, 4)]


def _cells(layout: MazeLayout) -> list[tuple[int, int]]:
    return [(c, r) for r in range(layout.height) for c in range(layout.width)]



def _links(layout: MazeLayout) -> int:
    return sum(len(layout.neighbours(cell)) for cell in _cells(layout)) // 2


def _dead_ends(layout: MazeLayout) -> int:
    return sum(len(layout.neighbours(cell)) == 1 for cell in _cells(layout))


def _boundary_closed(layout: MazeLayout) -> bool:
    return bool(
        layout.walls_west_edge.all()
        and layout.walls_south_edge.all()
        and layout.walls_east[:, -1].all()
        and layout.walls_north[-1, :].all()
    )


def _has_open_block(layout: MazeLayout, size: int) -> bool:
    for r0 in range(layout.height - size + 1):
        for c0 in range(layout.width - size + 1):
            inner_east = layout.walls_east[r0 : r0 + size, c0 : c0 + size - 1]
            inner_north = layout.walls_north[r0 : r0 + size - 1, c0 : c0 + size]
            if not inner_east.any() and not inner_north.any():
                return True
    return False


@pytest.mark.parametrize(("width", "height"), SIZES)
@pytest.mark.parametrize("seed", [0, 1, 7])
def test_perfect_maze_is_a_spanning_tree(width: int, height: int, seed: int) -> None:
    layout = generate_maze(width, height, seed=seed)
    assert (layout.width, layout.height) == (width, height)
    assert len(layout.reachable()) == width * height
    assert _links(layout) == width * height - 1
    assert _boundary_closed(layout)
    assert layout.start_cell == (0, 0)
    assert len(layout.open_sides((0, 0))) == 1
    assert layout.open_sides((0, 0)) == (["N"] if height > 1 else ["E"])
    assert layout.goal_cells == centre_cells(width, height)


def test_goal_is_the_centre() -> None:
    assert centre_cells(16, 16) == ((7, 7), (8, 7), (7, 8), (8, 8))
    assert centre_cells(5, 5) == ((2, 2),)
    assert centre_cells(6, 3) == ((2, 1), (3, 1))


@pytest.mark.parametrize("seed", range(6))
def test_braided_maze_has_loops_and_fewer_dead_ends(seed: int) -> None:
    perfect = generate_maze(12, 10, seed=seed)
    braided = generate_maze(12, 10, seed=seed, kind="braided", braid_fraction=0.6)
    assert _dead_ends(braided) < _dead_ends(perfect)
    assert _links(braided) > 12 * 10 - 1  # more links than a tree: loops
    assert len(braided.reachable()) == 12 * 10
    assert _boundary_closed(braided)
    assert braided.open_sides((0, 0)) == ["N"]
    fully = generate_maze(12, 10, seed=seed, kind="braided", braid_fraction=1.0)
    assert _dead_ends(fully) == 1  # only the start cell, kept as micromouse wants it


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("rooms", [1, 2])
def test_rooms_maze_has_open_areas(seed: int, rooms: int) -> None:
    layout = generate_maze(10, 8, seed=seed, kind="rooms", room_count=rooms)
    assert _has_open_block(layout, 3)
    assert len(layout.reachable()) == 80
    assert layout.open_sides((0, 0)) == ["N"]
    assert _boundary_closed(layout)
    perfect = generate_maze(10, 8, seed=seed)
    assert not _has_open_block(perfect, 2)  # a tree has no open 2x2, let alone 3x3
    # every inner link of every room: 12 per 3x3 room at most added to a tree
    assert _links(layout) - _links(perfect) <= 12 * rooms


def test_same_seed_same_maze_different_seed_different_maze() -> None:
    for kind in ("perfect", "braided", "rooms"):
        a = generate_maze(16, 16, seed=42, kind=kind)
        b = generate_maze(16, 16, seed=42, kind=kind)
        c = generate_maze(16, 16, seed=43, kind=kind)
        assert a == b
        assert a != c
        assert maze_to_text(a) == maze_to_text(b)


def test_generated_maze_round_trips_through_text() -> None:
    layout = generate_maze(7, 9, seed=5, kind="braided", cell_size_m=0.25)
    assert parse_maze(maze_to_text(layout), cell_size_m=0.25) == layout


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"width": 1, "height": 1}, "at least 2 cells"),
        ({"width": 4, "height": 4, "kind": "spiral"}, "kind must be"),
        ({"width": 4, "height": 4, "braid_fraction": 1.5}, "braid_fraction"),
        ({"width": 3, "height": 3, "kind": "rooms"}, "no room"),
        ({"width": 6, "height": 6, "kind": "rooms", "room_count": 5}, "only"),
    ],
)
def test_bad_arguments_are_rejected(kwargs: dict[str, object], fragment: str) -> None:
    kwargs.setdefault("seed", 0)
    with pytest.raises(ValueError, match=fragment):
        generate_maze(**kwargs)  # type: ignore[arg-type]
