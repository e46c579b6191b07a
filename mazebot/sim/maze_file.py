"""Micromouse text mazes: read them into worlds, write layouts back as text.

The format is the one of the public micromouse maze collections (e.g.
github.com/micromouseonline/mazefiles)::

    o---o---o
    |       |
    o   o---o
    | S   G |
    o---o---o

Posts ``o`` sit every 4 characters on even lines; between two posts ``---`` is a wall
and three spaces are none. Odd lines are cell rows: ``|`` or a space at every post
column, and a 3-character cell interior that may hold ``S`` (start) or ``G`` (goal).
Row 0 of the text is the north edge, while row 0 of a :class:`MazeLayout` is the
southern row, so rows are flipped on the way in and out.

Files without an ``S`` (the training mazes) start in the south-west corner cell
(col 0, row 0): that is the micromouse convention, the corner cell walled on three
sides.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from mazebot.config import MAZE_CELL_M
from mazebot.errors import UsageError
from mazebot.sim.world import MazeLayout, World, world_from_layout

#: Cell pitch of the robot's own maze (docs/design.md, "The reference robot": 1 ft cells). Contest micromouse mazes
#: are 0.18 m; pass ``cell_size_m=0.18`` to load one at its true scale.
DEFAULT_CELL_M = MAZE_CELL_M
#: Wall thickness of a micromouse maze, 12 mm.
DEFAULT_WALL_M = 0.012


class MazeFileError(UsageError):
    """A maze file is missing or does not follow the micromouse text format.

    The message names the file and, where it applies, the 1-based line and column.
    """


def parse_maze(text: str, cell_size_m: float = DEFAULT_CELL_M, source: str = "<text>") -> MazeLayout:
    """Parse micromouse maze text into a layout (row 0 = the southern row).

    Trailing whitespace, CRLF line ends and blank lines around the maze are ignored:
    files pass through editors and Windows machines. Anything else that breaks the
    format raises :class:`MazeFileError` naming ``source`` and the line.
    """
    lines = [line.rstrip() for line in text.replace("\r\n", "\n").replace("\r", "\n").split("\n")]
    while lines and not lines[-1]:
        lines.pop()
    first = 0  # blank lines before the maze are skipped; line numbers still count them
    while first < len(lines) and not lines[first]:
        first += 1
    lines = lines[first:]
    if len(lines) < 3 or len(lines) % 2 == 0:
        raise MazeFileError(
            f"{source}: expected an odd number (>= 3) of lines, alternating post rows and cell rows, found {len(lines)}"
        )
    top = lines[0]
    if len(top) < 5 or (len(top) - 1) % 4 != 0:
        raise MazeFileError(
            f"{source}:{first + 1}: the first post row must be 4*width+1 characters ('o---o---o'), found {len(top)}"
        )
    width = (len(top) - 1) // 4
    height = (len(lines) - 1) // 2
    row_len = 4 * width + 1

    walls_north_text = np.zeros((height + 1, width), dtype=bool)  # text order, line 0 = north
    walls_west_text = np.zeros((height, width + 1), dtype=bool)  # text order
    start: list[tuple[int, int]] = []
    goals: list[tuple[int, int]] = []

    for index, line in enumerate(lines):
        number = first + index + 1  # 1-based line number in the file
        if len(line) > row_len:
            raise MazeFileError(
                f"{source}:{number}: line is {len(line)} characters, longer than the {row_len} of the first post row"
            )
        line = line.ljust(row_len)
        if index % 2 == 0:  # post row
            for col in range(width + 1):
                if line[4 * col] != "o":
                    raise MazeFileError(
                        f"{source}:{number}:{4 * col + 1}: expected a post 'o', found {line[4 * col]!r}"
                    )
            for col in range(width):
                span = line[4 * col + 1 : 4 * col + 4]
                if span not in ("---", "   "):
                    raise MazeFileError(
                        f"{source}:{number}:{4 * col + 2}: expected '---' or three spaces between posts, found {span!r}"
                    )
                walls_north_text[index // 2, col] = span == "---"
        else:  # cell row
            text_row = index // 2
            for col in range(width + 1):
                mark = line[4 * col]
                if mark not in ("|", " "):
                    raise MazeFileError(
                        f"{source}:{number}:{4 * col + 1}: expected '|' or a space on a post column, found {mark!r}"
                    )
                walls_west_text[text_row, col] = mark == "|"
            for col in range(width):
                inside = line[4 * col + 1 : 4 * col + 4]
                cell = (col, height - 1 - text_row)
                for offset, ch in enumerate(inside):
                    if ch not in " SG":
                        raise MazeFileError(
                            f"{source}:{number}:{4 * col + 2 + offset}: expected ' ', 'S' or "
                            f"'G' inside a cell, found {ch!r}"
                        )
                if "S" in inside:
                    start.append(cell)
                if "G" in inside:
                    goals.append(cell)

    if len(start) > 1:
        raise MazeFileError(f"{source}: expected at most one start cell 'S', found {len(start)}")
    # Flip to layout order (row 0 = south). Text post line k is the north side of text
    # row k, i.e. of layout row height-1-k; the last post line is the south edge.
    walls_north = walls_north_text[:height][::-1].copy()
    walls_south_edge = walls_north_text[height].copy()
    walls_east = walls_west_text[:, 1:][::-1].copy()
    walls_west_edge = walls_west_text[:, 0][::-1].copy()
    goals.sort(key=lambda c: (c[1], c[0]))
    return MazeLayout(
        width=width,
        height=height,
        cell_size_m=cell_size_m,
        walls_east=walls_east,
        walls_north=walls_north,
        walls_west_edge=walls_west_edge,
        walls_south_edge=walls_south_edge,
        start_cell=start[0] if start else (0, 0),
        goal_cells=tuple(goals),
    )


def read_maze_layout(path: str | Path, cell_size_m: float = DEFAULT_CELL_M) -> MazeLayout:
    """Read a maze file into a layout; see :func:`parse_maze`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MazeFileError(f"maze file {path} not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise MazeFileError(f"maze file {path} cannot be read as text ({error})") from None
    return parse_maze(text, cell_size_m=cell_size_m, source=str(path))


def load_maze(
    path: str | Path,
    cell_size_m: float = DEFAULT_CELL_M,
    wall_thickness_m: float = DEFAULT_WALL_M,
) -> World:
    """Load a maze file as a world, the robot at the start cell's centre.

    The robot faces along an open side of the start cell, preferring sides that lead
    into the maze (see :func:`mazebot.sim.world.start_heading_rad`). Without an ``S``
    in the file it starts in the south-west corner cell (micromouse convention).
    """
    layout = read_maze_layout(path, cell_size_m=cell_size_m)
    world = world_from_layout(layout, wall_thickness_m=wall_thickness_m, name=Path(path).stem)
    world.meta["source"] = str(path)
    return world


def maze_to_text(layout: MazeLayout, mark_start: bool = True) -> str:
    """The layout in micromouse text form, ending with a newline.

    ``mark_start=False`` leaves out the ``S``, for layouts read from files that had none
    (their start is the south-west corner by convention, so reading the text back gives
    the same layout either way).
    """
    goals = set(layout.goal_cells)
    out: list[str] = []
    for text_row in range(layout.height + 1):
        row = layout.height - text_row  # the layout row whose south side this post line is
        flags = layout.walls_south_edge if row == 0 else layout.walls_north[row - 1]
        out.append("o" + "".join(("---" if f else "   ") + "o" for f in flags))
        if text_row == layout.height:
            break
        row -= 1  # the cell row below this post line
        parts = ["|" if layout.walls_west_edge[row] else " "]
        for col in range(layout.width):
            if mark_start and (col, row) == layout.start_cell:
                inside = " S "
            elif (col, row) in goals:
                inside = " G "
            else:
                inside = "   "
            parts.append(inside + ("|" if layout.walls_east[row, col] else " "))
        out.append("".join(parts))
    return "\n".join(out) + "\n"


def packaged_maze_path(name: str) -> Path:
    """Path of a maze shipped with mazebot (``mazebot/sim/mazes/NAME.txt``).

    ``name`` may be given with or without ``.txt``. Raises :class:`MazeFileError`
    listing the available names when there is no such maze.
    """
    stem = name.removesuffix(".txt")
    path = Path(str(resources.files("mazebot.sim") / "mazes" / f"{stem}.txt"))
    if not path.is_file():
        available = ", ".join(packaged_maze_names()) or "none"
        raise MazeFileError(f"no packaged maze named {name!r}; available: {available}")
    return path


def packaged_maze_names() -> list[str]:
    """Names of the mazes shipped with mazebot, sorted."""
    folder = Path(str(resources.files("mazebot.sim") / "mazes"))
    return sorted(p.stem for p in folder.glob("*.txt"))
