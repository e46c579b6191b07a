"""The geometry of a simulated world: wall surfaces as segments, posts as circles.

Everything the simulator needs to know about a world (ray casting, collisions, ground
truth rasters) reads these arrays; loaders and generators only have to produce them.
The frame is the world frame: x east, y north, metres; angles counter-clockwise.

Walls are solid rectangles, but a world stores only their outline: the boundary of
the union of all wall rectangles, as segments. That keeps a 16x16 maze to a few
hundred segments (the ray caster's cost grows with their number), leaves no hidden
surfaces inside walls, and lets a rasteriser fill the walls by the even-odd rule.
Every segment is oriented with the solid on its left, so its right-hand normal
``(dy, -dx)`` points into free space.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: The four sides of a maze cell and the heading (radians) of a robot facing through each.
SIDE_HEADING_RAD: dict[str, float] = {"N": np.pi / 2, "E": 0.0, "S": -np.pi / 2, "W": np.pi}
#: (dcol, drow) of the neighbour through each side.
SIDE_STEP: dict[str, tuple[int, int]] = {"N": (0, 1), "E": (1, 0), "S": (0, -1), "W": (-1, 0)}


@dataclass(frozen=True)
class MazeLayout:
    """The cell structure of a maze world, for ground truth and scripted routes.

    Cell (col, row) has its south-west corner at ``origin + (col, row) * cell_size_m``;
    row 0 is the southern row. ``walls_east[row, col]`` is True when there is a wall on
    the east side of that cell, ``walls_north[row, col]`` on its north side; the outer
    boundary is included (west of column 0 is ``walls_west_edge``, south of row 0 is
    ``walls_south_edge``).

    Layouts compare equal when their size, cell size, walls, start, goals and origin do
    (the arrays are compared element-wise), so a round trip can be checked with ``==``.

    >>> layout = MazeLayout.closed(2, 1, 0.3048)
    >>> layout.has_wall((0, 0), "E"), layout.neighbours((0, 0))
    (True, [])
    """

    width: int
    height: int
    cell_size_m: float
    walls_east: np.ndarray  # bool (height, width)
    walls_north: np.ndarray  # bool (height, width)
    walls_west_edge: np.ndarray  # bool (height,)
    walls_south_edge: np.ndarray  # bool (width,)
    start_cell: tuple[int, int]  # (col, row)
    goal_cells: tuple[tuple[int, int], ...] = ()
    origin_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        # Normalise to bool arrays of the documented shapes once, so every reader can
        # index without checking; a wrong shape is a programming error worth a clear line.
        expected = {
            "walls_east": (self.height, self.width),
            "walls_north": (self.height, self.width),
            "walls_west_edge": (self.height,),
            "walls_south_edge": (self.width,),
        }
        if self.width < 1 or self.height < 1:
            raise ValueError(f"maze must be at least 1x1 cells, got {self.width}x{self.height}")
        for name, shape in expected.items():
            arr = np.array(getattr(self, name), dtype=bool)
            if arr.shape != shape:
                raise ValueError(f"MazeLayout.{name} must have shape {shape}, got {arr.shape}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "start_cell", (int(self.start_cell[0]), int(self.start_cell[1])))
        goals = tuple((int(c), int(r)) for c, r in self.goal_cells)
        object.__setattr__(self, "goal_cells", goals)
        for cell in (self.start_cell, *goals):
            if not self.contains(cell):
                raise ValueError(f"cell {cell} is outside the {self.width}x{self.height} maze")

    @classmethod
    def closed(
        cls,
        width: int,
        height: int,
        cell_size_m: float,
        start_cell: tuple[int, int] = (0, 0),
        goal_cells: tuple[tuple[int, int], ...] = (),
    ) -> MazeLayout:
        """A maze with every wall standing: the starting point of generators."""
        return cls(
            width=width,
            height=height,
            cell_size_m=cell_size_m,
            walls_east=np.ones((height, width), dtype=bool),
            walls_north=np.ones((height, width), dtype=bool),
            walls_west_edge=np.ones(height, dtype=bool),
            walls_south_edge=np.ones(width, dtype=bool),
            start_cell=start_cell,
            goal_cells=goal_cells,
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, MazeLayout):
            return NotImplemented
        return (
            self.width == other.width
            and self.height == other.height
            and self.cell_size_m == other.cell_size_m
            and self.start_cell == other.start_cell
            and self.goal_cells == other.goal_cells
            and self.origin_m == other.origin_m
            and bool(np.array_equal(self.walls_east, other.walls_east))
            and bool(np.array_equal(self.walls_north, other.walls_north))
            and bool(np.array_equal(self.walls_west_edge, other.walls_west_edge))
            and bool(np.array_equal(self.walls_south_edge, other.walls_south_edge))
        )

    __hash__ = None  # type: ignore[assignment]  # holds arrays: not hashable

    def contains(self, cell: tuple[int, int]) -> bool:
        """True when ``cell`` (col, row) is inside the maze."""
        return 0 <= cell[0] < self.width and 0 <= cell[1] < self.height

    def has_wall(self, cell: tuple[int, int], side: str) -> bool:
        """True when the ``side`` ("N", "E", "S" or "W") of ``cell`` (col, row) is walled."""
        col, row = cell
        if side == "N":
            return bool(self.walls_north[row, col])
        if side == "E":
            return bool(self.walls_east[row, col])
        if side == "S":
            return bool(self.walls_south_edge[col] if row == 0 else self.walls_north[row - 1, col])
        if side == "W":
            return bool(self.walls_west_edge[row] if col == 0 else self.walls_east[row, col - 1])
        raise ValueError(f"side must be one of N, E, S, W, got {side!r}")

    def open_sides(self, cell: tuple[int, int]) -> list[str]:
        """The sides of ``cell`` without a wall, in the order N, E, S, W."""
        return [side for side in "NESW" if not self.has_wall(cell, side)]

    def neighbours(self, cell: tuple[int, int]) -> list[tuple[int, int]]:
        """Cells reachable from ``cell`` in one step (an open side leading into the maze)."""
        out = []
        for side in self.open_sides(cell):
            dc, dr = SIDE_STEP[side]
            nxt = (cell[0] + dc, cell[1] + dr)
            if self.contains(nxt):
                out.append(nxt)
        return out

    def reachable(self, start: tuple[int, int] | None = None) -> set[tuple[int, int]]:
        """The cells reachable from ``start`` (default: the start cell) through open sides, itself included."""
        first = self.start_cell if start is None else start
        seen, todo = {first}, [first]
        while todo:
            for nxt in self.neighbours(todo.pop()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    def cell_center_m(self, cell: tuple[int, int]) -> tuple[float, float]:
        """World coordinates (metres) of the centre of ``cell`` (col, row)."""
        return (
            self.origin_m[0] + (cell[0] + 0.5) * self.cell_size_m,
            self.origin_m[1] + (cell[1] + 0.5) * self.cell_size_m,
        )

    def cell_at(self, x_m: float, y_m: float) -> tuple[int, int] | None:
        """The cell (col, row) containing the point, or None outside the maze."""
        col = int(np.floor((x_m - self.origin_m[0]) / self.cell_size_m))
        row = int(np.floor((y_m - self.origin_m[1]) / self.cell_size_m))
        return (col, row) if self.contains((col, row)) else None

    def wall_count(self) -> int:
        """Number of wall pieces (one cell side each), the outer boundary included."""
        return int(
            self.walls_east.sum() + self.walls_north.sum() + self.walls_west_edge.sum() + self.walls_south_edge.sum()
        )

    def wall_rectangles_m(self, wall_thickness_m: float) -> np.ndarray:
        """The walls as solid rectangles, shape (R, 4) rows ``xmin, ymin, xmax, ymax``.

        Collinear runs of walls merge into one long rectangle. Each rectangle is centred
        on its boundary line and reaches half a thickness past the post centres at both
        ends, so two walls meeting at a post close the corner.
        """
        c = self.cell_size_m
        h = wall_thickness_m / 2.0
        ox, oy = self.origin_m
        rects: list[tuple[float, float, float, float]] = []
        # Horizontal boundary lines y = j * c, j = 0..height: flags per column.
        for j in range(self.height + 1):
            flags = self.walls_south_edge if j == 0 else self.walls_north[j - 1]
            for a, b in _true_runs(flags):
                y = oy + j * c
                rects.append((ox + a * c - h, y - h, ox + b * c + h, y + h))
        # Vertical boundary lines x = i * c, i = 0..width: flags per row.
        for i in range(self.width + 1):
            flags = self.walls_west_edge if i == 0 else self.walls_east[:, i - 1]
            for a, b in _true_runs(flags):
                x = ox + i * c
                rects.append((x - h, oy + a * c - h, x + h, oy + b * c + h))
        return np.array(rects, dtype=np.float64).reshape(-1, 4)


@dataclass(frozen=True)
class World:
    """A static 2D world.

    ``segments`` are the surfaces a lidar ray can hit and the robot can touch:
    shape (N, 4) rows of ``x1, y1, x2, y2`` in metres. ``circles`` are cylinders:
    shape (M, 3) rows of ``cx, cy, radius`` in metres. ``start_pose`` is where the robot
    is put down, ``(x_m, y_m, theta_rad)``.

    Worlds built here (mazes, rooms) give closed outlines with the solid on the left of
    each segment (see the module docstring); rasterisers rely on the outlines being
    closed to fill wall interiors.
    """

    name: str
    segments: np.ndarray
    circles: np.ndarray
    start_pose: tuple[float, float, float]
    bounds_m: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    maze: MazeLayout | None = None
    meta: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        segs = np.asarray(self.segments, dtype=np.float64).reshape(-1, 4)
        circ = np.asarray(self.circles, dtype=np.float64).reshape(-1, 3)
        object.__setattr__(self, "segments", segs)
        object.__setattr__(self, "circles", circ)


def _true_runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges ``[a, b)`` of consecutive True values in a 1D bool array."""
    padded = np.concatenate(([False], np.asarray(flags, dtype=bool), [False]))
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2], strict=True)]


def rectangles_outline(rects: np.ndarray) -> np.ndarray:
    """The boundary of the union of axis-aligned rectangles, as oriented segments.

    ``rects`` is (R, 4) rows ``xmin, ymin, xmax, ymax``; the result is (N, 4) rows
    ``x1, y1, x2, y2`` with the solid on the left, collinear pieces merged. Overlaps and
    shared edges vanish: only surfaces between solid and free space remain, which is
    what a lidar can see and what the even-odd fill of a raster needs.

    Method: compress the plane to the grid of distinct rectangle edge coordinates, mark
    the grid cells inside any rectangle, then read off the edges between a solid and a
    free grid cell, merging runs along each grid line.
    """
    rects = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    if rects.shape[0] == 0:
        return np.zeros((0, 4))
    xs = np.unique(np.concatenate((rects[:, 0], rects[:, 2])))
    ys = np.unique(np.concatenate((rects[:, 1], rects[:, 3])))
    # Compressed cell (r, q) spans ys[r-1]..ys[r] by xs[q-1]..xs[q]; row/column 0 and the
    # last row/column lie outside every rectangle, so the outline always closes.
    solid = np.zeros((ys.size + 1, xs.size + 1), dtype=bool)
    x0 = np.searchsorted(xs, rects[:, 0])
    x1 = np.searchsorted(xs, rects[:, 2])
    y0 = np.searchsorted(ys, rects[:, 1])
    y1 = np.searchsorted(ys, rects[:, 3])
    for a, b, c, d in zip(y0, y1, x0, x1, strict=True):
        solid[a + 1 : b + 1, c + 1 : d + 1] = True
    out: list[np.ndarray] = []
    # Horizontal edges on line ys[k]: between compressed rows k and k+1.
    # +1: solid above (free below) -> run eastwards; -1: solid below -> run westwards.
    step_y = solid[1:, :].astype(np.int8) - solid[:-1, :].astype(np.int8)  # (ny, nx+1)
    for k in range(ys.size):
        for sign in (1, -1):
            for a, b in _true_runs(step_y[k, 1:-1] == sign):
                xa, xb = xs[a], xs[b]
                seg = (xa, ys[k], xb, ys[k]) if sign > 0 else (xb, ys[k], xa, ys[k])
                out.append(np.array(seg))
    # Vertical edges on line xs[q]: between compressed columns q and q+1.
    # +1: solid to the east -> run southwards; -1: solid to the west -> run northwards.
    step_x = solid[:, 1:].astype(np.int8) - solid[:, :-1].astype(np.int8)  # (ny+1, nx)
    for q in range(xs.size):
        for sign in (1, -1):
            for a, b in _true_runs(step_x[1:-1, q] == sign):
                ya, yb = ys[a], ys[b]
                seg = (xs[q], yb, xs[q], ya) if sign > 0 else (xs[q], ya, xs[q], yb)
                out.append(np.array(seg))
    return np.array(out, dtype=np.float64).reshape(-1, 4)


def start_heading_rad(layout: MazeLayout, cell: tuple[int, int]) -> float:
    """The heading of a robot put down in ``cell`` facing along an open side.

    Sides leading into the maze win over open sides on the outer boundary (facing out of
    the maze is never useful); among equals the order is N, E, W, S, so a micromouse
    start cell (open only to the north) gives pi/2. A cell closed on all four sides
    faces north.
    """
    open_sides = layout.open_sides(cell)
    inward = [s for s in open_sides if layout.contains((cell[0] + SIDE_STEP[s][0], cell[1] + SIDE_STEP[s][1]))]
    for candidates in (inward, open_sides):
        for side in "NEWS":
            if side in candidates:
                return float(SIDE_HEADING_RAD[side])
    return float(SIDE_HEADING_RAD["N"])


def world_from_layout(layout: MazeLayout, wall_thickness_m: float = 0.012, name: str = "maze") -> World:
    """The world of a maze: wall outlines as segments, the robot in the start cell.

    Each wall is a rectangle ``wall_thickness_m`` thick centred on its cell boundary
    (see :meth:`MazeLayout.wall_rectangles_m`); the world keeps the outline of their
    union. The robot starts at the start cell's centre facing along an open side (see
    :func:`start_heading_rad`).
    """
    if not 0.0 < wall_thickness_m < layout.cell_size_m:
        raise ValueError(f"wall thickness must be in (0, cell size {layout.cell_size_m} m), got {wall_thickness_m} m")
    segments = rectangles_outline(layout.wall_rectangles_m(wall_thickness_m))
    x, y = layout.cell_center_m(layout.start_cell)
    theta = start_heading_rad(layout, layout.start_cell)
    h = wall_thickness_m / 2.0
    ox, oy = layout.origin_m
    bounds = (
        ox - h,
        oy - h,
        ox + layout.width * layout.cell_size_m + h,
        oy + layout.height * layout.cell_size_m + h,
    )
    return World(
        name=name,
        segments=segments,
        circles=np.zeros((0, 3)),
        start_pose=(x, y, theta),
        bounds_m=bounds,
        maze=layout,
        meta={"wall_thickness_m": wall_thickness_m, "cell_size_m": layout.cell_size_m},
    )
