"""The maze as a graph: one node per cell centre, one link per pair of neighbouring cells.

Why one module of ~880 lines: the maze frame (direction, pitch and phase of the wall lattice,
:func:`estimate_frame`) and the graph built on it change together: the graph re-anchors its
cells whenever the frame is refined (:func:`_shifted`), and both read the same three-state grid
through the same cell samples (:class:`_SampleCells`).

The planner does not search the occupancy grid cell by cell: a maze of 1 ft squares is a
graph of a few hundred nodes, and Nayak et al., *2D Autonomous Mapping* (III.C "graph builder"), puts a
waypoint at every cell centre and links neighbouring waypoints whose boundary is open.
This module builds that graph from the three-state grid SLAM publishes (−1 unknown,
0 free, 100 occupied; row 0 south) in three steps:

1. **Maze frame** (:func:`estimate_frame`). The robot is put down at an arbitrary angle,
   so the map frame (the start pose) is not the maze's. The walls say where the maze
   is: the dominant wall direction comes from the structure tensor of the occupied
   mask (the local gradient orientation, folded modulo 90° so both wall families vote
   for the same angle; Bigün & Granlund 1987); the cell phase along each axis is the
   circular mean of the wall positions of that family modulo the cell size; then a few
   least-squares steps fit angle and phases so the walls lie on the lattice lines
   (point-to-line ICP against the lattice). With ``pitch_search`` the pitch itself is
   measured from the walls too (:func:`mazebot.slam.lattice_fit.fit_pitch`: a maze built
   by hand is a few per cent off the configured cell size), once the walls show enough
   lattice lines; until then the configured one stands. Cell (0, 0) is the cell holding
   the start pose.

2. **Links** (:meth:`MazeGraph.update`). Each boundary between neighbouring cells is
   sampled along its middle part (the posts at its ends are left out) and a little to
   either side of the line; it is a **wall** when enough of it is occupied, **open**
   when it is known free from end to end, and **unknown** otherwise.

3. **Cell kinds** (:meth:`MazeGraph.kind`): dead ends (one open link), corridors (two),
   junctions (three or four), open areas (part of a 2×2 block of mutually open cells)
   and unexplored cells (a link still unknown, or the inside of the cell not yet seen:
   a dead end looked at only through its opening has unmapped corners).

The graph is updated in place as the map grows: the frame is kept while the walls
agree with it (re-estimated when the wall count has grown by a set fraction, and
re-anchored so cell indices stay put), the cell range grows with the map, and every
update reports the links whose state changed.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from mazebot.config import MAZE_CELL_M, PlannerConfig
from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN
from mazebot.slam.lattice_fit import fit_pitch

# the defaults below are the config's, each written once in mazebot.config
_PLANNER = PlannerConfig()

Cell = tuple[int, int]
"""A maze cell ``(i, j)``: ``i`` counts cells along the maze's u axis, ``j`` along v."""


class Direction(enum.IntEnum):
    """The four sides of a cell, counter-clockwise from +u (the maze's "east")."""

    E = 0
    N = 1
    W = 2
    S = 3

    @property
    def step(self) -> Cell:
        """``(di, dj)`` to the neighbour on this side."""
        return _STEPS[self]

    @property
    def opposite(self) -> Direction:
        return Direction((self + 2) % 4)

    @classmethod
    def between(cls, a: Cell, b: Cell) -> Direction:
        """The side of ``a`` that faces its neighbour ``b``."""
        step = (b[0] - a[0], b[1] - a[1])
        for d, s in _STEPS.items():
            if s == step:
                return d
        raise ValueError(f"cells {a} and {b} are not neighbours")


_STEPS: dict[Direction, Cell] = {Direction.E: (1, 0), Direction.N: (0, 1), Direction.W: (-1, 0), Direction.S: (0, -1)}
#: The sides in the order ``Direction`` iterates (a tuple: iterating an enum class is slow in a hot loop).
_DIRECTIONS: tuple[Direction, ...] = tuple(Direction)


class LinkState(enum.IntEnum):
    """What is known about the boundary between two neighbouring cells."""

    UNKNOWN = 0
    OPEN = 1
    WALL = 2


#: ``LinkState(v)`` by value: an index instead of the enum's constructor on the planner's hot path.
_LINK_STATES: tuple[LinkState, ...] = tuple(LinkState(v) for v in range(len(LinkState)))


class CellKind(enum.StrEnum):
    """The role of a cell in the maze, from its links."""

    UNEXPLORED = "unexplored"  # at least one link still unknown
    ENCLOSED = "enclosed"  # all four links walls (outside the maze, or a closed box)
    DEAD_END = "dead_end"  # one open link
    CORRIDOR = "corridor"  # two open links (straight or a corner)
    JUNCTION = "junction"  # three or four open links
    OPEN_AREA = "open_area"  # part of a 2x2 block of cells open to each other (no post between)


# -- the maze frame --------------------------------------------------------------------------


@dataclass(frozen=True)
class MazeFrame:
    """Where the maze lattice lies in the map frame.

    The maze axes (u, v) are the map axes rotated by ``angle_rad``; ``origin_m`` is the
    map position of the lattice corner (a post) south-west of cell (0, 0) in maze terms,
    so cell (i, j) spans ``u in [i, i + 1) * cell_size_m``, ``v in [j, j + 1) * cell_size_m``
    measured from the origin.

    >>> frame = MazeFrame(0.0, (0.0, 0.0), 0.3)
    >>> frame.cell_of(0.45, 0.1), frame.cell_center_m((1, 0))
    ((1, 0), (0.45, 0.15))
    """

    angle_rad: float
    origin_m: tuple[float, float]
    cell_size_m: float

    def to_maze(self, xy: np.ndarray) -> np.ndarray:
        """Map points (N, 2) in metres to maze coordinates (N, 2): metres along u and v from the origin."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - np.asarray(self.origin_m)
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        return np.column_stack((c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1]))

    def to_map(self, uv: np.ndarray) -> np.ndarray:
        """Maze coordinates (N, 2) back to map points (N, 2) in metres."""
        q = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        return np.column_stack((c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1])) + np.asarray(self.origin_m)

    def cell_of(self, x_m: float, y_m: float) -> Cell:
        """The cell holding map point ``(x_m, y_m)``."""
        u, v = self.to_maze(np.array([x_m, y_m]))[0] / self.cell_size_m
        return (math.floor(u), math.floor(v))

    def cell_center_m(self, cell: Cell) -> tuple[float, float]:
        """Map coordinates (metres) of the centre of ``cell``: the waypoint."""
        x, y = self.to_map(np.array([(cell[0] + 0.5) * self.cell_size_m, (cell[1] + 0.5) * self.cell_size_m]))[0]
        return (float(x), float(y))

    def heading_rad(self, direction: Direction) -> float:
        """Map-frame heading of a robot facing out of a cell through ``direction``."""
        return math.remainder(self.angle_rad + direction * math.pi / 2, math.tau)


@dataclass(frozen=True)
class FrameEstimate:
    """A maze frame with the evidence behind it.

    ``fit`` is the fraction of wall cells lying on a lattice line (≈1 in a maze, clearly
    less in a room with round obstacles: the explorer's maze-or-not test); ``support``
    the number of wall cells used.
    """

    frame: MazeFrame
    fit: float
    support: int


def estimate_frame(
    three_state: np.ndarray,
    grid_origin_m: tuple[float, float],
    resolution_m: float,
    cell_size_m: float = MAZE_CELL_M,
    anchor_xy_m: tuple[float, float] = (0.0, 0.0),
    prior_angle_rad: float | None = None,
    line_tolerance_m: float = 0.03,
    min_support: int = 20,
    pitch_search: float = 0.0,
) -> FrameEstimate | None:
    """The maze lattice that best explains the occupied cells, or None without enough walls.

    ``three_state`` is the SLAM grid (int8, row 0 south) whose cell (0, 0) has its
    south-west corner at ``grid_origin_m``. The cell holding ``anchor_xy_m`` (the start
    pose) becomes cell (0, 0). Angles are ambiguous modulo 90°; the representative
    closest to ``prior_angle_rad`` is returned (in (−45°, 45°] without a prior), so cell
    indices do not swap axes between updates. ``line_tolerance_m`` is how far a wall
    cell may lie from a lattice line and still count for ``fit``; fewer than
    ``min_support`` wall cells give None. ``pitch_search`` (a share of ``cell_size_m``,
    0: none) is how far from ``cell_size_m`` the pitch is looked for; the frame's
    ``cell_size_m`` is the pitch found (``cell_size_m`` while the walls do not measure it).
    """
    occupied = np.asarray(three_state) == OCCUPIED
    rows, cols = np.nonzero(occupied)
    if rows.size < min_support:
        return None
    xy = np.column_stack(
        (grid_origin_m[0] + (cols + 0.5) * resolution_m, grid_origin_m[1] + (rows + 0.5) * resolution_m)
    )
    normal_rad, weight = _wall_normals(occupied, rows, cols)

    # 1. Dominant direction: histogram of the normals folded modulo 90 degrees (4 phi).
    angle = _dominant_angle(normal_rad, weight)
    if prior_angle_rad is not None:
        angle += math.pi / 2 * round((prior_angle_rad - angle) / (math.pi / 2))
    else:
        angle = math.remainder(angle, math.pi / 2)
        if angle <= -math.pi / 4 + 1e-12:
            angle += math.pi / 2

    # 2. Phase: circular mean, modulo the cell size, of the positions of each wall family.
    across_u = np.abs(np.cos(normal_rad - angle))  # 1 for a wall whose normal is along u
    w_u = weight * (across_u > math.cos(math.radians(25)))
    w_v = weight * (across_u < math.sin(math.radians(25)))
    c, s = math.cos(angle), math.sin(angle)
    if pitch_search > 0:
        # both faces of a wall pooled: a grid cell's quantisation (a resolution step) is noisier than the
        # half thickness between a wall's faces, and once explored most walls are mapped from both sides
        u0, v0 = c * xy[:, 0] + s * xy[:, 1], -s * xy[:, 0] + c * xy[:, 1]
        classes = [(u0[w_u > 0], w_u[w_u > 0], 0), (v0[w_v > 0], w_v[w_v > 0], 1)]
        pitch = fit_pitch(classes, cell_size_m, search=pitch_search,
                          tolerance_m=max(line_tolerance_m, 2.0 * resolution_m))
        if pitch.measured:
            cell_size_m = pitch.pitch_m
    phase_u = _circular_phase(c * xy[:, 0] + s * xy[:, 1], w_u, cell_size_m)
    phase_v = _circular_phase(-s * xy[:, 0] + c * xy[:, 1], w_v, cell_size_m)

    # 3. Refinement: least-squares fit of the lattice lines to the walls.
    angle, phase_u, phase_v = _refine_lattice(
        xy, w_u, w_v, angle, phase_u, phase_v, cell_size_m, max(line_tolerance_m, 2.0 * resolution_m)
    )
    c, s = math.cos(angle), math.sin(angle)
    u = c * xy[:, 0] + s * xy[:, 1]
    v = -s * xy[:, 0] + c * xy[:, 1]

    # 4. Anchor: the lattice corner south-west of the anchor's cell.
    ua = c * anchor_xy_m[0] + s * anchor_xy_m[1]
    va = -s * anchor_xy_m[0] + c * anchor_xy_m[1]
    corner_u = phase_u + math.floor((ua - phase_u) / cell_size_m) * cell_size_m
    corner_v = phase_v + math.floor((va - phase_v) / cell_size_m) * cell_size_m
    origin = (c * corner_u - s * corner_v, s * corner_u + c * corner_v)

    off_u = np.abs(np.remainder(u - phase_u + cell_size_m / 2, cell_size_m) - cell_size_m / 2)
    off_v = np.abs(np.remainder(v - phase_v + cell_size_m / 2, cell_size_m) - cell_size_m / 2)
    fit = float(np.mean(np.minimum(off_u, off_v) <= line_tolerance_m))
    return FrameEstimate(
        MazeFrame(float(angle), (float(origin[0]), float(origin[1])), cell_size_m), fit, int(rows.size)
    )


def _wall_normals(occupied: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normal direction (radians, modulo pi) and coherence weight at each occupied cell.

    Structure tensor ``J = G * (grad I grad I^T)`` of the lightly smoothed occupied mask;
    its main eigenvector is the wall normal, even on the centre line of a one-cell-thick
    wall where the gradient itself vanishes. The coherence ``(l1 − l2) / (l1 + l2)``
    is ~1 along straight walls and low at posts and corners, which then barely vote.
    """
    image = ndimage.gaussian_filter(occupied.astype(np.float64), 1.0)
    gx = ndimage.sobel(image, axis=1)
    gy = ndimage.sobel(image, axis=0)
    jxx = ndimage.gaussian_filter(gx * gx, 2.0)[rows, cols]
    jyy = ndimage.gaussian_filter(gy * gy, 2.0)[rows, cols]
    jxy = ndimage.gaussian_filter(gx * gy, 2.0)[rows, cols]
    normal = 0.5 * np.arctan2(2.0 * jxy, jxx - jyy)
    trace = jxx + jyy
    coherence = np.divide(np.hypot(jxx - jyy, 2.0 * jxy), trace, out=np.zeros_like(trace), where=trace > 1e-12)
    return normal, coherence


def _dominant_angle(normal_rad: np.ndarray, weight: np.ndarray, bins: int = 180) -> float:
    """The wall direction modulo 90° with the most weight: histogram peak, then circular mean near it."""
    folded = np.remainder(4.0 * normal_rad, math.tau)  # both wall families fold onto one angle
    hist, edges = np.histogram(folded, bins=bins, range=(0.0, math.tau), weights=weight)
    smooth = ndimage.uniform_filter1d(hist, 5, mode="wrap")
    peak = 0.5 * (edges[np.argmax(smooth)] + edges[np.argmax(smooth) + 1])
    near = np.abs(np.remainder(folded - peak + math.pi, math.tau) - math.pi) < math.radians(40)
    z = np.sum(weight[near] * np.exp(1j * folded[near]))
    return float(np.angle(z) / 4.0) if abs(z) > 0 else float(peak / 4.0)


def _refine_lattice(
    xy: np.ndarray,
    weight_u: np.ndarray,
    weight_v: np.ndarray,
    angle_rad: float,
    phase_u_m: float,
    phase_v_m: float,
    cell_size_m: float,
    tolerance_m: float,
    iterations: int = 3,
) -> tuple[float, float, float]:
    """Least-squares lattice fit: the angle and phases that put the walls on the lattice lines.

    Each wall cell of the u family is assigned to its nearest line ``u = phase_u + k c``
    (v family likewise) and the small rotation ``δ`` and phase shifts are solved from
    the linearised residuals (``u(θ + δ) ≈ u + δ v``, ``v(θ + δ) ≈ v − δ u``), a few
    Gauss-Newton steps of point-to-line ICP against the lattice. Cells farther than
    ``tolerance_m`` from their line (posts, clutter) are left out of each step. Unlike a
    projection-profile search this is not biased by the grid's own diagonals.
    """
    centre = xy.mean(axis=0)
    p = xy - centre  # rotate about the centroid: angle and phase decouple better
    c0, s0 = math.cos(angle_rad), math.sin(angle_rad)
    # phases are given for the un-centred coordinates; move them to the centred ones
    pu = phase_u_m - (c0 * centre[0] + s0 * centre[1])
    pv = phase_v_m - (-s0 * centre[0] + c0 * centre[1])
    angle = angle_rad
    for _ in range(iterations):
        c, s = math.cos(angle), math.sin(angle)
        u = c * p[:, 0] + s * p[:, 1]
        v = -s * p[:, 0] + c * p[:, 1]
        ru = u - pu - np.round((u - pu) / cell_size_m) * cell_size_m
        rv = v - pv - np.round((v - pv) / cell_size_m) * cell_size_m
        use_u = (weight_u > 0) & (np.abs(ru) <= tolerance_m)
        use_v = (weight_v > 0) & (np.abs(rv) <= tolerance_m)
        if use_u.sum() < 3 or use_v.sum() < 3:
            break
        # unknowns (delta, d_pu, d_pv): ru + delta v - d_pu = 0, rv - delta u - d_pv = 0
        a = np.zeros((int(use_u.sum() + use_v.sum()), 3))
        b = np.concatenate((-ru[use_u], -rv[use_v]))
        wts = np.sqrt(np.concatenate((weight_u[use_u], weight_v[use_v])))
        nu = int(use_u.sum())
        a[:nu, 0], a[:nu, 1] = v[use_u], -1.0
        a[nu:, 0], a[nu:, 2] = -u[use_v], -1.0
        sol, *_ = np.linalg.lstsq(a * wts[:, None], b * wts, rcond=None)
        angle += float(sol[0])
        pu += float(sol[1])
        pv += float(sol[2])
    c, s = math.cos(angle), math.sin(angle)
    phase_u = pu + c * centre[0] + s * centre[1]
    phase_v = pv - s * centre[0] + c * centre[1]
    return angle, float(np.remainder(phase_u, cell_size_m)), float(np.remainder(phase_v, cell_size_m))


def _circular_phase(position_m: np.ndarray, weight: np.ndarray, period_m: float) -> float:
    """Weighted circular mean of positions modulo ``period_m``, in [0, period_m)."""
    z = np.sum(weight * np.exp(2j * math.pi * position_m / period_m))
    if abs(z) == 0:
        return 0.0
    return float(np.remainder(np.angle(z) / (2 * math.pi) * period_m, period_m))


# -- the graph -------------------------------------------------------------------------------


@dataclass(frozen=True)
class GraphUpdate:
    """What one :meth:`MazeGraph.update` changed.

    ``changed_links`` lists ``(cell, direction, new_state)`` for every link whose state
    differs from the previous update (each link once, from its west or south cell);
    ``frame_changed`` is True when the lattice was (re)estimated.
    """

    changed_links: list[tuple[Cell, Direction, LinkState]] = field(default_factory=list)
    frame_changed: bool = False


class MazeGraph:
    """Cell-centre waypoints and classified links, kept up to date from the occupancy grid.

    Example::

        graph = MazeGraph(cell_size_m=0.3048)
        graph.update(grid.three_state(), grid.origin_m, grid.resolution_m)
        graph.link((0, 0), Direction.N)          # LinkState.OPEN / WALL / UNKNOWN
        graph.open_neighbours((0, 0))           # [(0, 1)]
        graph.kind((0, 0))                      # CellKind.DEAD_END
        graph.frame.cell_center_m((0, 1))        # waypoint in the map frame

    Parameters (metres unless named otherwise): ``cell_size_m`` the maze pitch;
    ``wall_thickness_m`` the nominal wall thickness (widens the lattice-line tolerance);
    ``anchor_xy_m`` the start pose, whose cell is (0, 0); ``post_margin`` the fraction of
    a boundary left out at each end (posts, wall ends and blur live there);
    ``samples_along`` / ``across_m`` how densely a boundary is sampled along and how far
    either side of the lattice line; ``wall_fraction`` the share of along-samples that
    must see an occupied cell for a wall; ``open_fraction`` the share that must be free
    for an open link (with nothing occupied); ``refresh_growth`` the relative growth of
    the wall count that triggers a new frame estimate; ``interior_samples`` the side of
    the grid of points (``n x n``) probed inside each cell and ``interior_seen_min`` the
    share of them the map must know for the cell to count as seen; ``cell_kept_m`` how
    far a re-estimated frame may move the cells and still keep what was learnt about
    them (the seen shares); ``frame`` a fixed
    frame (then never re-estimated), e.g. for tests or a maze whose placement is known;
    ``pitch_search`` how far (a share of ``cell_size_m``) the true pitch is looked for
    (:func:`estimate_frame`): ``cell_size_m`` then follows the frame's measured pitch.
    """

    def __init__(
        self,
        cell_size_m: float = MAZE_CELL_M,
        wall_thickness_m: float = _PLANNER.wall_thickness_m,
        anchor_xy_m: tuple[float, float] = (0.0, 0.0),
        post_margin: float = 0.2,
        samples_along: int = 9,
        across_m: float = 0.02,
        wall_fraction: float = 0.3,
        open_fraction: float = 0.8,
        refresh_growth: float = 0.15,
        interior_samples: int = 5,
        interior_seen_min: float = 0.9,
        cell_kept_m: float = 0.05,
        frame: MazeFrame | None = None,
        pitch_search: float = 0.0,
    ) -> None:
        if cell_size_m <= 0:
            raise ValueError(f"cell_size_m must be positive, got {cell_size_m}")
        if not 0.0 <= post_margin < 0.5:
            raise ValueError(f"post_margin is a fraction of a cell side in [0, 0.5), got {post_margin}")
        if samples_along < 2:
            raise ValueError(f"samples_along must be at least 2, got {samples_along}")
        self.cell_size_m = float(cell_size_m)
        self.nominal_cell_size_m = float(cell_size_m)
        self.pitch_search = float(pitch_search)
        self.wall_thickness_m = float(wall_thickness_m)
        self.anchor_xy_m = (float(anchor_xy_m[0]), float(anchor_xy_m[1]))
        self.post_margin = float(post_margin)
        self.samples_along = int(samples_along)
        self.across_m = float(across_m)
        self.wall_fraction = float(wall_fraction)
        self.open_fraction = float(open_fraction)
        self.refresh_growth = float(refresh_growth)
        self.interior_samples = int(interior_samples)
        self.interior_seen_min = float(interior_seen_min)
        self.cell_kept_m = float(cell_kept_m)
        self._fixed_frame = frame is not None
        self.frame: MazeFrame | None = frame
        self.fit = 1.0 if frame is not None else 0.0
        self._support_at_estimate = 0
        # link arrays over cells [i0, i0 + width) x [j0, j0 + height): east[j, i], north[j, i]
        self._i0 = 0
        self._j0 = 0
        self._core: tuple[int, int, int, int] | None = None  # covered (i_lo, i_hi, j_lo, j_hi), inclusive
        self._east = np.zeros((0, 0), dtype=np.int8)
        self._north = np.zeros((0, 0), dtype=np.int8)
        self._seen = np.zeros((0, 0), dtype=np.float32)  # known share of each cell's interior
        self._adjacency: dict[Cell, list[Cell]] | None = None  # open_neighbours of every cell, until the links change
        self._samples = _SampleCells()  # where the link and interior samples fall in the grid, while that holds
        #: Counts the changes of the links or of the covered range: what a reader may key its own caches on
        #: (route costs, reachable cells). An update that reclassifies every link to the same states keeps it.
        self.links_version = 0
        #: The same for the open links alone (what routes follow: :meth:`open_neighbours`), and for the
        #: walls alone (what :meth:`wall_points_m` outlines): a link that turns from unknown to a wall
        #: changes no route, one that opens draws no wall.
        self.open_version = 0
        self.walls_version = 0
        # Read-side copies of the arrays as Python lists (one index costs less than a numpy element),
        # and answers per cell, all kept while the links stay as they are (the seen shares: until an update)
        self._link_rows: tuple[list[list[int]], list[list[int]]] | None = None
        self._unknown_sides: dict[Cell, tuple[Direction, ...]] = {}
        self._reachable: dict[Cell, frozenset[Cell]] = {}
        #: per start cell, the reachable cells without unknown sides (:meth:`explored_share`): rows and
        #: columns of those inside the range, and how many lie outside it
        self._closed_cells: dict[Cell, tuple[np.ndarray, np.ndarray, int]] = {}
        self._seen_rows: list[list[float]] | None = None
        #: every wall's outline (:meth:`_wall_outlines`) with what it was made for
        self._outlines: tuple[tuple[Any, ...], list[tuple[np.ndarray, np.ndarray]]] | None = None
        #: the grid the last update read (a copy) and its origin and resolution
        self._last_read: tuple[np.ndarray, tuple[float, float, float]] | None = None
        self._support = 0  # the occupied cells of that grid (counted while the frame is not fixed)
        #: the known part of the grid the cell range was last fitted to: rows and columns (first, last)
        self._known_box: tuple[int, int, int, int] | None = None

    # -- building ------------------------------------------------------------------------

    def update(self, three_state: np.ndarray, grid_origin_m: tuple[float, float], resolution_m: float) -> GraphUpdate:
        """Re-read the grid: refresh the frame if due, grow the cell range, reclassify links.

        Classification is a pure function of the grid and the frame, vectorised over all
        links (a 16x16 maze is ~600 links, ~10^4 samples), and the links that changed are
        reported. Between two planner ticks only a few of the grid's ~10^5 cells change
        (one revolution painted; on a 16x16 contest maze a median of 12, a tenth of the ticks
        none): while the frame stays and the cell range need not grow, only the links and
        cells whose samples fall on a changed grid cell are read again
        (:meth:`_update_changed`), the others keeping what the same samples gave last time.
        Either way the result is that of reading every link.
        """
        grid = np.asarray(three_state)
        read = (float(grid_origin_m[0]), float(grid_origin_m[1]), float(resolution_m))
        last, self._last_read = self._last_read, (grid.copy(), read)
        if last is not None and last[1] == read and last[0].shape == grid.shape and self.frame is not None:
            changed = np.flatnonzero(last[0].reshape(-1) != grid.reshape(-1))
            if changed.size == 0:  # the same grid: every step below would leave everything as it is
                return GraphUpdate()
            update = self._update_changed(grid, last[0], changed, grid_origin_m, resolution_m)
            if update is not None:
                return update
        return self._update_all(grid, grid_origin_m, resolution_m)

    def _update_all(self, grid: np.ndarray, grid_origin_m: tuple[float, float], resolution_m: float) -> GraphUpdate:
        """:meth:`update` reading every link and cell of the range."""
        old_frame = self.frame
        frame_changed = self._refresh_frame(grid, grid_origin_m, resolution_m)
        if self.frame is None:
            return GraphUpdate(frame_changed=frame_changed)
        same_cells = not frame_changed or (old_frame is not None and self._cells_kept(old_frame, self.frame))
        old_east, old_north, old_i0, old_j0 = self._east, self._north, self._i0, self._j0
        old_seen = self._seen
        self._resize(grid, grid_origin_m, resolution_m)
        self._east = self._classify(grid, grid_origin_m, resolution_m, Direction.E)
        self._north = self._classify(grid, grid_origin_m, resolution_m, Direction.N)
        self._seen = self._interior_seen(grid, grid_origin_m, resolution_m)
        if same_cells:
            # A cell once looked into stays looked into: in a log-odds map the samples next
            # to a wall band flip between known and unknown as hits and misses add up, and a
            # cell whose seen share wobbles around ``interior_seen_min`` would come back as
            # a frontier again and again (the robot dithered between two such cells for
            # minutes). A refined frame (the walls grew: a few millimetres, a fraction of a
            # degree) leaves the cells where they were; only one that moves them starts over.
            self._seen = np.maximum(self._seen, _shifted(old_seen, old_i0 - self._i0, old_j0 - self._j0, self._seen))
        for new, old in ((self._east, old_east), (self._north, old_north)):
            before = _shifted(old, old_i0 - self._i0, old_j0 - self._j0, new)
            if same_cells:
                # A link once known stays known until the map shows the other state: a thin
                # wall between two corridors loses hits to the beams grazing it from either
                # side, and each time it fell back to unknown it became a frontier again (the
                # robot shuttled along a 10-cell wall on test-zigzag-a for minutes). A wall
                # can still turn open and an opening a wall; only "unknown" is not believed.
                _keep_known(new, before)
        return self._links_read(old_east, old_north, old_i0, old_j0, frame_changed)

    def _update_changed(
        self, grid: np.ndarray, old: np.ndarray, changed: np.ndarray, grid_origin_m: tuple[float, float],
        resolution_m: float,
    ) -> GraphUpdate | None:
        """:meth:`update` when only the grid cells ``changed`` (flat indices) differ from ``old``, the
        grid the last update read: the links and cells whose samples fall on them are read again.

        None when the whole update is due: the occupied cells grew enough for a new frame
        estimate (:meth:`_refresh_frame`), or a newly known cell lies outside the known part of
        the grid the cell range was last fitted to (:meth:`_resize` might grow the range). Else
        everything :meth:`_update_all` would do: the range stays (the known part can only have
        shrunk inside that box), a link or cell none of whose samples changed would read the
        same states as last time, and "once known stays known" and "once seen stays seen"
        keep what they kept.
        """
        box = self._known_box
        if box is None:
            return None
        new_values, old_values = grid.reshape(-1)[changed], old.reshape(-1)[changed]
        support = (self._support + int(np.count_nonzero(new_values == OCCUPIED))
                   - int(np.count_nonzero(old_values == OCCUPIED)))
        if not self._fixed_frame and support >= self._support_at_estimate * (1.0 + self.refresh_growth):
            return None
        rows, cols = np.divmod(changed[new_values != UNKNOWN], grid.shape[1])
        if rows.size and (rows.min() < box[0] or rows.max() > box[1] or cols.min() < box[2] or cols.max() > box[3]):
            return None
        self._support = support
        hit = np.zeros(grid.size, dtype=bool)
        hit[changed] = True
        old_east, old_north = self._east, self._north
        width = self._east.shape[1]
        self._east, self._north = old_east.copy(), old_north.copy()
        for direction, links in ((Direction.E, self._east), (Direction.N, self._north)):
            cells = self._samples.cells_hit(direction, hit)
            if cells.size:
                j, i = np.divmod(cells, width)
                states = self._classify(grid, grid_origin_m, resolution_m, direction, cells)
                _keep_known(states, links[j, i])
                links[j, i] = states
        cells = self._samples.cells_hit("interior", hit)
        if cells.size:
            j, i = np.divmod(cells, width)
            self._seen = self._seen.copy()
            self._seen[j, i] = np.maximum(self._interior_seen(grid, grid_origin_m, resolution_m, cells),
                                          self._seen[j, i])
        return self._links_read(old_east, old_north, self._i0, self._j0, False)

    def _links_read(
        self, old_east: np.ndarray, old_north: np.ndarray, old_i0: int, old_j0: int, frame_changed: bool
    ) -> GraphUpdate:
        """The end of an update: the links that changed, and the caches read off the links dropped if any did."""
        changed: list[tuple[Cell, Direction, LinkState]] = []
        same_open = same_walls = True
        for direction, new, old in ((Direction.E, self._east, old_east), (Direction.N, self._north, old_north)):
            before = _shifted(old, old_i0 - self._i0, old_j0 - self._j0, new)
            for j, i in zip(*np.nonzero(new != before), strict=True):
                changed.append(((int(i) + self._i0, int(j) + self._j0), direction, LinkState(int(new[j, i]))))
            differs = new != before  # the shifted arrays hold every link of both (the range never shrinks)
            same_open = same_open and not ((new == LinkState.OPEN) != (before == LinkState.OPEN))[differs].any()
            same_walls = same_walls and not ((new == LinkState.WALL) != (before == LinkState.WALL))[differs].any()
        self._seen_rows = None
        same_links = (
            (self._i0, self._j0) == (old_i0, old_j0)
            and np.array_equal(self._east, old_east)
            and np.array_equal(self._north, old_north)
        )
        if not same_links:  # what is read off the links is a pure function of the arrays and their origin
            self.links_version += 1
            self.open_version += not same_open
            self.walls_version += not same_walls
            self._adjacency = None
            self._link_rows = None
            self._unknown_sides.clear()
            self._reachable.clear()
            self._closed_cells.clear()
        return GraphUpdate(changed, frame_changed)

    def _refresh_frame(self, grid: np.ndarray, grid_origin_m: tuple[float, float], resolution_m: float) -> bool:
        """Estimate the lattice when there is none yet or the walls have grown enough since."""
        if self._fixed_frame:
            return False
        support = self._support = int(np.count_nonzero(grid == OCCUPIED))
        if self.frame is not None and support < self._support_at_estimate * (1.0 + self.refresh_growth):
            return False
        prior = None if self.frame is None else self.frame.angle_rad
        tolerance = max(1.5 * resolution_m, self.wall_thickness_m)
        estimate = estimate_frame(
            grid, grid_origin_m, resolution_m, self.nominal_cell_size_m, self.anchor_xy_m, prior,
            line_tolerance_m=tolerance, pitch_search=self.pitch_search,
        )
        if estimate is None:
            return False
        self._support_at_estimate = support
        self.fit = estimate.fit
        old = self.frame
        self.frame = estimate.frame
        self.cell_size_m = estimate.frame.cell_size_m
        if old is None:
            return True
        moved = np.hypot(*np.subtract(old.origin_m, estimate.frame.origin_m))
        resized = abs(old.cell_size_m - estimate.frame.cell_size_m)
        return bool(abs(old.angle_rad - estimate.frame.angle_rad) > 1e-9 or moved > 1e-9 or resized > 1e-9)

    def _cells_kept(self, old: MazeFrame, new: MazeFrame) -> bool:
        """True when every covered cell lies within ``cell_kept_m`` of where ``old`` put it.

        The frame is re-estimated each time the walls grow by ``refresh_growth``; the
        estimate wanders by millimetres, which leaves every cell (and what was learnt about
        it) in place. The covered cells' corners are compared, where a turn moves most.
        """
        if self._core is None:
            return False
        lo_i, hi_i, lo_j, hi_j = self._core
        corners = np.array([[lo_i, lo_j], [hi_i + 1, lo_j], [lo_i, hi_j + 1], [hi_i + 1, hi_j + 1]], dtype=float)
        moved = np.hypot(*(old.to_map(corners * old.cell_size_m) - new.to_map(corners * new.cell_size_m)).T)
        return bool(moved.max() < self.cell_kept_m)

    def _resize(self, grid: np.ndarray, grid_origin_m: tuple[float, float], resolution_m: float) -> None:
        """Cover every cell that overlaps the known part of the grid (and keep old cells)."""
        assert self.frame is not None
        known = grid != UNKNOWN
        self._known_box = None
        if not known.any():
            lo_i = hi_i = lo_j = hi_j = 0
        else:
            rows = np.flatnonzero(known.any(axis=1))
            cols = np.flatnonzero(known.any(axis=0))
            self._known_box = (int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1]))
            x0 = grid_origin_m[0] + cols[0] * resolution_m
            x1 = grid_origin_m[0] + (cols[-1] + 1) * resolution_m
            y0 = grid_origin_m[1] + rows[0] * resolution_m
            y1 = grid_origin_m[1] + (rows[-1] + 1) * resolution_m
            corners = self.frame.to_maze(np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])) / self.cell_size_m
            lo_i, lo_j = np.floor(corners.min(axis=0)).astype(int)
            hi_i, hi_j = np.floor(corners.max(axis=0)).astype(int)
        if self._core is not None:  # never shrink: cells once covered stay
            lo_i, hi_i = min(lo_i, self._core[0]), max(hi_i, self._core[1])
            lo_j, hi_j = min(lo_j, self._core[2]), max(hi_j, self._core[3])
        self._core = (int(lo_i), int(hi_i), int(lo_j), int(hi_j))
        self._i0, self._j0 = int(lo_i) - 1, int(lo_j) - 1  # one ring of cells beyond the known area
        shape = (int(hi_j) - int(lo_j) + 3, int(hi_i) - int(lo_i) + 3)
        self._east = np.zeros(shape, dtype=np.int8)
        self._north = np.zeros(shape, dtype=np.int8)

    def _classify(
        self, grid: np.ndarray, grid_origin_m: tuple[float, float], resolution_m: float, direction: Direction,
        cells: np.ndarray | None = None,
    ) -> np.ndarray:
        """Link states (int8 [j, i]) of the east or north boundary of every cell in range; of the
        ``cells`` only (flat indices ``j * width + i``, int8 [k]) when given.

        Samples: ``samples_along`` points on the middle of the boundary, each with three
        points across it (on the line and ``across_m`` to either side). An along-position
        is *occupied* when any of its three samples is, *free* when all three are.
        """
        assert self.frame is not None
        frame = self.frame
        c = self.cell_size_m
        h, w = self._east.shape
        t = np.linspace(self.post_margin, 1.0 - self.post_margin, self.samples_along) * c
        across = np.array([-self.across_m, 0.0, self.across_m])
        # maze coordinates (h, w, along, across)
        shape = (h, w, t.size, across.size)

        def sample_xy() -> np.ndarray:
            ii, jj = np.meshgrid(np.arange(w) + self._i0, np.arange(h) + self._j0)
            # the boundary's start: its south end for an east link, its west end for a north link
            line_u = (ii + 1) * c if direction is Direction.E else ii * c
            line_v = jj * c if direction is Direction.E else (jj + 1) * c
            along = np.broadcast_to(t[None, None, :, None], shape)
            side = np.broadcast_to(across[None, None, None, :], shape)
            if direction is Direction.E:  # the boundary runs along v at u = (i + 1) c
                u = line_u[..., None, None] + side
                v = line_v[..., None, None] + along
            else:  # the boundary runs along u at v = (j + 1) c
                u = line_u[..., None, None] + along
                v = line_v[..., None, None] + side
            return frame.to_map(np.column_stack((u.reshape(-1), v.reshape(-1))))

        key = (direction, frame, self._i0, self._j0, shape)
        values = self._samples.lookup(key, grid, grid_origin_m, resolution_m, sample_xy, cells, t.size * across.size)
        values = values.reshape(shape if cells is None else (cells.size, *shape[2:]))
        occupied_along = (values == OCCUPIED).any(axis=-1)
        free_along = (values == FREE).all(axis=-1)
        occupied_share = occupied_along.mean(axis=-1)
        free_share = free_along.mean(axis=-1)
        out = np.full(values.shape[:-2], LinkState.UNKNOWN, dtype=np.int8)
        out[(free_share >= self.open_fraction) & ~occupied_along.any(axis=-1)] = LinkState.OPEN
        out[occupied_share >= self.wall_fraction] = LinkState.WALL
        return out

    def _interior_seen(
        self, grid: np.ndarray, grid_origin_m: tuple[float, float], resolution_m: float,
        cells: np.ndarray | None = None,
    ) -> np.ndarray:
        """Share (float32 [j, i]) of a grid of points inside each cell that the map knows (of the
        ``cells`` only, float32 [k], when given: flat indices ``j * width + i``).

        Links say where the robot can go; this says whether the cell itself has been
        looked into (a dead end seen only through its opening has unseen corners).
        Points are spread over the cell inset by the wall's half thickness plus a grid cell.
        """
        assert self.frame is not None
        frame = self.frame
        c = self.cell_size_m
        h, w = self._east.shape
        inset = (0.5 * self.wall_thickness_m + resolution_m) / c
        t = np.linspace(inset, 1.0 - inset, self.interior_samples) * c
        shape = (h, w, t.size, t.size)

        def sample_xy() -> np.ndarray:
            ii, jj = np.meshgrid(np.arange(w) + self._i0, np.arange(h) + self._j0)
            u = (ii * c)[..., None, None] + np.broadcast_to(t[None, None, :, None], shape)
            v = (jj * c)[..., None, None] + np.broadcast_to(t[None, None, None, :], shape)
            return frame.to_map(np.column_stack((u.reshape(-1), v.reshape(-1))))

        key = ("interior", frame, self._i0, self._j0, shape)
        values = self._samples.lookup(key, grid, grid_origin_m, resolution_m, sample_xy, cells, t.size * t.size)
        values = values.reshape(shape if cells is None else (cells.size, *shape[2:]))
        return (values != UNKNOWN).mean(axis=(-1, -2)).astype(np.float32)

    # -- reading -------------------------------------------------------------------------

    @property
    def ready(self) -> bool:
        """True once a frame exists (enough walls seen), so cells and links mean something."""
        return self.frame is not None

    def cell_range(self) -> tuple[range, range]:
        """The ``i`` and ``j`` ranges of the cells the graph currently covers."""
        h, w = self._east.shape
        return range(self._i0, self._i0 + w), range(self._j0, self._j0 + h)

    def cells(self) -> Iterator[Cell]:
        """Every covered cell, south to north, west to east."""
        irange, jrange = self.cell_range()
        for j in jrange:
            for i in irange:
                yield (i, j)

    def link(self, cell: Cell, direction: Direction) -> LinkState:
        """State of the boundary on side ``direction`` of ``cell`` (UNKNOWN outside the range)."""
        i, j = cell
        if direction is Direction.W:
            i, direction = i - 1, Direction.E
        elif direction is Direction.S:
            j, direction = j - 1, Direction.N
        if self._link_rows is None:
            self._link_rows = (self._east.tolist(), self._north.tolist())
        rows = self._link_rows[0] if direction is Direction.E else self._link_rows[1]
        r, q = j - self._j0, i - self._i0
        if 0 <= r < len(rows) and 0 <= q < len(rows[r]):
            return _LINK_STATES[rows[r][q]]
        return LinkState.UNKNOWN

    def on_walls(self, xy_m: np.ndarray, tolerance_m: float) -> np.ndarray:
        """Which map points ((N, 2), metres) lie within ``tolerance_m`` of the line of a WALL link: (N,) bool.

        A boundary is a WALL once ``wall_fraction`` of it is seen occupied, and an opening never
        shows occupied cells along it: unknown cells on such a line are a stretch of that wall
        the lidar saw only at grazing angles (their cells flip), not a way into unexplored space.
        """
        points = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        out = np.zeros(points.shape[0], dtype=bool)
        frame = self.frame
        if frame is None or points.shape[0] == 0:
            return out
        c = self.cell_size_m
        uv = frame.to_maze(points) / c
        h, w = self._east.shape
        for axis, links in ((0, self._east), (1, self._north)):
            line = np.rint(uv[:, axis]).astype(np.int64)  # the nearest lattice line across this axis
            near = np.abs(uv[:, axis] - line) * c <= tolerance_m
            along = np.floor(uv[:, 1 - axis]).astype(np.int64)
            i = (line - 1 if axis == 0 else along) - self._i0  # the cell whose E (N) side the line is
            j = (along if axis == 0 else line - 1) - self._j0
            inside = near & (i >= 0) & (i < w) & (j >= 0) & (j < h)
            out[inside] |= links[j[inside], i[inside]] == LinkState.WALL
        return out

    def link_between(self, a: Cell, b: Cell) -> LinkState:
        """State of the boundary between neighbouring cells ``a`` and ``b``."""
        return self.link(a, Direction.between(a, b))

    def open_neighbours(self, cell: Cell) -> list[Cell]:
        """Cells joined to ``cell`` by an open link, in the order E, N, W, S.

        Route searches call this for every cell they expand, several searches a planner
        tick: the answers for all cells are read off the link arrays once per update. They
        depend on the open links alone: the same while :attr:`open_version` stays.
        """
        if self._adjacency is None:
            self._adjacency = self._open_adjacency()
        return self._adjacency.get(cell, [])

    def _open_adjacency(self) -> dict[Cell, list[Cell]]:
        east = self._east == LinkState.OPEN  # [j, i]: (i, j) -> (i + 1, j)
        north = self._north == LinkState.OPEN  # [j, i]: (i, j) -> (i, j + 1)
        # the four directions as boolean masks over the cells in range (W and S read the neighbour's link)
        west = np.zeros_like(east)
        west[:, 1:] = east[:, :-1]
        south = np.zeros_like(north)
        south[1:, :] = north[:-1, :]
        adjacency: dict[Cell, list[Cell]] = {}
        any_open = east | north | west | south
        for j, i in zip(*np.nonzero(any_open), strict=True):
            cell = (int(i) + self._i0, int(j) + self._j0)
            out = []
            for mask, d in ((east, Direction.E), (north, Direction.N), (west, Direction.W), (south, Direction.S)):
                if mask[j, i]:
                    out.append((cell[0] + d.step[0], cell[1] + d.step[1]))
            adjacency[cell] = out
        # cells just outside the range reached by an open link of the edge cells
        for outs in list(adjacency.values()):
            for nxt in outs:
                if nxt not in adjacency:
                    adjacency[nxt] = [
                        (nxt[0] + d.step[0], nxt[1] + d.step[1])
                        for d in Direction
                        if self.link(nxt, d) is LinkState.OPEN
                    ]
        return adjacency

    def unknown_sides(self, cell: Cell) -> list[Direction]:
        """Sides of ``cell`` whose link is still unknown."""
        sides = self._unknown_sides.get(cell)
        if sides is None:
            sides = self._unknown_sides[cell] = tuple(d for d in _DIRECTIONS if self.link(cell, d) is LinkState.UNKNOWN)
        return list(sides)

    def interior_seen(self, cell: Cell) -> float:
        """Share of the inside of ``cell`` the map knows, 0 to 1 (0 outside the range)."""
        if self._seen_rows is None:
            self._seen_rows = self._seen.tolist()  # the float32 shares as Python floats, as float() gives them
        r, q = cell[1] - self._j0, cell[0] - self._i0
        if 0 <= r < len(self._seen_rows) and 0 <= q < len(self._seen_rows[r]):
            return self._seen_rows[r][q]
        return 0.0

    def mark_looked_into(self, cell: Cell) -> None:
        """Count ``cell``'s inside as seen from now on (until a new frame moves the cells).

        For a cell the robot has driven into: the lidar saw it on the approach, and from
        inside it the cell's own walls are closer than the lidar's minimum range, so what
        the map still lacks there (the cells along its walls) no more looking will fill.
        """
        r, q = cell[1] - self._j0, cell[0] - self._i0
        if 0 <= r < self._seen.shape[0] and 0 <= q < self._seen.shape[1]:
            self._seen[r, q] = 1.0
            self._seen_rows = None

    def needs_look(self, cell: Cell) -> bool:
        """True when less than ``interior_seen_min`` of the cell's inside is known."""
        return self.interior_seen(cell) < self.interior_seen_min

    def is_explored(self, cell: Cell) -> bool:
        """True when all four links of ``cell`` are known and its inside has been seen."""
        return not self.unknown_sides(cell) and not self.needs_look(cell)

    def kind(self, cell: Cell) -> CellKind:
        """Dead end, corridor, junction, open area, enclosed or unexplored (see :class:`CellKind`)."""
        if not self.is_explored(cell):
            return CellKind.UNEXPLORED
        if self.in_open_area(cell):
            return CellKind.OPEN_AREA
        degree = len(self.open_neighbours(cell))
        if degree == 0:
            return CellKind.ENCLOSED
        if degree == 1:
            return CellKind.DEAD_END
        if degree == 2:
            return CellKind.CORRIDOR
        return CellKind.JUNCTION

    def in_open_area(self, cell: Cell) -> bool:
        """True when ``cell`` is a corner of a 2x2 block whose four inner links are all open."""
        i, j = cell
        for di, dj in ((0, 0), (-1, 0), (0, -1), (-1, -1)):
            a = (i + di, j + dj)  # south-west cell of a candidate block
            b, n, bn = (a[0] + 1, a[1]), (a[0], a[1] + 1), (a[0] + 1, a[1] + 1)
            if all(self.link_between(p, q) is LinkState.OPEN for p, q in ((a, b), (a, n), (b, bn), (n, bn))):
                return True
        return False

    def explored_share(self, start: Cell) -> float | None:
        """Share of the cells reachable from ``start`` that are explored (:meth:`is_explored`); None if none.

        The pilot's coverage, every planner tick. Which reachable cells have all four links
        known changes only with the links (kept with them, as :meth:`reachable`); their inside
        shares change with every map, and are read in one array lookup, compared as
        :meth:`needs_look` compares them (float32 shares against a Python float), instead of
        a call per cell (a 16x16 maze: ~1 ms of a tick's CPU under a Pi 4's share).
        """
        reachable = self.reachable(start)
        if not reachable:
            return None
        closed = self._closed_cells.get(start)
        if closed is None:  # the reachable cells without unknown sides: inside the range (rows, columns), outside
            inside, outside = [], 0
            h, w = self._seen.shape
            for cell in reachable:
                if self.unknown_sides(cell):
                    continue
                r, q = cell[1] - self._j0, cell[0] - self._i0
                if 0 <= r < h and 0 <= q < w:
                    inside.append((r, q))
                else:
                    outside += 1
            rows = np.array([r for r, _ in inside], dtype=np.intp)
            cols = np.array([q for _, q in inside], dtype=np.intp)
            closed = self._closed_cells[start] = (rows, cols, outside)
        rows, cols, outside = closed
        seen = self._seen[rows, cols].astype(np.float64)  # exact: as float() gives each float32 share
        explored = int(np.count_nonzero(seen >= self.interior_seen_min))
        if self.interior_seen_min <= 0.0:  # a cell outside the range has a share of 0
            explored += outside
        return explored / len(reachable)

    def reachable(self, start: Cell) -> set[Cell]:
        """Cells connected to ``start`` through open links (breadth-first; kept while the links stay)."""
        kept = self._reachable.get(start)
        if kept is not None:
            return set(kept)
        seen = {start}
        queue = deque([start])
        while queue:
            cell = queue.popleft()
            for nxt in self.open_neighbours(cell):
                if nxt not in seen:
                    seen.add(nxt)
                    queue.append(nxt)
        self._reachable[start] = frozenset(seen)
        return seen

    def frontier_links(self, start: Cell) -> list[tuple[Cell, Direction | None]]:
        """What is left to explore from ``start``: unknown links and unseen cells, all reachable.

        Each is ``(cell, side)`` with ``cell`` reachable (the robot can go there to look):
        ``side`` an unknown link, or None when the cell's own inside is still unseen.
        """
        out: list[tuple[Cell, Direction | None]] = []
        for cell in sorted(self.reachable(start)):
            out.extend((cell, d) for d in self.unknown_sides(cell))
            if self.needs_look(cell):
                out.append((cell, None))
        return out

    def links(self) -> Iterable[tuple[Cell, Direction, LinkState]]:
        """Every covered east and north link as ``(cell, direction, state)``."""
        for direction, array in ((Direction.E, self._east), (Direction.N, self._north)):
            for j, i in zip(*np.nonzero(np.ones_like(array, dtype=bool)), strict=True):
                yield (int(i) + self._i0, int(j) + self._j0), direction, LinkState(int(array[j, i]))

    def wall_points_m(self, center_xy_m: tuple[float, float], radius_m: float, spacing_m: float = 0.01) -> np.ndarray:
        """Points (N, 2, map frame) on the surfaces of the WALL links within ``radius_m``.

        A maze wall runs straight from post to post, so once a link is known to be a wall
        its whole outline is known, including the post ends a log-odds map loses (a
        12 mm wall end seen edge-on collects few hits, and the beams grazing it erase
        them). Each wall is the ``wall_thickness_m`` rectangle around its boundary,
        reaching half a thickness past both posts, sampled every ``spacing_m`` along
        both faces and across both ends: exact surfaces for the local planner, which
        cannot see them when they are closer than the lidar's minimum range.

        The outlines of all walls are made once per state of the links and frame
        (:meth:`_wall_outlines`); a call picks those of the walls near the centre and
        the points within the radius, as making only the near ones would.
        """
        if self.frame is None or not self._east.size:
            return np.zeros((0, 2))
        blocks = self._wall_outlines(spacing_m)
        centre_uv = self.frame.to_maze(np.array(center_xy_m))[0]
        reach = radius_m + self.cell_size_m
        pieces = []
        for anchor_uv, points in blocks:
            near = np.hypot(anchor_uv[:, 0] - centre_uv[0], anchor_uv[:, 1] - centre_uv[1]) <= reach
            if near.any():
                pieces.append(points[near].reshape(-1, 2))
        if not pieces:
            return np.zeros((0, 2))
        xy = np.concatenate(pieces)
        keep = np.hypot(xy[:, 0] - center_xy_m[0], xy[:, 1] - center_xy_m[1]) <= radius_m
        return xy[keep]

    def _wall_outlines(self, spacing_m: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every WALL link's outline in map-frame points, by direction and face: blocks of
        ``(start corners (W, 2, maze frame), points (W, P, 2))``, a row per wall.

        Kept while the links, the frame and the spacing stay the same: the planner asks
        every tick, and the walls change a few times a minute.
        """
        assert self.frame is not None
        key = (self.walls_version, self.frame, self.cell_size_m, spacing_m)
        kept = self._outlines
        if kept is not None and kept[0][0] == key[0] and kept[0][1] is key[1] and kept[0][2:] == key[2:]:
            return kept[1]
        c = self.cell_size_m
        h = 0.5 * self.wall_thickness_m
        n_along = max(2, math.ceil((c + 2 * h) / spacing_m) + 1)
        along = np.linspace(-h, c + h, n_along)
        across = np.linspace(-h, h, max(2, math.ceil(2 * h / spacing_m) + 1))
        blocks: list[tuple[np.ndarray, np.ndarray]] = []
        for direction, array in ((Direction.E, self._east), (Direction.N, self._north)):
            jj, ii = np.nonzero(array == LinkState.WALL)
            if jj.size == 0:
                continue
            i = ii + self._i0
            j = jj + self._j0
            # the boundary's start corner (its south end for an east link, west end for a north link)
            u0 = ((i + 1) * c if direction is Direction.E else i * c).astype(float)
            v0 = (j * c if direction is Direction.E else (j + 1) * c).astype(float)
            faces = [(side, along) for side in (-h, h)] + [(across, end) for end in (-h, c + h)]
            for off, run in faces:
                off_arr = np.broadcast_to(np.asarray(off, dtype=float), np.broadcast(off, run).shape)
                run_arr = np.broadcast_to(np.asarray(run, dtype=float), off_arr.shape)
                if direction is Direction.E:  # the wall runs along v at u = u0
                    u = u0[:, None] + off_arr[None, :]
                    v = v0[:, None] + run_arr[None, :]
                else:  # the wall runs along u at v = v0
                    u = u0[:, None] + run_arr[None, :]
                    v = v0[:, None] + off_arr[None, :]
                points = self.frame.to_map(np.column_stack((u.reshape(-1), v.reshape(-1))))
                blocks.append((np.column_stack((u0, v0)), points.reshape(u0.size, -1, 2)))
        self._outlines = (key, blocks)
        return blocks


def _keep_known(new: np.ndarray, before: np.ndarray) -> None:
    """In place: a link ``new`` reads as unknown keeps the known state it had ``before``."""
    forgotten = (new == LinkState.UNKNOWN) & (before != LinkState.UNKNOWN)
    new[forgotten] = before[forgotten]


def _shifted(old: np.ndarray, di: int, dj: int, like: np.ndarray) -> np.ndarray:
    """``old`` (indexed [j - j0_old, i - i0_old]) placed in an array shaped like ``like`` whose
    origin is ``di``/``dj`` cells before old's; zeros where old did not reach (never shrinks, so it fits)."""
    out = np.zeros_like(like)
    h, w = old.shape
    if h and w:
        out[dj : dj + h, di : di + w] = old
    return out


@dataclass
class _Samples:
    """One set of sample points, where they fall in the grid: ``per_cell`` samples a cell, in cell order."""

    key: tuple[Any, ...]
    inside: np.ndarray  # bool, a sample on the grid
    flat: np.ndarray  # the grid's flat index of each sample on the grid
    per_cell: int
    _index: np.ndarray | None = None  # (cells, per_cell): the flat index, -1 off the grid
    _owner: np.ndarray | None = None  # the cell of each sample on the grid

    def index(self) -> np.ndarray:
        if self._index is None:
            index = np.full(self.inside.shape[0], -1, dtype=np.int64)
            index[self.inside] = self.flat
            self._index = index.reshape(-1, self.per_cell)
        return self._index

    def owner(self) -> np.ndarray:
        if self._owner is None:
            self._owner = np.flatnonzero(self.inside) // self.per_cell
        return self._owner


class _SampleCells:
    """The grid cells under a fixed set of sample points, kept while frame, cells and grid stay.

    The link and interior samples of every covered cell (~10^4 points on a 16x16 maze)
    depend only on the maze frame, the covered cell range and the grid's placement; those
    change when the frame is re-estimated or the grid grows, a few times a run, while the
    grid's values change with every revolution. So the planner tick reads the grid at
    indices worked out once, instead of transforming every point again: the same values
    as transforming them each time, at a fraction of the cost. The same indices say which
    cells' samples fall on given grid cells (:meth:`cells_hit`).
    """

    def __init__(self) -> None:
        self._cells: dict[Any, _Samples] = {}

    def lookup(
        self,
        key: tuple[Any, ...],
        grid: np.ndarray,
        origin_m: tuple[float, float],
        resolution_m: float,
        sample_xy: Callable[[], np.ndarray],
        cells: np.ndarray | None = None,
        per_cell: int = 1,
    ) -> np.ndarray:
        """Three-state values at the points ``sample_xy()`` would give for ``key`` (UNKNOWN off the grid).

        The points are cells' samples, ``per_cell`` of them a cell, one cell after another;
        with ``cells`` (flat indices of cells), the values of those cells' samples only.
        """
        full_key = (*key[1:], grid.shape, (float(origin_m[0]), float(origin_m[1])), float(resolution_m))
        kept = self._cells.get(key[0])
        if kept is None or kept.key != full_key:
            xy = sample_xy()
            rows, cols = grid.shape
            c = np.floor((xy[:, 0] - origin_m[0]) / resolution_m).astype(np.int64)
            r = np.floor((xy[:, 1] - origin_m[1]) / resolution_m).astype(np.int64)
            inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
            kept = _Samples(full_key, inside, r[inside] * cols + c[inside], per_cell)
            self._cells[key[0]] = kept
        if cells is not None:
            index = kept.index()[cells]
            values = grid.reshape(-1)[index]
            values[index < 0] = UNKNOWN
            return values.reshape(-1)
        out = np.full(kept.inside.shape[0], UNKNOWN, dtype=np.int8)
        out[kept.inside] = grid.reshape(-1)[kept.flat]
        return out

    def cells_hit(self, name: Any, hit: np.ndarray) -> np.ndarray:
        """The cells (flat indices, ascending) with a sample of the set ``name`` on a grid cell where ``hit``
        (bool, flat over the grid its last :meth:`lookup` read) is True."""
        kept = self._cells.get(name)
        if kept is None:
            return np.zeros(0, dtype=np.int64)
        return np.unique(kept.owner()[hit[kept.flat]])
