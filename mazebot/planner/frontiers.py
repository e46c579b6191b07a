"""Grid frontiers, and the poses from which the robot's lidar can look into them.

Yamauchi's frontier-based exploration (Yamauchi 1997, "A frontier-based approach for
autonomous exploration", CIRA): a *frontier cell* is a known-free cell of the occupancy
grid next to an unknown one; 8-connected frontier cells form a *frontier*; driving to a
frontier lets the sensor see the unknown space beyond it. Yamauchi's robot drove onto
the frontier itself. Ours cannot always, and it would not help when it could:

- the robot is a disc of ``footprint_radius_m`` that keeps ``clearance_m`` from walls:
  it can stand only on the passable cells of the inflated costmap
  (:class:`~mazebot.planner.global_path.GridCostmap`, the configuration space of
  Lozano-Pérez 1983), and in a 1 ft corridor that is a band a few centimetres wide
  down its middle, never next to a wall where the frontier often is;
- the lidar drops every return closer than its minimum range (0.15 m on an A1M8,
  Slamtec datasheet), and with it everything the ray crossed: a frontier within that
  range of the robot stays unknown however long the robot stands there.

So a frontier is only *reachable* through a **viewpoint**: a passable cell the robot can
drive to (a finite path cost) from which a straight ray of known free cells reaches the
frontier's unknown cells at a range between the lidar's minimum range and the planning
view radius. A lidar ray in that direction crosses the unknown cell whatever it holds
(free: it passes on; a wall: it stops there) and resolves it. The number of the
frontier's unknown cells a viewpoint sees is its **information gain**. Viewpoints are
ranked by gain and path cost together, as González-Baños and Latombe ("Navigation
strategies for exploring indoor environments", IJRR 21(10), 2002) rank candidate poses
by ``gain * exp(-lambda * cost)``: here as a score in metres,
``cost_m - gain_weight_m * ln(gain)``, lower is better (``gain_weight_m`` is 1/lambda: the
route metres a gain ``e`` times larger is worth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN

_FOUR = ((1, 0), (-1, 0), (0, 1), (0, -1))


@dataclass(frozen=True)
class Frontier:
    """One frontier: its free ``cells`` and the ``unknown`` cells they border ((K, 2) ``(row, col)`` arrays).

    ``unknown`` is what the lidar has to see for the frontier to be resolved.
    """

    cells: np.ndarray
    unknown: np.ndarray

    @property
    def centroid_rc(self) -> tuple[float, float]:
        """The mean ``(row, col)`` of its free cells."""
        mean = self.cells.mean(axis=0)
        return (float(mean[0]), float(mean[1]))


@dataclass(frozen=True)
class Viewpoint:
    """A place to look at a frontier from: a grid ``cell``, its path ``cost_m`` from the robot,
    the unknown cells it sees (``gain``, estimated from a sample) and its ``score_m``."""

    cell: tuple[int, int]
    cost_m: float
    gain: float
    score_m: float


def frontier_unknowns(three_state: np.ndarray, wall_margin_cells: int = 2, sliver_cells: int = 2) -> np.ndarray:
    """The unknown cells that count for frontiers: a boolean grid.

    Unknown cells within ``wall_margin_cells`` of an occupied cell do not count: in a
    log-odds map a wall is a band of cells of which some never collect enough hits, and
    the free cells along it are no gateway to unexplored space (a real opening is wider
    than the margin, so its middle still counts).

    Nor do unknown areas with no cell more than ``sliver_cells`` (4-neighbour steps) from
    known space: slivers the map leaves in a wall between two corridors the robot drove,
    whose 12 mm the lidar sees only at grazing angles from either side (a 16x16 maze's long
    corridors: stretches of wall line that stay unknown with free space on both sides, "seen"
    from every viewpoint and resolved from none). Unexplored space worth a visit (a cell
    behind a misread opening, the map's outside) is wider than ``2 * sliver_cells + 1``
    cells somewhere; a sliver hides no passage the robot or its lidar could use.
    """
    grid = np.asarray(three_state)
    all_unknown = grid == UNKNOWN
    unknown = all_unknown.copy()
    if wall_margin_cells > 0:
        unknown &= ~_dilate_4(grid == OCCUPIED, wall_margin_cells)
    if sliver_cells > 0 and unknown.any():
        core = ~_dilate_4(~all_unknown, sliver_cells)  # unknown cells farther than that from known ones
        labels, _ = ndimage.label(all_unknown, structure=np.ones((3, 3), dtype=bool))
        wide = np.unique(labels[core])
        unknown &= np.isin(labels, wide[wide > 0])
    return unknown


def _dilate_4(mask: np.ndarray, iterations: int) -> np.ndarray:
    """``scipy.ndimage.binary_dilation(mask, iterations=iterations)`` (the 4-neighbour cross,
    nothing beyond the border), by shifted ORs: the same cells, a tenth of the time on a
    16x16 maze's grid."""
    out = mask.copy()
    for _ in range(iterations):
        src = out.copy()
        out[1:, :] |= src[:-1, :]
        out[:-1, :] |= src[1:, :]
        out[:, 1:] |= src[:, :-1]
        out[:, :-1] |= src[:, 1:]
    return out


def find_frontiers(
    three_state: np.ndarray, min_cells: int = 4, wall_margin_cells: int = 2, sliver_cells: int = 2
) -> list[Frontier]:
    """Yamauchi's frontiers: 8-connected groups of free cells with an unknown 4-neighbour.

    Unknown cells next to walls and thin unknown slivers do not count (see :func:`frontier_unknowns`); groups
    smaller than ``min_cells`` (speckle, the pockets behind posts) are dropped. Each
    frontier carries the unknown cells its free cells touch.
    """
    grid = np.asarray(three_state)
    unknown = frontier_unknowns(grid, wall_margin_cells, sliver_cells)
    touches = np.zeros_like(unknown)
    touches[1:, :] |= unknown[:-1, :]
    touches[:-1, :] |= unknown[1:, :]
    touches[:, 1:] |= unknown[:, :-1]
    touches[:, :-1] |= unknown[:, 1:]
    frontier = (grid == FREE) & touches
    labels, count = ndimage.label(frontier, structure=np.ones((3, 3), dtype=bool))
    if count == 0:
        return []
    cells = _group_by_label(labels, count)
    # each unknown cell goes to the frontier of a free 4-neighbour (the first one found)
    owner = np.zeros(grid.shape, dtype=labels.dtype)
    rows, cols = grid.shape
    for dr, dc in _FOUR:
        neighbour = np.zeros_like(labels)
        neighbour[max(0, -dr) : rows - max(0, dr), max(0, -dc) : cols - max(0, dc)] = labels[
            max(0, dr) : rows - max(0, -dr), max(0, dc) : cols - max(0, -dc)
        ]
        take = unknown & (owner == 0) & (neighbour > 0)
        owner[take] = neighbour[take]
    unknown_cells = _group_by_label(owner, count)
    return [Frontier(c, u) for c, u in zip(cells, unknown_cells, strict=True) if c.shape[0] >= min_cells]


def frontier_regions(
    three_state: np.ndarray, min_cells: int = 4, wall_margin_cells: int = 2, sliver_cells: int = 2
) -> list[np.ndarray]:
    """The free cells of each frontier of :func:`find_frontiers`: a list of (K, 2) ``(row, col)`` arrays."""
    return [f.cells for f in find_frontiers(three_state, min_cells, wall_margin_cells, sliver_cells)]


def _group_by_label(labels: np.ndarray, count: int) -> list[np.ndarray]:
    """The ``(row, col)`` cells of each label 1..count, as a list of (K, 2) arrays (K may be 0)."""
    rows, cols = np.nonzero(labels)
    order = np.argsort(labels[rows, cols], kind="stable")
    rows, cols = rows[order], cols[order]
    sizes = np.bincount(labels[rows, cols], minlength=count + 1)[1:]
    return np.split(np.column_stack((rows, cols)), np.cumsum(sizes)[:-1])


def sees(
    free: np.ndarray,
    viewpoints: np.ndarray,
    targets: np.ndarray,
    min_range_cells: float,
    max_range_cells: float,
    half_width_cells: float = 0.5,
) -> np.ndarray:
    """Which viewpoint's lidar would resolve which target cell: a (C, T) boolean array.

    ``free`` is the known-free grid; ``viewpoints`` (C, 2) and ``targets`` (T, 2) are
    ``(row, col)`` cells. A target is seen when it lies between ``min_range_cells`` and
    ``max_range_cells`` (centre to centre) and a strip ``2 * half_width_cells`` wide
    along the segment to it, sampled every half cell on its centre line and both edges,
    crosses only known free cells until the last cell and a half before the target: the
    lidar's ray in that direction gets there and whatever it finds (free space, a wall)
    is painted. The strip's width keeps out rays that only graze a corner: looking along
    the edge of a shadow from the line it was cast along resolves nothing new, though a
    one-cell-wide digital line may slip past the corner.
    """
    v = np.asarray(viewpoints, dtype=np.float64)[:, None, :]
    t = np.asarray(targets, dtype=np.float64)[None, :, :]
    delta = t - v  # (C, T, 2)
    dist = np.hypot(delta[..., 0], delta[..., 1])
    in_range = (dist >= min_range_cells) & (dist <= max_range_cells)
    if not in_range.any():
        return in_range
    steps = np.maximum(np.ceil(2.0 * dist), 1.0)  # samples every half cell
    k = np.arange(1, int(steps[in_range].max()))
    frac = k[None, None, :] / steps[..., None]  # (C, T, S); beyond 1 for short segments
    before = frac < 1.0
    rows = v[..., 0, None] + frac * delta[..., 0, None]
    cols = v[..., 1, None] + frac * delta[..., 1, None]
    rr, cc = np.rint(rows).astype(np.int64), np.rint(cols).astype(np.int64)
    on_target = (rr == t[..., 0, None]) & (cc == t[..., 1, None])
    clear = _free_at(free, rr, cc) | ~before | on_target
    if half_width_cells == 0.0:
        # a strip of no width is its centre line: the edges' samples are the centre line's, and where
        # they are checked (more than a cell and a half short of the target, never the target's own
        # cell) the centre line is already required free
        return in_range & clear.all(axis=2)
    # the strip's edges, up to a cell and a half short of the target (its neighbours there are unknown)
    away = (frac * dist[..., None] < dist[..., None] - 1.5) & before
    unit = delta / np.maximum(dist, 1e-9)[..., None]
    for side in (-half_width_cells, half_width_cells):
        er = np.rint(rows - side * unit[..., 1, None]).astype(np.int64)
        ec = np.rint(cols + side * unit[..., 0, None]).astype(np.int64)
        clear &= _free_at(free, er, ec) | ~away
    return in_range & clear.all(axis=2)


def _free_at(free: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``free[rows, cols]``, False off the grid."""
    inside = (rows >= 0) & (rows < free.shape[0]) & (cols >= 0) & (cols < free.shape[1])
    return free[np.clip(rows, 0, free.shape[0] - 1), np.clip(cols, 0, free.shape[1] - 1)] & inside


def viewpoint_candidates(
    frontier: Frontier,
    cost_cells: np.ndarray,
    resolution_m: float,
    view_radius_m: float,
    excluded: np.ndarray | None = None,
) -> np.ndarray:
    """The reachable cells within ``view_radius_m`` of ``frontier``'s unknown cells, cheapest first: (C, 2).

    ``cost_cells`` is the path cost (cell lengths) from the robot to every cell, inf
    where the robot cannot stand or get to (``GridCostmap.distances_from`` masked by
    ``passable``); ``excluded`` (a boolean grid) masks cells that already failed to
    resolve this frontier.
    """
    targets = frontier.unknown
    if targets.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    radius = view_radius_m / resolution_m
    r0, c0 = np.maximum(targets.min(axis=0) - math.ceil(radius), 0)
    r1, c1 = np.minimum(targets.max(axis=0) + math.ceil(radius) + 1, cost_cells.shape)
    window = np.isfinite(cost_cells[r0:r1, c0:c1])
    if excluded is not None:
        window &= ~excluded[r0:r1, c0:c1]
    if not window.any():
        return np.zeros((0, 2), dtype=np.int64)
    mask = np.zeros(window.shape, dtype=bool)
    mask[targets[:, 0] - r0, targets[:, 1] - c0] = True
    near = ndimage.distance_transform_edt(~mask) <= radius
    rows, cols = np.nonzero(window & near)
    candidates = np.column_stack((rows + r0, cols + c0))
    order = np.argsort(cost_cells[candidates[:, 0], candidates[:, 1]], kind="stable")
    return candidates[order]


def score_bound_m(frontier: Frontier, candidates: np.ndarray, cost_cells: np.ndarray, resolution_m: float,
                  gain_weight_m: float) -> float:
    """A lower bound of :func:`best_viewpoint`'s score: the cheapest candidate seeing every unknown cell.

    Frontiers are evaluated in the order of their bounds, and those whose bound is no
    better than the best score found so far are skipped (branch and bound).
    """
    if candidates.shape[0] == 0 or frontier.unknown.shape[0] == 0:
        return math.inf
    cheapest_m = float(cost_cells[candidates[0, 0], candidates[0, 1]]) * resolution_m
    return cheapest_m - gain_weight_m * math.log(frontier.unknown.shape[0])


def best_viewpoint(
    frontier: Frontier,
    candidates: np.ndarray,
    free: np.ndarray,
    cost_cells: np.ndarray,
    resolution_m: float,
    min_range_m: float,
    view_radius_m: float,
    gain_weight_m: float,
    max_candidates: int = 96,
    max_targets: int = 16,
    extra: tuple[int, int] | None = None,
    keep_margin_m: float = 0.0,
) -> Viewpoint | None:
    """The lowest-score viewpoint of ``frontier`` among ``candidates``, or None when none sees it.

    ``candidates`` come from :func:`viewpoint_candidates` (cheapest first); at most
    ``max_candidates`` of them, evenly spread over their costs, are checked, plus
    ``extra`` (the viewpoint chosen last tick), which is kept while it still sees the
    frontier and scores within ``keep_margin_m`` of the best (the goal does not hop
    between equals as the robot moves). Each is checked against
    up to ``max_targets`` of the unknown cells, evenly spread, and its gain scaled up to
    all of them. A lidar return must lie beyond ``min_range_m`` plus one cell (the range
    to the far side of a wall cell is not its centre's).
    """
    targets = frontier.unknown
    if candidates.shape[0] > max_candidates:
        candidates = candidates[_spread(candidates.shape[0], max_candidates)]
    if extra is not None and np.isfinite(cost_cells[extra]):
        candidates = np.vstack((candidates, np.array([extra], dtype=candidates.dtype)))
    if candidates.shape[0] == 0 or targets.shape[0] == 0:
        return None
    sample = targets[_spread(targets.shape[0], max_targets)] if targets.shape[0] > max_targets else targets
    seen = sees(free, candidates, sample, min_range_m / resolution_m + 1.0, view_radius_m / resolution_m).sum(axis=1)
    ok = seen > 0
    if not ok.any():
        return None
    gain = seen[ok] * (targets.shape[0] / sample.shape[0])
    cost_m = cost_cells[candidates[ok, 0], candidates[ok, 1]] * resolution_m
    score = cost_m - gain_weight_m * np.log(gain)
    k = int(np.argmin(score))
    kept = extra is not None and ok[-1] and (candidates[-1, 0], candidates[-1, 1]) == extra
    if kept and score[-1] <= score[k] + keep_margin_m:
        k = score.size - 1
    cell = (int(candidates[ok][k, 0]), int(candidates[ok][k, 1]))
    return Viewpoint(cell, float(cost_m[k]), float(gain[k]), float(score[k]))


def _spread(n: int, k: int) -> np.ndarray:
    """``k`` (or fewer) indices spread evenly over ``0 .. n-1``, both ends included."""
    return np.unique(np.linspace(0, n - 1, k).round().astype(np.int64))


class SweptCells:
    """How many map revolutions the lidar had each unknown cell in clear view: cells it was *swept* by.

    A frontier is worth a visit for what its unknown cells may hide. Once the robot stood
    where its lidar had a cell within ``view_radius_m`` (beyond the minimum range, along a
    strip of known free cells: :func:`sees`) for several revolutions painted into the map,
    and the cell is still unknown, driving there again shows nothing new: the cell is a
    stretch of wall seen only at grazing angles (a 16x16 maze's corridor walls: their cells
    flip between unknown, free and wall as revolutions come in, and the frontier they make
    comes and goes behind the robot), not a way into unexplored space. A real opening seen
    that way is painted free, and the cells behind it are new.

    Counted per cell of the infinite lattice the map's grid is cut from (the grid grows: its
    origin moves by whole cells), only the unknown cells next to known free ones (where a
    frontier's unknown cells are), near the robot: a few hundred cells, a millisecond a tick.

    Example::

        swept = SweptCells()
        swept.count(grid, origin_m, resolution_m, (x_m, y_m), 0.15, 0.9)  # once per painted revolution
        mask = swept.swept_mask(grid.shape, origin_m, resolution_m, 4)   # cells swept 4 times or more
    """

    def __init__(self) -> None:
        self._counts = np.zeros((0, 0), dtype=np.int16)
        self._anchor = (0, 0)  # lattice (row, col) of self._counts[0, 0]

    @staticmethod
    def _anchor_of(origin_m: tuple[float, float], resolution_m: float) -> tuple[int, int]:
        return (round(origin_m[1] / resolution_m), round(origin_m[0] / resolution_m))

    def _aligned(self, shape: tuple[int, int], anchor: tuple[int, int]) -> np.ndarray:
        """The counts on the cells of a grid of ``shape`` whose cell (0, 0) is lattice cell ``anchor``."""
        if self._counts.shape == shape and self._anchor == anchor:
            return self._counts
        out = np.zeros(shape, dtype=np.int16)
        dr, dc = self._anchor[0] - anchor[0], self._anchor[1] - anchor[1]
        rows, cols = self._counts.shape
        r0, c0 = max(dr, 0), max(dc, 0)
        r1, c1 = min(dr + rows, shape[0]), min(dc + cols, shape[1])
        if r1 > r0 and c1 > c0:
            out[r0:r1, c0:c1] = self._counts[r0 - dr : r1 - dr, c0 - dc : c1 - dc]
        return out

    def count(
        self,
        three_state: np.ndarray,
        origin_m: tuple[float, float],
        resolution_m: float,
        robot_xy_m: tuple[float, float],
        min_range_m: float,
        view_radius_m: float,
    ) -> int:
        """Add one revolution to each unknown cell next to known free space the robot's lidar sees now.

        Call once per map revolution painted (the map changed since the last call); returns how
        many cells were counted. Seen as :func:`best_viewpoint` counts a viewpoint's gain (from
        the robot's cell, between the minimum range plus a cell and ``view_radius_m``), along the
        beam's centre line: the robot stands on the swept cells' side for revolutions on end, at
        slightly different poses, so a corner the line only grazes is no false view that lasts.
        """
        grid = np.asarray(three_state)
        anchor = self._anchor_of(origin_m, resolution_m)
        self._counts = self._aligned(grid.shape, anchor)
        self._anchor = anchor
        radius = view_radius_m / resolution_m
        r = math.floor((robot_xy_m[1] - origin_m[1]) / resolution_m)
        c = math.floor((robot_xy_m[0] - origin_m[0]) / resolution_m)
        pad = math.ceil(radius) + 1
        r0, r1 = max(r - pad, 0), min(r + pad + 1, grid.shape[0])
        c0, c1 = max(c - pad, 0), min(c + pad + 1, grid.shape[1])
        if r1 <= r0 or c1 <= c0:
            return 0
        window = grid[r0:r1, c0:c1]
        free = window == FREE
        beside_free = np.zeros_like(free)
        beside_free[1:, :] |= free[:-1, :]
        beside_free[:-1, :] |= free[1:, :]
        beside_free[:, 1:] |= free[:, :-1]
        beside_free[:, :-1] |= free[:, 1:]
        rows, cols = np.nonzero((window == UNKNOWN) & beside_free)
        near = np.hypot(rows + r0 - r, cols + c0 - c) <= radius
        if not near.any():
            return 0
        targets = np.column_stack((rows[near], cols[near]))  # in the window: its rays stay inside it
        # the beam's centre line only: a wall's cells seen at a grazing angle are reached along the free band
        # beside the wall, where a strip as wide as a cell (a viewpoint's test) already touches the wall line
        robot = np.array([[r - r0, c - c0]])
        seen = sees(free, robot, targets, min_range_m / resolution_m + 1.0, radius, half_width_cells=0.0)[0]
        hit = targets[seen]
        np.add.at(self._counts, (hit[:, 0] + r0, hit[:, 1] + c0), 1)
        np.minimum(self._counts, np.iinfo(np.int16).max - 1, out=self._counts)
        return int(hit.shape[0])

    def swept_mask(
        self, shape: tuple[int, int], origin_m: tuple[float, float], resolution_m: float, min_revolutions: int
    ) -> np.ndarray:
        """The cells of a grid (``shape``, ``origin_m``) swept ``min_revolutions`` times or more, and their
        8 neighbours (a cell at the edge of the map's thresholds flips with its neighbour)."""
        counts = self._aligned(shape, self._anchor_of(origin_m, resolution_m))
        swept = counts >= min_revolutions
        out = swept.copy()
        out[1:, :] |= swept[:-1, :]
        out[:-1, :] |= swept[1:, :]
        grown = out.copy()
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        return grown
