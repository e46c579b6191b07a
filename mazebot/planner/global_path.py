"""Global paths: shortest routes on the maze's cell graph, and on an inflated grid.

In a maze the global planner works on the cell graph (:mod:`mazebot.planner.maze_graph`):
every open link joins two cell centres by a straight line (Nayak et al., "2D Autonomous Mapping", III.C), so a
route is a list of cells. :func:`shortest_cell_path` is A* (Hart, Nilsson & Raphael
1968) with the Manhattan heuristic over states (cell, heading), which lets a turn cost
extra: an in-place turn takes as long as driving a fair part of a cell, and a route
with fewer turns is faster even when it is as long. :func:`merge_straight` then keeps
only the cells where the route changes direction, so the local planner drives each
corridor as one straight segment.

Worlds that are not cell mazes (a room with cylinders) are planned on the occupancy
grid itself: :class:`GridCostmap` inflates the occupied cells by the robot's footprint
radius plus clearance (the configuration space of a round robot is the free space
shrunk by its radius, Lozano-Pérez 1983), adds a cost that falls off away from the
walls so paths keep to the middle, and :meth:`GridCostmap.plan` runs scipy's Dijkstra
on the 8-connected grid; :func:`shortcut` removes the staircase with line-of-sight checks.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from mazebot.config import RobotConfig
from mazebot.slam.grid import FREE, OCCUPIED

# the defaults below are the config's, each written once in mazebot.config
_ROBOT = RobotConfig()

Cell = tuple[int, int]
Neighbours = Callable[[Cell], Iterable[Cell]]
"""``open_neighbours(cell)``: the cells a robot can drive to from ``cell`` in one step."""

_DIRS: tuple[Cell, ...] = ((1, 0), (0, 1), (-1, 0), (0, -1))


def _turns(a: int, b: int) -> int:
    """Quarter turns between two of the four directions (0, 1 or 2)."""
    d = (b - a) % 4
    return min(d, 4 - d)


def cell_costs(
    neighbours: Neighbours,
    start: Cell,
    start_heading: int | None = None,
    turn_cost: float = 0.0,
) -> dict[Cell, float]:
    """Cost of the cheapest route from ``start`` to every reachable cell (Dijkstra).

    One step between cells costs 1; each quarter turn costs ``turn_cost`` more (in cell
    steps). ``start_heading`` (0 E, 1 N, 2 W, 3 S, the index of
    :class:`~mazebot.planner.maze_graph.Direction`) is the robot's current facing; None
    makes the first move free of turn cost.
    """
    best: dict[Cell, float] = {start: 0.0}
    settled: dict[tuple[Cell, int | None], float] = {}
    heap: list[tuple[float, Cell, int]] = []
    heapq.heappush(heap, (0.0, start, -1 if start_heading is None else start_heading))
    while heap:
        cost, cell, heading = heapq.heappop(heap)
        if (cell, heading) in settled:
            continue
        settled[(cell, heading)] = cost
        best[cell] = min(best.get(cell, math.inf), cost)
        for nxt in neighbours(cell):
            d = _DIRS.index((nxt[0] - cell[0], nxt[1] - cell[1]))
            step = 1.0 + (0.0 if heading < 0 else turn_cost * _turns(heading, d))
            if (nxt, d) not in settled:
                heapq.heappush(heap, (cost + step, nxt, d))
    return best


def shortest_cell_path(
    neighbours: Neighbours,
    start: Cell,
    goal: Cell,
    start_heading: int | None = None,
    turn_cost: float = 0.0,
) -> list[Cell] | None:
    """The cheapest route ``[start, ..., goal]`` through open links, or None if unreachable.

    A* over (cell, heading) states: step cost 1 per cell plus ``turn_cost`` per quarter
    turn (see :func:`cell_costs`); the Manhattan distance never overestimates, so the
    route is optimal for that cost.
    """
    if start == goal:
        return [start]
    h0 = -1 if start_heading is None else start_heading
    heap: list[tuple[float, float, Cell, int]] = [(_manhattan(start, goal), 0.0, start, h0)]
    parent: dict[tuple[Cell, int], tuple[Cell, int] | None] = {(start, h0): None}
    cost_so_far: dict[tuple[Cell, int], float] = {(start, h0): 0.0}
    closed: set[tuple[Cell, int]] = set()
    while heap:
        _, cost, cell, heading = heapq.heappop(heap)
        state = (cell, heading)
        if state in closed:
            continue
        closed.add(state)
        if cell == goal:
            route = []
            node: tuple[Cell, int] | None = state
            while node is not None:
                route.append(node[0])
                node = parent[node]
            return route[::-1]
        for nxt in neighbours(cell):
            d = _DIRS.index((nxt[0] - cell[0], nxt[1] - cell[1]))
            new_cost = cost + 1.0 + (0.0 if heading < 0 else turn_cost * _turns(heading, d))
            key = (nxt, d)
            if new_cost < cost_so_far.get(key, math.inf):
                cost_so_far[key] = new_cost
                parent[key] = state
                heapq.heappush(heap, (new_cost + _manhattan(nxt, goal), new_cost, nxt, d))
    return None


def _manhattan(a: Cell, b: Cell) -> float:
    return float(abs(a[0] - b[0]) + abs(a[1] - b[1]))


def merge_straight(cells: Sequence[Cell]) -> list[Cell]:
    """Keep the first and last cell and every cell where the route turns.

    The cells in the middle of a straight run are dropped: the local planner drives
    the run as one segment instead of stopping at each centre.

    >>> merge_straight([(0, 0), (0, 1), (0, 2), (1, 2)])
    [(0, 0), (0, 2), (1, 2)]
    """
    if len(cells) < 3:
        return list(cells)
    out = [cells[0]]
    for prev, cell, nxt in zip(cells, cells[1:], cells[2:], strict=False):
        if (cell[0] - prev[0], cell[1] - prev[1]) != (nxt[0] - cell[0], nxt[1] - cell[1]):
            out.append(cell)
    out.append(cells[-1])
    return out


def cell_waypoints(cells: Sequence[Cell], center_m: Callable[[Cell], tuple[float, float]]) -> list[tuple[float, float]]:
    """Map-frame waypoints (metres) of a merged cell route, e.g. ``frame.cell_center_m``."""
    return [center_m(c) for c in cells]


# -- grid planning -------------------------------------------------------------------------

_NEIGHBOURS_8: tuple[tuple[int, int, float], ...] = (
    (0, 1, 1.0),
    (1, 0, 1.0),
    (0, -1, 1.0),
    (-1, 0, 1.0),
    (1, 1, math.sqrt(2.0)),
    (1, -1, math.sqrt(2.0)),
    (-1, 1, math.sqrt(2.0)),
    (-1, -1, math.sqrt(2.0)),
)


class GridCostmap:
    """The occupancy grid as a configuration-space costmap for a round robot.

    Example::

        costmap = GridCostmap(grid.three_state(), grid.origin_m, grid.resolution_m)
        path_m = costmap.plan((0.0, 0.0), (1.2, 0.4))        # [(x, y), ...] or None
        waypoints_m = shortcut(path_m, costmap)

    A cell is *passable* when it is known free and farther than
    ``footprint_radius_m + clearance_m`` (metres) from every occupied cell (and, unless
    ``unknown_is_free``, from every unknown one — the robot never plans through space it
    has not seen). Stepping onto a cell costs its length times
    ``1 + wall_cost * exp(-(d - r) / wall_decay_m)``, where ``d`` is the distance to the
    nearest obstacle and ``r`` the inflation radius: paths keep away from walls where
    there is room. ``clearance_m_grid`` is ``d`` in metres, for the callers that need it.
    ``closed_cells`` (a mask of the grid's shape) marks cells blocked as if occupied: the
    passages the robot could not take (:mod:`mazebot.planner.passages`).
    """

    def __init__(
        self,
        three_state: np.ndarray,
        origin_m: tuple[float, float],
        resolution_m: float,
        footprint_radius_m: float = _ROBOT.footprint_radius_m,
        clearance_m: float = _ROBOT.clearance_m,
        wall_cost: float = 4.0,
        wall_decay_m: float = 0.05,
        unknown_is_free: bool = False,
        closed_cells: np.ndarray | None = None,
    ) -> None:
        grid = np.asarray(three_state)
        self.origin_m = (float(origin_m[0]), float(origin_m[1]))
        self.resolution_m = float(resolution_m)
        self.inflation_m = float(footprint_radius_m + clearance_m)
        blocked = grid == OCCUPIED
        if closed_cells is not None:  # passages the robot could not take, as walls (:mod:`.passages`)
            blocked = blocked | closed_cells
        if not unknown_is_free:
            blocked = blocked | (grid != FREE)
        self.known_free = grid == FREE
        # distance (metres) from each cell centre to the nearest blocked cell centre
        if blocked.any():
            self.clearance_m_grid = ndimage.distance_transform_edt(~blocked) * self.resolution_m
        else:
            self.clearance_m_grid = np.full(grid.shape, np.inf)
        self.passable = (self.clearance_m_grid > self.inflation_m) & (self.known_free | unknown_is_free)
        excess = np.clip(self.clearance_m_grid - self.inflation_m, 0.0, None)
        self.step_cost = 1.0 + wall_cost * np.exp(-excess / wall_decay_m)
        self._graph: csr_matrix | None = None
        self._search: tuple[tuple[int, int], np.ndarray, np.ndarray] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.passable.shape

    def to_cell(self, x_m: float, y_m: float) -> tuple[int, int]:
        """(row, col) of the grid cell holding ``(x_m, y_m)``; may lie off the grid."""
        return (
            math.floor((y_m - self.origin_m[1]) / self.resolution_m),
            math.floor((x_m - self.origin_m[0]) / self.resolution_m),
        )

    def to_world(self, row: float, col: float) -> tuple[float, float]:
        """Map coordinates (metres) of a grid cell's centre (or of a fractional row and column)."""
        return (
            self.origin_m[0] + (col + 0.5) * self.resolution_m,
            self.origin_m[1] + (row + 0.5) * self.resolution_m,
        )

    def contains(self, row: int, col: int) -> bool:
        return 0 <= row < self.shape[0] and 0 <= col < self.shape[1]

    def nearest_passable(self, row: int, col: int, max_radius_cells: int = 10) -> tuple[int, int] | None:
        """The passable cell nearest to ``(row, col)`` within a square window, or None.

        The robot's own cell can fail the inflation test (it may stand a little closer to
        a wall than the planning margin); plans then start from the nearest cell that
        passes.
        """
        if self.contains(row, col) and self.passable[row, col]:
            return (row, col)
        r0, r1 = max(row - max_radius_cells, 0), min(row + max_radius_cells + 1, self.shape[0])
        c0, c1 = max(col - max_radius_cells, 0), min(col + max_radius_cells + 1, self.shape[1])
        if r0 >= r1 or c0 >= c1:
            return None
        rr, cc = np.nonzero(self.passable[r0:r1, c0:c1])
        if rr.size == 0:
            return None
        k = int(np.argmin((rr + r0 - row) ** 2 + (cc + c0 - col) ** 2))
        return (int(rr[k] + r0), int(cc[k] + c0))

    def plan(self, start_xy_m: tuple[float, float], goal_xy_m: tuple[float, float]) -> list[tuple[float, float]] | None:
        """Cheapest path from start to goal over passable cells: map-frame points (metres), or None.

        Both ends snap to the nearest passable cell. The search is the single-source
        Dijkstra of :meth:`distances_from` (compiled, and already run from the robot's
        cell when frontiers were just ranked from there): a Python A* over the same cells
        cost 35 ms a plan in the room world, longer than a control period.
        """
        start = self.nearest_passable(*self.to_cell(*start_xy_m))
        goal = self.nearest_passable(*self.to_cell(*goal_xy_m))
        if start is None or goal is None:
            return None
        _, predecessors = self._search_from(start)
        cols = self.shape[1]
        node, first = goal[0] * cols + goal[1], start[0] * cols + start[1]
        cells = [goal]
        while node != first:
            node = int(predecessors[node])
            if node < 0:  # scipy marks cells it never reached with -9999
                return None
            cells.append(divmod(node, cols))
        return [self.to_world(r, c) for r, c in reversed(cells)]

    def distances_from(self, xy_m: tuple[float, float]) -> np.ndarray:
        """Path cost (cell-length units) from ``xy_m`` to every cell; inf where unreachable.

        One Dijkstra over the passable cells (scipy's compiled implementation), for
        choosing among many goals at once (frontiers).
        """
        rows, cols = self.shape
        start = self.nearest_passable(*self.to_cell(*xy_m))
        if start is None:
            return np.full((rows, cols), np.inf)
        distances, _ = self._search_from(start)
        return distances.reshape(rows, cols)

    def _search_from(self, start: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Costs and predecessors of every cell from ``start`` (row, col), kept for the next call."""
        if self._search is not None and self._search[0] == start:
            return self._search[1], self._search[2]
        if self._graph is None:
            self._graph = self._build_graph()
        distances, predecessors = dijkstra(
            self._graph, directed=True, indices=start[0] * self.shape[1] + start[1], return_predecessors=True
        )
        self._search = (start, np.asarray(distances), np.asarray(predecessors))
        return self._search[1], self._search[2]

    def _build_graph(self) -> csr_matrix:
        """The 8-connected passable cells as a sparse weighted digraph (vectorised)."""
        rows, cols = self.shape
        idx = np.arange(rows * cols).reshape(rows, cols)
        src, dst, weight = [], [], []
        for dr, dc, length in _NEIGHBOURS_8:
            r0, r1 = max(0, -dr), rows - max(0, dr)
            c0, c1 = max(0, -dc), cols - max(0, dc)
            a = self.passable[r0:r1, c0:c1]
            b = self.passable[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
            ok = a & b
            if dr and dc:
                ok &= self.passable[r0 + dr : r1 + dr, c0:c1] & self.passable[r0:r1, c0 + dc : c1 + dc]
            src.append(idx[r0:r1, c0:c1][ok])
            dst.append(idx[r0 + dr : r1 + dr, c0 + dc : c1 + dc][ok])
            weight.append(length * self.step_cost[r0 + dr : r1 + dr, c0 + dc : c1 + dc][ok])
        return csr_matrix(
            (np.concatenate(weight), (np.concatenate(src), np.concatenate(dst))), shape=(rows * cols, rows * cols)
        )

    def segment_passable(self, a_m: tuple[float, float], b_m: tuple[float, float]) -> bool:
        """True when every cell along the straight segment a→b is passable."""
        return bool(self.segments_passable(a_m, [b_m])[0])

    def segments_passable(self, a_m: tuple[float, float], ends_m: Sequence[tuple[float, float]]) -> np.ndarray:
        """For each end ``b``: True when every cell along the straight segment a→b is passable.

        The segment is sampled every half grid cell, both ends included (the points of
        ``np.linspace(0, 1, n)``: ``k`` times the step, the last exactly 1). All segments
        are walked out from ``a`` together, a few samples at a time, and a segment is
        dropped at its first sample in a blocked cell: from a point in a 1 ft corridor
        most later points of a path are behind a wall a few centimetres away, so most
        segments are decided by their first samples (the same samples and answers as
        checking each segment whole, at a fraction of the cost).
        """
        ax, ay = float(a_m[0]), float(a_m[1])
        dx_list = [float(b[0]) - ax for b in ends_m]
        dy_list = [float(b[1]) - ay for b in ends_m]
        half = 0.5 * self.resolution_m
        lengths = [math.hypot(x, y) for x, y in zip(dx_list, dy_list, strict=True)]
        counts = np.array([max(2, math.ceil(length / half) + 1) for length in lengths], dtype=np.int64)
        alive = np.ones(counts.size, dtype=bool)
        if counts.size == 0:
            return alive
        dx, dy = np.array(dx_list), np.array(dy_list)
        step = 1.0 / (counts - 1)
        rows, cols = self.shape
        first, width = 0, SEGMENT_SAMPLES_FIRST
        while True:
            todo = np.flatnonzero(alive & (counts > first))
            if todo.size == 0:
                return alive
            n = counts[todo, None]
            k = np.arange(first, first + width, dtype=np.int64)[None, :]
            t = np.where(k == n - 1, 1.0, k.astype(np.float64) * step[todo, None])
            x = ax + t * dx[todo, None]
            y = ay + t * dy[todo, None]
            c = np.floor((x - self.origin_m[0]) / self.resolution_m).astype(np.int64)
            r = np.floor((y - self.origin_m[1]) / self.resolution_m).astype(np.int64)
            inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
            ok = inside.copy()
            ok[inside] = self.passable[r[inside], c[inside]]
            ok |= k >= n  # past a segment's end: nothing to check
            alive[todo] = ok.all(axis=1)
            first += width
            width *= 2


#: Samples per segment in :meth:`GridCostmap.segments_passable`'s first round (each next one twice as many).
SEGMENT_SAMPLES_FIRST = 16


def shortcut(path_m: Sequence[tuple[float, float]], costmap: GridCostmap) -> list[tuple[float, float]]:
    """Drop the points a straight passable segment can skip (greedy line of sight).

    From each kept point, jump to the farthest later point still visible through
    passable cells: a grid staircase becomes a few straight segments. Every later point
    is asked at once (:meth:`GridCostmap.segments_passable`; a 16x16 maze's grid path
    has hundreds of points, and one numpy call per segment cost a quarter of a planner
    tick there).
    """
    if len(path_m) < 3:
        return list(path_m)
    out = [path_m[0]]
    i = 0
    last = len(path_m) - 1
    while i < last:
        j = i + 1  # the next point is always taken: it is the path's own step
        if i + 2 <= last:
            visible = np.flatnonzero(costmap.segments_passable(path_m[i], path_m[i + 2 :]))
            if visible.size:
                j = i + 2 + int(visible[-1])
        out.append(path_m[j])
        i = j
    return out
