"""Seeded maze generator: perfect, braided (with loops) and rooms (with open areas).

Real mazes are few (the contest files are all 16x16), so tests and benchmarks need
mazes of any size, with the features that make mapping hard: loops, which a
wall-follower never closes and which give SLAM its loop closures, and open areas with
no walls to match against. Every maze is a pure function of its arguments: the same
seed gives the same maze, so a failing benchmark can be replayed.

Conventions follow micromouse: the start is the south-west corner cell (0, 0) with
exactly one open side (north, or east in a one-row maze), and the goal is the centre
(the middle 2x2 cells of an even-sized maze, fewer when a side is odd). Goal cells are
only marked; their walls are whatever the generator made.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from mazebot.config import MAZE_CELL_M
from mazebot.sim.world import MazeLayout

MazeKind = Literal["perfect", "braided", "rooms"]


class _Links:
    """Which neighbouring cells are joined: the mutable working form of a maze.

    ``east[row, col]`` joins (col, row) to (col + 1, row); ``north[row, col]`` joins it
    to (col, row + 1). The outer boundary is always closed.
    """

    def __init__(self, width: int, height: int) -> None:
        self.width = width
        self.height = height
        self.east = np.zeros((height, max(width - 1, 0)), dtype=bool)
        self.north = np.zeros((max(height - 1, 0), width), dtype=bool)

    def neighbours(self, cell: tuple[int, int]) -> list[tuple[int, int]]:
        """The cells next to ``cell`` inside the maze, joined or not, in the order N, E, S, W."""
        col, row = cell
        out = []
        for dc, dr in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            c, r = col + dc, row + dr
            if 0 <= c < self.width and 0 <= r < self.height:
                out.append((c, r))
        return out

    def _slot(self, a: tuple[int, int], b: tuple[int, int]) -> tuple[np.ndarray, int, int]:
        (ca, ra), (cb, rb) = sorted((a, b))  # sorted: the west or south cell first
        if ra == rb and cb == ca + 1:
            return self.east, ra, ca
        if ca == cb and rb == ra + 1:
            return self.north, ra, ca
        raise ValueError(f"cells {a} and {b} are not neighbours")

    def join(self, a: tuple[int, int], b: tuple[int, int], joined: bool = True) -> None:
        array, r, c = self._slot(a, b)
        array[r, c] = joined

    def joined(self, a: tuple[int, int], b: tuple[int, int]) -> bool:
        array, r, c = self._slot(a, b)
        return bool(array[r, c])

    def degree(self, cell: tuple[int, int]) -> int:
        return sum(self.joined(cell, n) for n in self.neighbours(cell))

    def to_layout(self, cell_size_m: float, goal_cells: tuple[tuple[int, int], ...]) -> MazeLayout:
        walls_east = np.ones((self.height, self.width), dtype=bool)
        walls_east[:, :-1] = ~self.east
        walls_north = np.ones((self.height, self.width), dtype=bool)
        walls_north[:-1, :] = ~self.north
        return MazeLayout(
            width=self.width,
            height=self.height,
            cell_size_m=cell_size_m,
            walls_east=walls_east,
            walls_north=walls_north,
            walls_west_edge=np.ones(self.height, dtype=bool),
            walls_south_edge=np.ones(self.width, dtype=bool),
            start_cell=(0, 0),
            goal_cells=goal_cells,
        )


def centre_cells(width: int, height: int) -> tuple[tuple[int, int], ...]:
    """The middle cells: 2 per even side, 1 per odd side (sorted south to north, west to east)."""
    cols = [width // 2 - 1, width // 2] if width % 2 == 0 else [width // 2]
    rows = [height // 2 - 1, height // 2] if height % 2 == 0 else [height // 2]
    return tuple((c, r) for r in rows for c in cols)


def generate_maze(
    width: int,
    height: int,
    seed: int,
    kind: MazeKind = "perfect",
    cell_size_m: float = MAZE_CELL_M,
    braid_fraction: float = 0.5,
    room_count: int = 1,
    room_size: int = 3,
) -> MazeLayout:
    """A ``width`` x ``height`` maze, the same for the same arguments.

    ``kind``:

    - ``"perfect"``: a spanning tree (iterative recursive backtracker): exactly one path
      between any two cells, long corridors, many dead ends.
    - ``"braided"``: a perfect maze with ``braid_fraction`` of its dead ends (the start
      cell excepted) opened into a neighbour, which makes loops.
    - ``"rooms"``: a perfect maze with ``room_count`` open areas of ``room_size`` x
      ``room_size`` cells carved in (no inner walls), away from the start cell.

    The start cell (0, 0) is a leaf of the spanning tree, joined only to its north
    neighbour (east in a one-row maze), and no later step opens it further.
    """
    if width < 1 or height < 1 or width * height < 2:
        raise ValueError(f"a maze needs at least 2 cells, got {width}x{height}")
    if kind not in ("perfect", "braided", "rooms"):
        raise ValueError(f"kind must be 'perfect', 'braided' or 'rooms', got {kind!r}")
    if not 0.0 <= braid_fraction <= 1.0:
        raise ValueError(f"braid_fraction must be in [0, 1], got {braid_fraction}")
    rng = np.random.default_rng(seed)
    links = _Links(width, height)
    _backtracker(links, rng)
    if kind == "braided":
        _braid(links, rng, braid_fraction)
    elif kind == "rooms":
        _carve_rooms(links, rng, room_count, room_size)
    return links.to_layout(cell_size_m, centre_cells(width, height))


def _backtracker(links: _Links, rng: np.random.Generator) -> None:
    """Spanning tree by depth-first search with random neighbour order.

    The start cell is left out of the search and attached at the end through one side,
    which keeps the tree a tree and the start a dead end with one open side.
    """
    start = (0, 0)
    entry = (0, 1) if links.height > 1 else (1, 0)
    visited = np.zeros((links.height, links.width), dtype=bool)
    visited[start[1], start[0]] = True
    visited[entry[1], entry[0]] = True
    stack = [entry]
    while stack:
        cell = stack[-1]
        fresh = [n for n in links.neighbours(cell) if not visited[n[1], n[0]]]
        if not fresh:
            stack.pop()
            continue
        nxt = fresh[int(rng.integers(len(fresh)))]
        links.join(cell, nxt)
        visited[nxt[1], nxt[0]] = True
        stack.append(nxt)
    links.join(start, entry)


def _braid(links: _Links, rng: np.random.Generator, fraction: float) -> None:
    """Open ``fraction`` of the dead ends into a neighbour, preferring another dead end.

    Joining two dead ends removes both with one wall. The start cell and its entry link
    are left alone so the start keeps exactly one open side.
    """
    start = (0, 0)
    dead_ends = [
        (c, r) for r in range(links.height) for c in range(links.width) if (c, r) != start and links.degree((c, r)) == 1
    ]
    order = rng.permutation(len(dead_ends))
    to_open = round(fraction * len(dead_ends))
    opened = 0
    for i in order:
        if opened >= to_open:
            break
        cell = dead_ends[int(i)]
        if links.degree(cell) != 1:
            continue  # already opened as the partner of an earlier dead end
        candidates = [n for n in links.neighbours(cell) if n != start and not links.joined(cell, n)]
        if not candidates:
            continue
        partners = [n for n in candidates if links.degree(n) == 1]
        pool = partners or candidates
        links.join(cell, pool[int(rng.integers(len(pool)))])
        opened += 1


def _carve_rooms(links: _Links, rng: np.random.Generator, count: int, size: int) -> None:
    """Remove every inner wall of ``count`` non-overlapping ``size`` x ``size`` blocks.

    Blocks never contain the start cell (its single open side must stay single); removing
    walls only adds links, so every cell stays reachable.
    """
    if count < 1 or size < 2:
        raise ValueError(f"rooms need room_count >= 1 and room_size >= 2, got {count}, {size}")
    corners = [
        (c, r)
        for r in range(links.height - size + 1)
        for c in range(links.width - size + 1)
        if not (c == 0 and r == 0)  # (0, 0) is in a block only if the block starts there
    ]
    if not corners:
        raise ValueError(
            f"a {links.width}x{links.height} maze has no room for a {size}x{size} open area away from the start cell"
        )
    taken = np.zeros((links.height, links.width), dtype=bool)
    placed = 0
    for i in rng.permutation(len(corners)):
        c0, r0 = corners[int(i)]
        if taken[r0 : r0 + size, c0 : c0 + size].any():
            continue
        taken[r0 : r0 + size, c0 : c0 + size] = True
        links.east[r0 : r0 + size, c0 : c0 + size - 1] = True
        links.north[r0 : r0 + size - 1, c0 : c0 + size] = True
        placed += 1
        if placed == count:
            return
    raise ValueError(
        f"only {placed} of {count} non-overlapping {size}x{size} rooms fit in a {links.width}x{links.height} maze"
    )
