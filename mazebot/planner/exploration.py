"""Where to go next: exploration strategies over the maze graph, and grid frontiers.

Why one module of ~1000 lines: :class:`Explorer` is one state machine over goals (choose, drive,
arrive, dwell, blacklist, retry, give up) shared by the maze mode and the frontier mode; the
strategies and the goal records above it exist only for it, and a change to how a goal is given
up touches both modes at once.

Exploring means driving to where something is still unknown until nothing reachable is.
In a maze the unknowns are **frontier links**: a link of a reachable cell whose state
(open or wall) is not known yet (Nayak et al., "2D Autonomous Mapping", III.C: "this unknown link can be referred to
as a frontier for autonomous mapping"). Going to the cell that owns the link lets the
lidar resolve it. A reachable cell whose inside has not been seen (a dead end looked at
only through its opening) is a frontier too, so every cell of the maze ends up mapped,
not just its links. Two strategies choose among them:

- :class:`DepthFirstStrategy`, the seed's choice: the most recently discovered frontier
  first (a stack), so the robot follows one branch to its end before back-tracking.
- :class:`NearestFrontierStrategy`, the default: the frontier with the cheapest route
  from the robot (cells driven plus a cost per in-place turn). When several are about
  equally near, it takes the one farthest from everything else still to do (the other
  frontiers and the start cell, where the run ends): a two-step look-ahead that
  finishes a side branch now rather than coming back for it later, which is what keeps
  the total driving close to the depth-first tour's unavoidable back-tracking while
  skipping the dead ends the lidar has already seen to the end.

A cell maze is recognised by its walls (:attr:`MazeGraph.fit`, the share of wall cells
on the lattice). Worlds that are not mazes (a room with cylinders, a maze whose walls
miss the lattice) are explored with Yamauchi's frontier-based method (Yamauchi 1997, "A
frontier-based approach for autonomous exploration"): frontier cells are known-free grid
cells next to unknown ones, grouped into connected regions (:mod:`.frontiers`). The robot
drives to a *viewpoint* of a region: a cell of the inflated costmap's configuration space
from which the lidar sees the region's unknown cells beyond its minimum range, the one
with the best trade of path cost against the unknown cells it sees.

Targets that cannot be resolved (a region the robot cannot reach or see, a link the
lidar never classifies) are blacklisted once they stop progressing, so nothing traps the
robot. How long that takes is counted in what the robot did, never in seconds: in the
map's revolutions (the lidar turns SLAM painted into the map: the evidence that could
have resolved the target) while it was the target without its route cost reaching a new
low, or while the robot stood at it. On a slower computer SLAM paints fewer revolutions
a second and the targets get as many chances as on a fast one.

A grid frontier whose unknown cells are mostly *swept* is *closed*, in both modes: on every
painted revolution the explorer counts the unknown cells next to known free space that the
lidar has in clear view (within ``view_radius_m``, beyond its minimum range, along free cells;
:class:`~mazebot.planner.frontiers.SweptCells`); one in view for ``sweep_revolutions`` that is
still unknown shows nothing new from anywhere the robot can stand. On a 16x16 maze the last
frontiers are stretches of corridor wall seen only at grazing angles: their cells flip between
unknown, free and wall as revolutions come in, the frontier vanishes as the robot comes near
and comes back behind it, and the robot drove to and fro along a corridor for them. A frontier
a resolved one leaves a few cells beyond it has new cells and is a goal, wherever it is.
In a maze, a frontier whose unknown cells lie on the line of a link the graph knows as a wall
is closed as well: those late frontiers are faces of closed blocks of cells, seen through the
gaps a grazing view leaves in a painted wall line (an opening shows no occupied cell along it).

A blacklisted target is not given up for good: it is tried again once the robot has
driven ``retry_after_m`` elsewhere (the map around it has changed), or at once when
nothing else is left, up to ``max_attempts`` attempts in all. Only when no reachable
unknown remains that has attempts left, neither a maze link nor (``map_check``) a
frontier of the grid itself (known free cells next to unknown ones: the maze graph can
misread a link as a wall), does the explorer turn to :attr:`Phase.RETURNING`, plan back to
the start, and report :attr:`Phase.DONE` on arrival.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from mazebot.config import PlannerConfig, RobotConfig
from mazebot.planner.frontiers import (
    Frontier,
    SweptCells,
    Viewpoint,
    best_viewpoint,
    find_frontiers,
    frontier_regions,
    frontier_unknowns,
    score_bound_m,
    viewpoint_candidates,
)
from mazebot.planner.global_path import (
    GridCostmap,
    cell_costs,
    cell_waypoints,
    merge_straight,
    shortcut,
    shortest_cell_path,
)
from mazebot.planner.maze_graph import Cell, Direction, MazeGraph
from mazebot.planner.passages import ClosedPassage, across_path_m, occupied_near, rasterise_segments
from mazebot.slam.grid import FREE, UNKNOWN
from mazebot.steps import all_at_once_method

# the defaults below are the config's, each written once in mazebot.config
_PLANNER = PlannerConfig()
_ROBOT = RobotConfig()

__all__ = [
    "Candidate",
    "DepthFirstStrategy",
    "Explorer",
    "Goal",
    "NearestFrontierStrategy",
    "Phase",
    "Strategy",
    "frontier_regions",
    "make_strategy",
]


class Phase(enum.StrEnum):
    """Where the run is: the planner's part of the run state."""

    EXPLORING = "exploring"
    RETURNING = "returning"
    DONE = "done"


@dataclass(frozen=True)
class Goal:
    """What the local planner should do now.

    ``waypoints_m`` is the route in the map frame from near the robot to ``target_m``
    (metres); ``cells`` the maze cells it passes through (merged: corners only), empty in
    frontier mode; ``reason`` a short human description for logs and the web page.
    """

    phase: Phase
    target_m: tuple[float, float]
    waypoints_m: list[tuple[float, float]]
    cells: list[Cell] = field(default_factory=list)
    reason: str = ""


@dataclass(frozen=True)
class Candidate:
    """A frontier the robot could resolve: ``cell``'s side ``side`` is unknown (or, with
    ``side`` None, the inside of ``cell`` has not been seen yet).

    ``cost`` is the route cost from the robot to ``cell`` (cells plus turn costs);
    ``discovered`` the update counter when the frontier was first seen.
    """

    cell: Cell
    side: Direction | None
    cost: float
    discovered: int

    @property
    def side_order(self) -> int:
        """A sortable stand-in for ``side`` (None, the cell itself, last)."""
        return 4 if self.side is None else int(self.side)


class Strategy(Protocol):
    """Picks the frontier link to resolve next."""

    name: str

    def choose(
        self, candidates: Sequence[Candidate], distances_from: Callable[[Cell], dict[Cell, float]], start_cell: Cell
    ) -> Candidate:
        """One of ``candidates`` (never empty). ``distances_from(cell)`` gives route costs from a cell."""
        ...


class DepthFirstStrategy:
    """The seed's depth-first search: the most recently discovered frontier first.

    Frontier links form a stack in the order they appear; the newest one is resolved
    next, nearer ones first among those discovered together. The robot thus follows a
    branch to its end, then back-tracks to the newest open question.
    """

    name = "dfs"

    def choose(
        self, candidates: Sequence[Candidate], distances_from: Callable[[Cell], dict[Cell, float]], start_cell: Cell
    ) -> Candidate:
        return min(candidates, key=lambda c: (-c.discovered, c.cost, c.cell, c.side_order))


class NearestFrontierStrategy:
    """The cheapest frontier to reach, breaking near-ties by what leaving it would cost later.

    ``tie_margin`` (in cell steps): candidates whose cost is within this of the cheapest
    are tied. Among tied cells, the one whose distance to the rest (every other
    frontier cell and the start cell) is largest wins: visiting it last would mean a
    long detour back, visiting it now costs the same as the others.
    """

    name = "nearest"

    def __init__(self, tie_margin: float = 0.5) -> None:
        if tie_margin < 0:
            raise ValueError(f"tie_margin must be >= 0 cells, got {tie_margin}")
        self.tie_margin = float(tie_margin)

    def choose(
        self, candidates: Sequence[Candidate], distances_from: Callable[[Cell], dict[Cell, float]], start_cell: Cell
    ) -> Candidate:
        best = min(c.cost for c in candidates)
        tied = [c for c in candidates if c.cost <= best + self.tie_margin]
        tied_cells = sorted({c.cell for c in tied})
        if len(tied_cells) == 1:
            return min(tied, key=lambda c: (c.cost, c.side_order))
        rest = {c.cell for c in candidates} - set(tied_cells) | {start_cell}
        regret: dict[Cell, float] = {}
        for cell in tied_cells:
            costs = distances_from(cell)
            others = [costs.get(r, math.inf) for r in rest if r != cell]
            regret[cell] = min(others) if others else 0.0
        return max(tied, key=lambda c: (regret[c.cell], -c.cost, -c.side_order, c.cell))


def make_strategy(name: str, tie_margin: float = 0.5) -> Strategy:
    """The strategy called ``name``: ``"nearest"`` (default) or ``"dfs"``."""
    if name == "nearest":
        return NearestFrontierStrategy(tie_margin)
    if name == "dfs":
        return DepthFirstStrategy()
    raise ValueError(f"exploration strategy must be 'nearest' or 'dfs', got {name!r}")


@dataclass(frozen=True)
class _RegionKey:
    """Identity of a frontier target: the centroid (metres) of its region when first chosen."""

    centroid_m: tuple[float, float]


@dataclass(frozen=True)
class _Region:
    """A reachable frontier region: its viewpoint (route cost in metres, score, gain), goal, centroid, size,
    and where its unknown cells are (map frame, metres: an (N, 2) array of x, y)."""

    view: Viewpoint
    goal_m: tuple[float, float]
    centroid_m: tuple[float, float]
    size: int
    unknown_m: np.ndarray

    @property
    def cost_m(self) -> float:
        return self.view.cost_m


@dataclass
class _Target:
    """Bookkeeping of one target, for switching hysteresis and blacklisting.

    The counts only run while it is the current target, and they are kept when it stops
    being one: a frontier that flickers in and out of a noisy map (or that the robot
    dithers to and from) adds up its revolutions over all its turns as the target instead
    of starting afresh each time, so it is blacklisted after ``progress_revolutions`` of
    being chosen without getting cheaper, or ``dwell_revolutions`` of the robot standing
    on it, in total.
    """

    key: object
    position_m: tuple[float, float]
    cost: float
    best_cost: float
    stalled: int = 0  # map revolutions as the target without the route cost reaching a new low
    dwelt: int = 0  # map revolutions as the target with the robot at it
    last: int | None = None  # the map's revolution count at the last tick it was the target
    at_goal: bool = False  # the robot was at it on that tick
    dropped: int = 0  # times it was left for another target while still there (grid frontiers)


@dataclass
class _GivenUp:
    """A blacklisted target: how often it was tried, and the robot's odometer when it was given up."""

    attempts: int
    travelled_m: float


class Explorer:
    """Decides the next goal each planner tick, in a maze or in any other world.

    Example::

        explorer = Explorer(start_xy_m=(0.0, 0.0))
        goal = explorer.update(grid.three_state(), grid.origin_m, grid.resolution_m, pose, revolutions)
        goal.phase, goal.waypoints_m     # hand the waypoints to the local planner
        explorer.report_unreachable()    # the local planner gave up on this goal

    Parameters: ``graph`` the maze graph to keep updated (a default one is built);
    ``strategy`` a :class:`Strategy` or its name; ``mode`` ``"auto"`` (a maze when the
    walls fit the lattice), ``"maze"`` or ``"frontier"``; ``start_xy_m`` the start pose
    (map frame, metres), where the run ends; ``maze_fit_min`` the share of wall cells on
    lattice lines that makes a maze (with ``maze_fit_hysteresis`` before leaving maze
    mode; every maze map measured fits at 1.0, while a room's first straight walls fit at
    0.91-0.96 until its cylinders and its off-lattice far wall show); ``turn_cost_cells``
    the cost of a quarter turn in cell steps; ``switch_margin``
    how much cheaper (in cell steps; in frontier mode, in cell lengths of route) a new
    target must be to replace the current one; ``goal_tolerance_m`` how close counts as
    arrived (keep it above the local planner's own tolerance, or the robot stops short
    of "arrived"); ``progress_revolutions`` how many map revolutions a target may go
    without its route cost dropping before it is blacklisted, ``dwell_revolutions`` how
    many it may stay unresolved once the robot is there (the map's revolutions are
    SLAM's painted scans, passed to :meth:`update`; 5.5 a second on an A1 when SLAM
    keeps up); ``retry_after_m`` how far the robot must drive before a blacklisted
    target is tried again, ``max_attempts`` how often a target is tried in all,
    ``max_drops`` how often a grid frontier may be left for another while it is still there
    before it is blacklisted (the robot going back and forth between frontiers);
    ``map_check`` whether a maze is done only when the grid has no reachable frontier
    either; ``footprint_radius_m``/``clearance_m`` the robot
    for the grid costmap; ``min_frontier_cells`` the smallest frontier region worth a
    visit, ``frontier_wall_margin_cells`` how close to a wall unknown cells are taken
    for wall, ``frontier_sliver_cells`` how thin an unknown area is taken for a sliver of
    wall (see :func:`~mazebot.planner.frontiers.find_frontiers`); ``lidar_min_range_m``
    the lidar's minimum range (``[lidar] min_range_m``: nothing nearer is ever seen);
    ``view_radius_m`` how far from a viewpoint the unknown cells it is counted to see may
    be (a planning range, well inside the lidar's), ``view_candidates`` how many places
    within that radius are checked for lines of sight to a region, ``view_targets`` to how
    many of its unknown cells, ``gain_weight_m`` the route metres that seeing e times more
    unknown cells is worth (see :mod:`.frontiers`); ``region_match_m`` how near a region's
    centroid must stay to be the same target from tick to tick;
    ``blacklist_radius_m`` the region around a blacklisted frontier that is skipped, and
    around a viewpoint that failed to resolve its frontier (a retry looks from elsewhere);
    ``inside_half_m`` how close (along either maze axis) the robot must come to a cell's
    centre for the cell to count as visited, its inside seen (see
    :meth:`MazeGraph.mark_looked_into`); ``recheck_revolutions`` how many map revolutions
    apart the whole grid is searched while the robot returns home; ``sweep_revolutions`` for
    how many painted revolutions the lidar must have an unknown cell in clear view for it to
    count as swept (a frontier of mostly swept cells is closed, :class:`SweptCells`).
    """

    def __init__(
        self,
        graph: MazeGraph | None = None,
        strategy: Strategy | str = _PLANNER.strategy,
        mode: Literal["auto", "maze", "frontier"] = _PLANNER.mode,
        start_xy_m: tuple[float, float] = (0.0, 0.0),
        maze_fit_min: float = 0.96,
        maze_fit_hysteresis: float = 0.04,
        turn_cost_cells: float = 0.5,
        switch_margin: float = 1.0,
        goal_tolerance_m: float = _PLANNER.goal_tolerance_m,
        progress_revolutions: int = _PLANNER.progress_revolutions,
        dwell_revolutions: int = _PLANNER.dwell_revolutions,
        retry_after_m: float = _PLANNER.retry_after_m,
        max_attempts: int = _PLANNER.max_attempts,
        max_drops: int = _PLANNER.max_drops,
        map_check: bool = True,
        footprint_radius_m: float = _ROBOT.footprint_radius_m,
        clearance_m: float = _ROBOT.clearance_m,
        min_frontier_cells: int = 4,
        frontier_wall_margin_cells: int = 2,
        frontier_sliver_cells: int = 2,
        lidar_min_range_m: float = 0.15,
        view_radius_m: float = 0.9,
        view_candidates: int = 96,
        view_targets: int = 16,
        gain_weight_m: float = 0.3,
        region_match_m: float = 0.3,
        blacklist_radius_m: float = 0.15,
        inside_half_m: float = 0.075,
        recheck_revolutions: int = 5,
        sweep_revolutions: int = 4,
    ) -> None:
        if mode not in ("auto", "maze", "frontier"):
            raise ValueError(f"mode must be 'auto', 'maze' or 'frontier', got {mode!r}")
        self.graph = graph if graph is not None else MazeGraph(anchor_xy_m=start_xy_m)
        self.strategy = make_strategy(strategy) if isinstance(strategy, str) else strategy
        self.mode_setting = mode
        self.start_xy_m = (float(start_xy_m[0]), float(start_xy_m[1]))
        self.maze_fit_min = float(maze_fit_min)
        self.maze_fit_hysteresis = float(maze_fit_hysteresis)
        self.turn_cost_cells = float(turn_cost_cells)
        self.switch_margin = float(switch_margin)
        self.goal_tolerance_m = float(goal_tolerance_m)
        if progress_revolutions < 1 or dwell_revolutions < 1 or max_attempts < 1 or max_drops < 1:
            raise ValueError(
                "need progress_revolutions, dwell_revolutions, max_attempts and max_drops >= 1, got "
                f"{progress_revolutions}, {dwell_revolutions}, {max_attempts}, {max_drops}"
            )
        self.progress_revolutions = int(progress_revolutions)
        self.dwell_revolutions = int(dwell_revolutions)
        self.retry_after_m = float(retry_after_m)
        self.max_attempts = int(max_attempts)
        self.max_drops = int(max_drops)
        self.map_check = bool(map_check)
        self.footprint_radius_m = float(footprint_radius_m)
        self.clearance_m = float(clearance_m)
        self.min_frontier_cells = int(min_frontier_cells)
        self.frontier_wall_margin_cells = int(frontier_wall_margin_cells)
        self.frontier_sliver_cells = int(frontier_sliver_cells)
        self.lidar_min_range_m = float(lidar_min_range_m)
        if view_radius_m <= lidar_min_range_m:
            raise ValueError(f"view_radius_m ({view_radius_m}) must exceed lidar_min_range_m ({lidar_min_range_m})")
        self.view_radius_m = float(view_radius_m)
        self.view_candidates = int(view_candidates)
        self.view_targets = int(view_targets)
        self.gain_weight_m = float(gain_weight_m)
        self.region_match_m = float(region_match_m)
        self.blacklist_radius_m = float(blacklist_radius_m)
        self.inside_half_m = float(inside_half_m)
        if recheck_revolutions < 1:
            raise ValueError(f"recheck_revolutions must be >= 1, got {recheck_revolutions}")
        self.recheck_revolutions = int(recheck_revolutions)
        if sweep_revolutions < 1:
            raise ValueError(f"sweep_revolutions must be >= 1, got {sweep_revolutions}")
        self.sweep_revolutions = int(sweep_revolutions)

        self.phase = Phase.EXPLORING
        self.mode: Literal["maze", "frontier"] = "frontier" if mode == "frontier" else "maze"
        self.blacklisted_links: set[tuple[Cell, Direction | None]] = set()
        self.blacklisted_points_m: list[tuple[float, float]] = []
        self.updates = 0
        self._discovered: dict[tuple[Cell, Direction | None], int] = {}
        self._target: _Target | None = None
        self._history: dict[object, _Target] = {}  # every target so far, by key: counts survive a switch
        self._given_up: dict[object, _GivenUp] = {}  # blacklisted targets, by key
        #: (region centroid, viewpoint) of grid frontiers blacklisted from there: a retry looks from elsewhere
        self._failed_views_m: list[tuple[tuple[float, float], tuple[float, float]]] = []
        #: the unknown cells the lidar had in clear view, counted in map revolutions (:class:`SweptCells`)
        self.swept = SweptCells()
        self._last_sweep: int | None = None  # the map's revolutions at the last count
        #: centroids of grid frontiers closed: most of their unknown cells were swept (the lidar had them
        #: in clear view for ``sweep_revolutions`` and they stayed unknown); no goal, there or again
        self.closed_points_m: list[tuple[float, float]] = []
        #: comebacks of each closed place (by index): a frontier there again after a tick without one
        self.comebacks: list[int] = []
        self._closed_hit: set[int] = set()  # closed places with a frontier back on the last search
        #: the region followed on the last tick (its key and where its unknown cells were)
        self._followed: tuple[object, _Region] | None = None
        self._last_grid_search: int | None = None  # the map's revolutions at the last whole-grid search
        self._frontier_unknown: np.ndarray | None = None  # the last search's frontiers' unknown cells
        self.travelled_m = 0.0  # the robot's path length so far (from the poses of the ticks)
        self._last_xy_m: tuple[float, float] | None = None
        self._revolutions = 0  # the map's revolution count at this tick
        self._costmap: GridCostmap | None = None
        #: route costs (:func:`cell_costs`) by (start cell, heading), while the graph's links stay the same:
        #: the robot spends about a second in a cell, five planner ticks on the same links and start
        self._route_costs: dict[tuple[Cell, int | None], dict[Cell, float]] = {}
        self._route_costs_version: tuple[int, int] = (-1, -1)
        #: what happened to targets since the caller last emptied it (blacklists, with why)
        self.events: list[str] = []
        #: passages the robot could not take (:mod:`.passages`): routes go round them until the map there changes
        self.closed_passages: list[ClosedPassage] = []
        self._closed_version = 0  # counts the changes of closed_passages (route caches key on it)
        #: the closed links as pairs of cells, for the current maze frame (with the version and frame read)
        self._closed_links: tuple[int, object, frozenset[frozenset[Cell]]] = (0, None, frozenset())
        #: unknown links and unseen cells reachable only through a closed passage: given up, said once
        self.beyond_closed: set[tuple[Cell, Direction | None]] = set()
        #: why the robot cannot get home (the only way passes a closed passage), else None
        self.no_way_home: str | None = None
        #: the closed passages were opened once already because they closed the only way home
        self._home_retested = False

    # -- the tick ------------------------------------------------------------------------

    def update_steps(
        self,
        three_state: np.ndarray,
        grid_origin_m: tuple[float, float],
        resolution_m: float,
        pose: tuple[float, float, float],
        revolutions: int | None = None,
    ) -> Generator[None, None, Goal | None]:
        """:meth:`update` in two stages (:mod:`mazebot.steps`): the maze graph from the map, then the goal."""
        self.updates += 1
        self._revolutions = self.updates if revolutions is None else int(revolutions)
        xy = (float(pose[0]), float(pose[1]))
        if self._last_xy_m is not None:
            self.travelled_m += math.dist(xy, self._last_xy_m)
        self._last_xy_m = xy
        grid = np.asarray(three_state)
        self._costmap = None
        if self._last_sweep is None or self._revolutions > self._last_sweep:  # one count per painted revolution
            self._last_sweep = self._revolutions
            self.swept.count(grid, grid_origin_m, resolution_m, xy, self.lidar_min_range_m, self.view_radius_m)
        if self.mode_setting != "frontier":
            self.graph.update(grid, grid_origin_m, resolution_m)
            yield
        self._expire_closed(grid, grid_origin_m, resolution_m)
        self._choose_mode()
        if self.phase is Phase.DONE:
            return Goal(Phase.DONE, self.start_xy_m, [self.start_xy_m], reason="done: back at the start")
        if not _known_free_at(grid, grid_origin_m, resolution_m, pose) or (
            self.mode == "maze" and self.graph.frame is None
        ):
            return None  # the map does not cover the robot yet (first scans): an empty map is not "done"
        self._retry_given_up(everything=False)
        goal = yield from self._explore_goal_steps(grid, grid_origin_m, resolution_m, pose)
        if goal is None and self._retry_given_up(everything=True):  # nothing else left: try them again
            goal = yield from self._explore_goal_steps(grid, grid_origin_m, resolution_m, pose)
        if goal is None:
            goal = self._return_goal(grid, grid_origin_m, resolution_m, pose)
        return goal

    update = all_at_once_method(
        update_steps,
        """Read the map, choose the next goal; None only when there is nothing to do yet.

        ``pose`` is the robot's map-frame ``(x_m, y_m, theta_rad)``; ``revolutions`` the
        count of lidar revolutions painted into the map so far (SLAM's), the clock of the
        blacklisting (None: count this explorer's updates instead). Returns a goal in
        every phase (in DONE: stay at the start); None before the map holds anything to
        plan on.
        """,
    )

    def _explore_goal_steps(
        self, grid: np.ndarray, origin: tuple[float, float], resolution_m: float, pose: tuple[float, float, float]
    ) -> Generator[None, None, Goal | None]:
        """The next unknown to resolve: a maze link or cell, else (``map_check``) a frontier of the grid.

        In stages: a frontier goal reads the whole grid several times (the frontiers, a
        distance transform, a search over every free cell, the viewpoints, the path), 25 ms
        on a 16x16 maze here, four times that on a Pi 4's share; the event loop (and the
        planner task's own motion half, see :mod:`mazebot.tasks.planner_task`) runs between.
        """
        if self.mode == "maze":
            goal = self._maze_goal(pose)
            if goal is None and self.map_check and self._grid_search_due():
                # the graph knows no unknown link: the grid itself must not know any
                # known free space next to unknown space the robot can reach either
                yield
                goal = yield from self._frontier_goal_steps(grid, origin, resolution_m, pose)
            return goal
        if not self._grid_search_due():
            return None
        return (yield from self._frontier_goal_steps(grid, origin, resolution_m, pose))

    def _grid_search_due(self) -> bool:
        """False while the robot returns home and the grid was searched less than ``recheck_revolutions``
        map revolutions ago.

        Once nothing is left the robot drives home, and a search of the whole grid on every
        tick (its frontiers, a distance transform, viewpoints: 25-45 ms on a 16x16 maze here,
        four times that on a Pi 4's share) would find the same nothing; a frontier that the
        map still shows is found a second or so later (counted in revolutions the map took
        in, so a slower CPU searches as often per revolution, not per second).
        """
        last = self._last_grid_search
        if self.phase is Phase.RETURNING and last is not None and self._revolutions - last < self.recheck_revolutions:
            return False
        self._last_grid_search = self._revolutions
        return True

    def _retry_given_up(self, everything: bool) -> bool:
        """Take blacklisted targets with attempts left off the blacklist; True if any was.

        Those given up ``retry_after_m`` of driving ago, or (``everything``) all of them:
        the robot has nothing else left to do.
        """
        retried = False
        for key, given_up in list(self._given_up.items()):
            if given_up.attempts >= self.max_attempts or key not in self._blacklisted_keys():
                continue
            if not everything and self.travelled_m - given_up.travelled_m < self.retry_after_m:
                continue
            if isinstance(key, _RegionKey):
                self.blacklisted_points_m.remove(key.centroid_m)
            else:
                self.blacklisted_links.discard(key)
            target = self._history.get(key)
            if target is not None:  # a fresh start: its counts begin again
                target.stalled, target.dwelt, target.dropped, target.best_cost = 0, 0, 0, math.inf
            retried = True
        return retried

    def _blacklisted_keys(self) -> set[object]:
        return {*self.blacklisted_links, *(_RegionKey(c) for c in self.blacklisted_points_m)}

    def report_unreachable(self, now_s: float | None = None) -> None:
        """The local planner could not reach the current goal: blacklist it and choose again."""
        target = self._target
        if target is None or self.phase is not Phase.EXPLORING:
            return
        self._blacklist(target, "the local planner could not reach it")

    def reset(self) -> None:
        """Start a new run: forget the phase, targets and blacklists (the graph follows the map)."""
        self.phase = Phase.EXPLORING
        self.blacklisted_links.clear()
        self.blacklisted_points_m.clear()
        self._discovered.clear()
        self._history.clear()
        self._given_up.clear()
        self._failed_views_m.clear()
        self.swept = SweptCells()
        self._last_sweep = None
        self.closed_points_m.clear()
        self.comebacks.clear()
        self._closed_hit.clear()
        self._followed = None
        self._last_grid_search = None
        self._frontier_unknown = None
        self._target = None
        self.forget_closed()

    def forget_closed(self) -> None:
        """Forget every closed passage (a new run, or a start pressed after the robot said it had no way
        home: the user may have moved what closed it)."""
        self.closed_passages.clear()
        self._closed_version += 1
        self.beyond_closed.clear()
        self.no_way_home = None
        self._home_retested = False

    def _choose_mode(self) -> None:
        if self.mode_setting != "auto":
            self.mode = self.mode_setting
            return
        if not self.graph.ready:
            self.mode = "frontier"
            return
        threshold = self.maze_fit_min - (self.maze_fit_hysteresis if self.mode == "maze" else 0.0)
        self.mode = "maze" if self.graph.fit >= threshold else "frontier"

    # -- maze mode -----------------------------------------------------------------------

    def _maze_goal(self, pose: tuple[float, float, float]) -> Goal | None:
        graph = self.graph
        frame = graph.frame
        if frame is None:
            return None
        robot = frame.cell_of(pose[0], pose[1])
        uv_m = frame.to_maze(np.array(pose[:2]))[0] - (np.array(robot) + 0.5) * frame.cell_size_m
        if float(np.abs(uv_m).max()) <= self.inside_half_m:  # well inside, not just across the border
            graph.mark_looked_into(robot)  # been there: nothing more to see inside it
        heading = _heading_index(pose[2], frame.angle_rad)
        costs = self._costs_from(robot, heading)
        if self.closed_passages:
            self._note_beyond_closed(robot, costs)
        links: list[tuple[Cell, Direction | None]] = []
        for cell in sorted(costs):
            links.extend((cell, side) for side in graph.unknown_sides(cell))
            if graph.needs_look(cell) and cell != robot:  # from inside, its walls are within the lidar's min range
                links.append((cell, None))
        for link in links:
            self._discovered.setdefault(link, self.updates)
        candidates = [
            Candidate(cell, side, costs[cell], self._discovered[(cell, side)])
            for cell, side in links
            if (cell, side) not in self.blacklisted_links
        ]
        if not candidates:
            # No link left. A grid frontier being followed (``map_check``) stays the target:
            # forgetting it here each tick made every frontier tick a first choice, with no
            # hysteresis, no kept viewpoint and no revolutions counted towards a blacklist.
            if self._target is not None and not isinstance(self._target.key, _RegionKey):
                self._target = None
            return None
        self.phase = Phase.EXPLORING

        def distances_from(cell: Cell) -> dict[Cell, float]:
            return self._costs_from(cell, None)

        start_cell = frame.cell_of(*self.start_xy_m)
        choice = self.strategy.choose(candidates, distances_from, start_cell)
        current = self._target
        keys = {(c.cell, c.side): c for c in candidates}
        if current is not None and current.key in keys:
            kept = keys[current.key]
            if self.strategy.name == "dfs":  # stay on a branch until a newer frontier appears
                keep = kept.discovered >= choice.discovered
            else:  # switch only for a clearly cheaper target: no dithering between equals
                keep = kept.cost <= choice.cost + self.switch_margin
            if keep:
                choice = kept
        position = frame.cell_center_m(choice.cell)
        target = self._track((choice.cell, choice.side), position, choice.cost, at_goal=choice.cell == robot)
        if target is None:  # just blacklisted (no progress): choose again among the rest
            return self._maze_goal(pose) if candidates[1:] else None
        route = shortest_cell_path(self._neighbours(), robot, choice.cell, heading, self.turn_cost_cells)
        side = "its inside" if choice.side is None else f"its {choice.side.name} side"
        what = f"look at {side} of cell {choice.cell}"
        cells = merge_straight(route or [choice.cell])
        return Goal(
            Phase.EXPLORING,
            position,
            cell_waypoints(cells, frame.cell_center_m),
            cells,
            f"{what} ({self.strategy.name})",
        )

    def _costs_from(self, cell: Cell, heading: int | None) -> dict[Cell, float]:
        """:func:`cell_costs` from ``cell`` facing ``heading`` over the graph's open links (read only).

        The same dict again while the open links have not changed (``MazeGraph.open_version``:
        the search reads nothing else of the graph).
        """
        graph = self.graph
        version = (graph.open_version, self._closed_version)
        if self._route_costs_version != version:
            self._route_costs.clear()
            self._route_costs_version = version
        key = (cell, heading)
        costs = self._route_costs.get(key)
        if costs is None:
            costs = self._route_costs[key] = cell_costs(self._neighbours(), cell, heading, self.turn_cost_cells)
        return costs

    # -- frontier mode -------------------------------------------------------------------

    def _costmap_for(self, grid: np.ndarray, origin: tuple[float, float], resolution_m: float) -> GridCostmap:
        if self._costmap is None:
            closed = None
            if self.closed_passages:
                segments = [p.segment_m for p in self.closed_passages]
                closed = rasterise_segments(segments, grid.shape, origin, resolution_m)
            self._costmap = GridCostmap(
                grid, origin, resolution_m, self.footprint_radius_m, self.clearance_m, closed_cells=closed
            )
        return self._costmap

    def _frontier_goal_steps(
        self,
        grid: np.ndarray,
        origin: tuple[float, float],
        resolution_m: float,
        pose: tuple[float, float, float],
    ) -> Generator[None, None, Goal | None]:
        current = self._target
        anchor = current.key.centroid_m if current is not None and isinstance(current.key, _RegionKey) else None
        kept_goal = current.position_m if anchor is not None and current is not None else None
        options = yield from self._frontier_options_steps(
            grid, origin, resolution_m, (pose[0], pose[1]), anchor, kept_goal
        )
        followed, self._followed = self._followed, None
        still_there = anchor is not None and any(math.dist(o.centroid_m, anchor) < self.region_match_m for o in options)
        followed_gone = followed is not None and current is not None and followed[0] == current.key and not still_there
        if followed is not None and followed_gone and self.mode == "maze":  # the grid's check of a maze
            self._log_gone(followed[1], grid, origin, resolution_m, pose)  # the followed frontier is gone
        if not options:
            self._target = None
            return None
        costmap = self._costmap_for(grid, origin, resolution_m)
        self.phase = Phase.EXPLORING
        choice = options[0]
        same: _Region | None = None
        if anchor is not None:
            same = next((o for o in options if math.dist(o.centroid_m, anchor) < self.region_match_m), None)
            margin_m = self.switch_margin * self.graph.cell_size_m
            if same is not None and same.view.score_m <= choice.view.score_m + margin_m:
                choice = same
        if current is not None and same is not None and choice is not same:
            # left for another while it is still there: a frontier the robot keeps going to
            # and turning away from is blacklisted after max_drops of the explorer's choices
            current.dropped += 1
            if current.dropped >= self.max_drops:
                self._blacklist(current, f"left for another frontier {current.dropped} times")
        key = current.key if current is not None and choice is same else self._region_key(choice.centroid_m)
        at_goal = math.dist((pose[0], pose[1]), choice.goal_m) < self.goal_tolerance_m + resolution_m
        if self._track(key, choice.goal_m, choice.cost_m, at_goal) is None:
            # just blacklisted (no progress): choose again among the rest
            return (yield from self._frontier_goal_steps(grid, origin, resolution_m, pose))
        self._followed = (key, choice)
        yield
        path = costmap.plan((pose[0], pose[1]), choice.goal_m)
        waypoints = shortcut(path, costmap) if path else [choice.goal_m]
        cx, cy = choice.centroid_m
        return Goal(
            Phase.EXPLORING,
            choice.goal_m,
            waypoints,
            [],
            f"frontier of {choice.size} cells at {cx:.2f}, {cy:.2f} (sees {choice.view.gain:.0f} unknown)",
        )

    def _frontier_options_steps(
        self,
        grid: np.ndarray,
        origin: tuple[float, float],
        resolution_m: float,
        robot_xy_m: tuple[float, float],
        anchor_m: tuple[float, float] | None = None,
        kept_goal_m: tuple[float, float] | None = None,
    ) -> Generator[None, None, list[_Region]]:
        """Reachable, non-blacklisted frontier regions with their best viewpoints, lowest score first.

        Regions are looked at in the order of a lower bound of their score (the cheapest
        place near them, seeing all their unknown cells) and those that cannot beat the
        best found so far are skipped, except the current target's (near ``anchor_m``),
        whose last viewpoint ``kept_goal_m`` is a candidate again so it can be kept. The
        costmap (a distance transform of the whole grid) is only made when there are
        frontiers: in a maze, once the graph knows every link, the grid's check finds none
        on most ticks.
        """
        frontiers = find_frontiers(
            grid, self.min_frontier_cells, self.frontier_wall_margin_cells, self.frontier_sliver_cells
        )
        self._frontier_unknown = np.zeros(grid.shape, dtype=bool)  # every frontier's unknown cells, this tick
        for frontier in frontiers:
            self._frontier_unknown[frontier.unknown[:, 0], frontier.unknown[:, 1]] = True
        if not frontiers:
            self._note_comebacks(set())
            return []
        yield
        costmap = self._costmap_for(grid, origin, resolution_m)
        yield
        distances = costmap.distances_from(robot_xy_m)
        cost_cells = np.where(costmap.passable, distances, np.inf)
        free = grid == FREE
        swept = self.swept.swept_mask(grid.shape, origin, resolution_m, self.sweep_revolutions)
        hits: set[int] = set()
        fresh: set[int] = set()
        ranked: list[tuple[float, bool, Frontier, tuple[float, float], np.ndarray]] = []
        for frontier in frontiers:
            centroid = costmap.to_world(*frontier.centroid_rc)
            if any(math.dist(centroid, b) < self.blacklist_radius_m for b in self.blacklisted_points_m):
                continue
            why = self._nothing_new(frontier, swept, origin, resolution_m)
            if why is not None:  # mostly cells the lidar had in view, or a wall the graph knows: nothing new
                hits.add(self._close(centroid, why, fresh))
                continue
            excluded = self._failed_view_mask(centroid, costmap)
            candidates = viewpoint_candidates(frontier, cost_cells, resolution_m, self.view_radius_m, excluded)
            if candidates.shape[0] == 0:
                continue  # no place within view of it the robot can get to: unreachable for now
            bound = score_bound_m(frontier, candidates, cost_cells, resolution_m, self.gain_weight_m)
            is_current = anchor_m is not None and math.dist(centroid, anchor_m) < self.region_match_m
            ranked.append((bound, is_current, frontier, centroid, candidates))
        self._note_comebacks(hits, fresh)
        ranked.sort(key=lambda item: (not item[1], item[0]))  # the current target first, then by bound
        options: list[_Region] = []
        best = math.inf
        for bound, is_current, frontier, centroid, candidates in ranked:
            if not is_current and bound >= best:
                continue
            yield
            extra = None
            if is_current and kept_goal_m is not None:
                cell = costmap.to_cell(*kept_goal_m)
                extra = cell if costmap.contains(*cell) else None
            view = best_viewpoint(
                frontier,
                candidates,
                free,
                cost_cells,
                resolution_m,
                self.lidar_min_range_m,
                self.view_radius_m,
                self.gain_weight_m,
                self.view_candidates,
                self.view_targets,
                extra,
                keep_margin_m=self.switch_margin * self.graph.cell_size_m,
            )
            if view is None:
                continue  # nowhere it could be seen from
            unknown_m = np.column_stack((frontier.unknown[:, 1], frontier.unknown[:, 0])) + 0.5
            unknown_m = unknown_m * resolution_m + np.asarray(origin, dtype=np.float64)
            options.append(
                _Region(view, costmap.to_world(*view.cell), centroid, int(frontier.cells.shape[0]), unknown_m)
            )
            best = min(best, view.score_m)
        options.sort(key=lambda o: (o.view.score_m, -o.size))
        return options

    def _log_gone(
        self,
        region: _Region,
        grid: np.ndarray,
        origin: tuple[float, float],
        resolution_m: float,
        pose: tuple[float, float, float],
    ) -> None:
        """Log what became of the followed ``region``'s unknown cells when it vanished with the robot within view.

        Gone: most of its unknown cells belong to no frontier of this tick's search; a region
        that only moved or merged (its centroid farther than ``region_match_m`` from where it was
        first chosen) is still there and not logged. A log line, nothing more (a maze's grid
        check only): whether a frontier back there is a goal again is decided by its cells
        (:meth:`_close`), not by this vanishing. On a 16x16 maze the corridor walls' cells flip
        between unknown, free and wall with the revolutions (the lines say how many were painted).
        """
        if region.unknown_m.shape[0] == 0:
            return
        near_m = float(np.min(np.hypot(region.unknown_m[:, 0] - pose[0], region.unknown_m[:, 1] - pose[1])))
        if near_m > self.view_radius_m:
            return
        rows, cols = _cells_of(region.unknown_m, grid.shape, origin, resolution_m)
        owned = self._frontier_unknown
        if owned is not None and owned.shape == grid.shape and 2 * np.count_nonzero(owned[rows, cols]) >= rows.size:
            return  # still a frontier's: it moved or merged, it did not vanish
        cx, cy = region.centroid_m
        self.events.append(
            f"frontier at {cx:.2f}, {cy:.2f} gone with the robot {near_m:.2f} m from it "
            f"({self._why_gone(region, grid, origin, resolution_m)})"
        )

    def _nothing_new(
        self, frontier: Frontier, swept: np.ndarray, origin: tuple[float, float], resolution_m: float
    ) -> str | None:
        """Why driving to ``frontier`` would show nothing new (for the log), or None when it may.

        Most of its unknown cells are *swept*: the lidar had them in clear view, within
        ``view_radius_m`` and beyond its minimum range, for ``sweep_revolutions`` painted
        revolutions while they stayed unknown (:class:`SweptCells`); looking again from
        anywhere the robot can stand shows the same. A frontier a resolved one leaves a few
        cells beyond it (a corridor or a room seen further) has new cells and stays a goal,
        wherever it is: the rule holds in frontier mode too, where closing by place stopped
        6x6 runs at coverage 0.18-0.45.

        In a maze, also when most of its unknown cells lie on the line of a link the graph
        knows as a wall (:meth:`MazeGraph.on_walls`, within the wall band of the frontiers'
        wall margin): the stretch of a wall the lidar saw only at grazing angles, with the
        unknown inside of a closed block of cells behind it (a 16x16 maze's late frontiers,
        which the robot drove back along the bottom corridor for). The grid's check is there
        for a link the graph misread as a wall, and an opening shows no occupied cell along it.
        """
        n = frontier.unknown.shape[0]
        swept_cells = int(np.count_nonzero(swept[frontier.unknown[:, 0], frontier.unknown[:, 1]]))
        if 2 * swept_cells > n:
            revolutions = self.sweep_revolutions
            return f"{swept_cells} of its {n} unknown cells swept (in the lidar's view for {revolutions} revolutions)"
        if self.mode != "maze" or self.graph.frame is None:
            return None
        xy_m = (frontier.unknown[:, ::-1] + 0.5) * resolution_m + np.asarray(origin, dtype=np.float64)
        band_m = self.graph.wall_thickness_m / 2 + self.frontier_wall_margin_cells * resolution_m
        walled = int(np.count_nonzero(self.graph.on_walls(xy_m, band_m)))
        if 2 * walled > n:
            return f"{walled} of its {n} unknown cells on walls the maze graph knows"
        return None

    def _close(self, centroid_m: tuple[float, float], why: str, fresh: set[int]) -> int:
        """A frontier at ``centroid_m`` that would show nothing new (``why``) is no goal: the index of its
        closed place (a new one, added to ``fresh`` and logged, when none is within ``region_match_m``)."""
        k = self._closed_near(centroid_m)
        if k is None:
            k = len(self.closed_points_m)
            self.closed_points_m.append(centroid_m)
            self.comebacks.append(0)
            fresh.add(k)
            self.events.append(f"closed frontier at {centroid_m[0]:.2f}, {centroid_m[1]:.2f}: {why}: not a goal")
        return k

    def _why_gone(
        self, region: _Region, grid: np.ndarray, origin: tuple[float, float], resolution_m: float
    ) -> str:
        """What became of a vanished region's unknown cells, for the log: painted, now within the
        wall margin of an occupied cell, now part of a sliver, or still unknown (the region then
        fell below ``min_frontier_cells`` or out of every viewpoint's sight)."""
        rows, cols = _cells_of(region.unknown_m, grid.shape, origin, resolution_m)
        unknown = grid[rows, cols] == UNKNOWN
        off_walls = frontier_unknowns(grid, self.frontier_wall_margin_cells, 0)[rows, cols]
        counted = frontier_unknowns(grid, self.frontier_wall_margin_cells, self.frontier_sliver_cells)[rows, cols]
        return (
            f"of its {region.unknown_m.shape[0]} unknown cells {np.count_nonzero(~unknown)} painted, "
            f"{np.count_nonzero(unknown & ~off_walls)} beside a wall, {np.count_nonzero(off_walls & ~counted)} "
            f"in a sliver, {np.count_nonzero(counted)} still counted"
        )

    def _closed_near(self, centroid_m: tuple[float, float]) -> int | None:
        """The index of the closed place within ``region_match_m`` of ``centroid_m``, else None."""
        best, best_m = None, self.region_match_m
        for k, point in enumerate(self.closed_points_m):
            d_m = math.dist(point, centroid_m)
            if d_m < best_m:
                best, best_m = k, d_m
        return best

    def _note_comebacks(self, hits: set[int], fresh: set[int] | None = None) -> None:
        """Count and report the closed places with a frontier again that had none on the last search
        (``fresh``: those closed on this one)."""
        for k in sorted(hits - self._closed_hit - (fresh or set())):
            self.comebacks[k] += 1
            cx, cy = self.closed_points_m[k]
            self.events.append(
                f"frontier back at closed {cx:.2f}, {cy:.2f} (comeback {self.comebacks[k]}): not a goal again"
            )
        self._closed_hit = hits

    def _failed_view_mask(self, centroid_m: tuple[float, float], costmap: GridCostmap) -> np.ndarray | None:
        """Cells near viewpoints from which this region (matched by centroid) was already given up on."""
        views = [v for c, v in self._failed_views_m if math.dist(c, centroid_m) < self.region_match_m]
        if not views:
            return None
        mask = np.zeros(costmap.shape, dtype=bool)
        radius = self.blacklist_radius_m / costmap.resolution_m
        for view in views:
            r, c = costmap.to_cell(*view)
            r0, r1 = max(0, math.floor(r - radius)), min(costmap.shape[0], math.ceil(r + radius) + 1)
            c0, c1 = max(0, math.floor(c - radius)), min(costmap.shape[1], math.ceil(c + radius) + 1)
            rr, cc = np.mgrid[r0:r1, c0:c1]
            mask[r0:r1, c0:c1] |= (rr - r) ** 2 + (cc - c) ** 2 <= radius**2
        return mask

    # -- returning -----------------------------------------------------------------------

    def _return_goal(
        self, grid: np.ndarray, origin: tuple[float, float], resolution_m: float, pose: tuple[float, float, float]
    ) -> Goal:
        self.phase = Phase.RETURNING
        self._target = None
        frame = self.graph.frame
        if self.mode == "maze" and frame is not None:
            start_cell = frame.cell_of(*self.start_xy_m)
            target = frame.cell_center_m(start_cell)
            if math.dist((pose[0], pose[1]), target) <= self.goal_tolerance_m:
                self.phase = Phase.DONE
                return Goal(Phase.DONE, target, [target], [start_cell], "done: back at the start cell")
            robot = frame.cell_of(pose[0], pose[1])
            heading = _heading_index(pose[2], frame.angle_rad)
            route = shortest_cell_path(self._neighbours(), robot, start_cell, heading, self.turn_cost_cells)
            if route is not None:
                cells = merge_straight(route)
                waypoints = cell_waypoints(cells, frame.cell_center_m)
                return Goal(Phase.RETURNING, target, waypoints, cells, "return to start")
            if self.closed_passages and shortest_cell_path(self.graph.open_neighbours, robot, start_cell) is not None:
                if self._retest_home():  # the only way home is a closed passage: once, it is tried again
                    return self._return_goal(grid, origin, resolution_m, pose)
                return self._no_way_home(target, pose)
            # no open-link route (a link misread as a wall): plan on the grid instead
            costmap = self._costmap_for(grid, origin, resolution_m)
            path = costmap.plan((pose[0], pose[1]), target)
            waypoints = _ending_at(shortcut(path, costmap) if path else [], target)
            return Goal(Phase.RETURNING, target, waypoints, [], "return to start (grid route)")
        target = self.start_xy_m
        if math.dist((pose[0], pose[1]), target) <= self.goal_tolerance_m:
            self.phase = Phase.DONE
            return Goal(Phase.DONE, target, [target], [], "done: back at the start")
        costmap = self._costmap_for(grid, origin, resolution_m)
        path = costmap.plan((pose[0], pose[1]), target)
        if path is None and self.closed_passages:
            if self._retest_home():
                return self._return_goal(grid, origin, resolution_m, pose)
            return self._no_way_home(target, pose)
        waypoints = _ending_at(shortcut(path, costmap) if path else [], target)
        return Goal(Phase.RETURNING, target, waypoints, [], "return to start")

    # -- passages the robot could not take -------------------------------------------------

    def close_passage(
        self, path_m: np.ndarray, k: int, three_state: np.ndarray, origin_m: tuple[float, float], resolution_m: float
    ) -> ClosedPassage:
        """Remember that no lane reached point ``k`` of the path ``path_m`` ((M, 2) map frame, in order):
        in a maze the link the path crosses nearest to it, elsewhere a short segment across the path.

        Routes go round it from the next update (:meth:`_neighbours`, :meth:`_costmap_for`) until the
        map near it changes (:meth:`_expire_closed`).
        """
        pts = np.asarray(path_m, dtype=np.float64).reshape(-1, 2)
        where = (float(pts[k, 0]), float(pts[k, 1]))
        evidence = occupied_near(three_state, origin_m, resolution_m, where)
        crossing = self._crossing_near(pts, k) if self.mode == "maze" else None
        if crossing is None:
            passage = ClosedPassage(where, None, None, across_path_m(pts, k), evidence)
        else:
            a, b = crossing
            frame = self.graph.frame
            assert frame is not None  # a crossing needs cells
            side = Direction.between(a, b)
            passage = ClosedPassage(
                where, (a, side), (frame.cell_center_m(a), frame.cell_center_m(b)), self._boundary_m(a, side), evidence
            )
        self.closed_passages.append(passage)
        self._closed_version += 1
        self.no_way_home = None
        self.events.append(
            f"closed for this robot: {passage.describe()} (no lane for its body on the local map; "
            f"{evidence.shape[0]} occupied cells near it): routes go round it until the map there changes"
        )
        return passage

    def _crossing_near(self, pts: np.ndarray, k: int) -> tuple[Cell, Cell] | None:
        """The two cells of the link the path crosses nearest (along the path) to its point ``k``."""
        frame = self.graph.frame
        if frame is None or pts.shape[0] < 2:
            return None
        cells = [frame.cell_of(float(x), float(y)) for x, y in pts]
        best: tuple[int, tuple[Cell, Cell]] | None = None
        for i in range(1, len(cells)):
            a, b = cells[i - 1], cells[i]
            if abs(a[0] - b[0]) + abs(a[1] - b[1]) != 1:
                continue
            gap = abs(i - k)
            if best is None or gap < best[0]:
                best = (gap, (a, b))
        return None if best is None else best[1]

    def _boundary_m(self, cell: Cell, side: Direction) -> tuple[tuple[float, float], tuple[float, float]]:
        """The two posts (map frame) of ``cell``'s side ``side``: the link's boundary."""
        frame = self.graph.frame
        assert frame is not None
        c = frame.cell_size_m
        i, j = cell
        corners = {
            Direction.E: ((i + 1, j), (i + 1, j + 1)),
            Direction.N: ((i, j + 1), (i + 1, j + 1)),
            Direction.W: ((i, j), (i, j + 1)),
            Direction.S: ((i, j), (i + 1, j)),
        }[side]
        uv = np.array(corners, dtype=np.float64) * c
        xy = frame.to_map(uv)
        return ((float(xy[0, 0]), float(xy[0, 1])), (float(xy[1, 0]), float(xy[1, 1])))

    def _neighbours(self) -> Callable[[Cell], list[Cell]]:
        """The graph's open neighbours without the closed links (the graph's own function when none is)."""
        closed = self._closed_link_pairs()
        if not closed:
            return self.graph.open_neighbours
        graph = self.graph

        def neighbours(cell: Cell) -> list[Cell]:
            return [n for n in graph.open_neighbours(cell) if frozenset((cell, n)) not in closed]

        return neighbours

    def _closed_link_pairs(self) -> frozenset[frozenset[Cell]]:
        """The closed links as pairs of neighbouring cells in the current frame (kept while both stay)."""
        frame = self.graph.frame
        version, kept_frame, pairs = self._closed_links
        if version == self._closed_version and kept_frame is frame:
            return pairs
        found = set()
        for passage in self.closed_passages:
            if passage.cells_m is None or frame is None:
                continue
            a, b = (frame.cell_of(*xy) for xy in passage.cells_m)
            if abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1:
                found.add(frozenset((a, b)))
        pairs = frozenset(found)
        self._closed_links = (self._closed_version, frame, pairs)
        if kept_frame is not frame:
            self._route_costs_version = (-1, -1)  # the same version, other cells: the costs kept are stale
        return pairs

    def _expire_closed(self, grid: np.ndarray, origin: tuple[float, float], resolution_m: float) -> None:
        """Forget the closed passages whose map has changed (the map may have been wrong there): tried again."""
        for passage in list(self.closed_passages):
            if passage.map_changed(grid, origin, resolution_m):
                self.closed_passages.remove(passage)
                self._closed_version += 1
                self.no_way_home = None
                self.events.append(f"{passage.describe()} open again: the map near it changed, it is tried again")

    def _note_beyond_closed(self, robot: Cell, costs: dict[Cell, float]) -> None:
        """Give up (once, counted) the unknowns reachable only through closed passages."""
        graph = self.graph
        beyond: set[tuple[Cell, Direction | None]] = set()
        for cell in graph.reachable(robot) - costs.keys():
            beyond.update((cell, side) for side in graph.unknown_sides(cell))
            if graph.needs_look(cell):
                beyond.add((cell, None))
        new = beyond - self.beyond_closed
        if new:
            self.beyond_closed |= new
            self.events.append(
                f"{len(new)} unknown links or cells reachable only through a closed passage given up "
                f"({len(self.beyond_closed)} so far)"
            )

    def _retest_home(self) -> bool:
        """The closed passages close the only way home: open them all again, once a run (True if it did).

        A give-up while returning can be a passing trouble the lane check took for a closed passage
        (a hand-built 8x8 maze: the robot stood 135 revolutions at a corner, then drove through it
        once the goal was given up); home is worth a second try before the motors stop for good.
        """
        if self._home_retested:
            return False
        self._home_retested = True
        closed = "; ".join(p.describe() for p in self.closed_passages)
        self.closed_passages.clear()
        self._closed_version += 1
        self._costmap = None
        self.events.append(f"the only way home passes {closed}: opened again, tried once more")
        return True

    def _no_way_home(self, target: tuple[float, float], pose: tuple[float, float, float]) -> Goal:
        """The goal when the only way home passes a closed passage: stay; :attr:`no_way_home` says why."""
        closed = "; ".join(p.describe() for p in self.closed_passages)
        self.no_way_home = f"no way home at ({pose[0]:.2f}, {pose[1]:.2f}) for this robot: {closed} closed"
        return Goal(Phase.RETURNING, target, [(float(pose[0]), float(pose[1]))], [], "no way home")

    # -- target bookkeeping --------------------------------------------------------------

    def _track(self, key: object, position: tuple[float, float], cost: float, at_goal: bool) -> _Target | None:
        """Keep counts for the target; blacklist it (returning None) when it stops progressing.

        The map's revolutions count only between consecutive ticks on the same target, so
        a target picked up again later continues its counts where it left them (see
        :class:`_Target`).
        """
        now = self._revolutions
        target = self._history.get(key)
        if target is None:
            target = _Target(key, position, cost, best_cost=cost)
            self._history[key] = target
        continued = self._target is target and target.last is not None
        step = max(0, now - target.last) if continued and target.last is not None else 0
        if not continued and cost > target.best_cost + self._fresh_margin(key):
            # Chosen again from much farther away than its best (the robot went elsewhere
            # meanwhile): progress counts from here, or the drive back would count as
            # stalled until it gets closer than it once was. Its stalled count is kept.
            target.best_cost = cost
        self._target = target
        target.position_m, target.cost = position, cost
        if cost < target.best_cost - 1e-6:
            target.best_cost, target.stalled = cost, 0
        else:
            target.stalled += step
        if at_goal and continued and target.at_goal:
            target.dwelt += step
        target.last, target.at_goal = now, at_goal
        stalled = target.stalled > self.progress_revolutions
        dwelt = target.dwelt > self.dwell_revolutions
        if stalled or dwelt:
            self._blacklist(target, f"chosen {target.stalled} map revolutions without progress, {target.dwelt} there")
            return None
        return target

    def _region_key(self, centroid_m: tuple[float, float]) -> _RegionKey:
        """The key of the region target chosen before nearest ``centroid_m`` (within ``region_match_m``,
        not blacklisted), else a new one.

        A frontier region changes shape as the map grows (its centroid moves by cells from tick
        to tick): matched by place, a region dropped and chosen again goes on with its counts
        (revolutions stalled and dwelt, times dropped) instead of starting afresh as a new target.
        """
        blacklisted = set(self.blacklisted_points_m)
        best: _RegionKey | None = None
        best_m = self.region_match_m
        for key in self._history:
            if isinstance(key, _RegionKey) and key.centroid_m not in blacklisted:
                d_m = math.dist(key.centroid_m, centroid_m)
                if d_m < best_m:
                    best, best_m = key, d_m
        return best if best is not None else _RegionKey(centroid_m)

    def _near_region(self, a: object, b: object) -> bool:
        """True when two grid-frontier targets are one region (their centroids within the blacklist radius)."""
        return (
            isinstance(a, _RegionKey)
            and isinstance(b, _RegionKey)
            and math.dist(a.centroid_m, b.centroid_m) < self.blacklist_radius_m
        )

    def _fresh_margin(self, key: object) -> float:
        """How much costlier than its best a target picked up again must be to count progress afresh.

        Two switching margins (cells in a maze, metres for grid frontiers): a target
        that flickers or is dithered to and from comes back at about its old cost and
        keeps its clocks.
        """
        margin = 2.0 * self.switch_margin
        return margin * self.graph.cell_size_m if isinstance(key, _RegionKey) else margin

    def _blacklist(self, target: _Target, why: str) -> None:
        key = target.key
        attempts = 1 + max(
            (g.attempts for k, g in self._given_up.items() if k == key or self._near_region(k, key)), default=0
        )
        self._given_up[key] = _GivenUp(attempts, self.travelled_m)
        what = f"frontier at {key.centroid_m[0]:.2f}, {key.centroid_m[1]:.2f}" if isinstance(key, _RegionKey) else key
        again = "given up" if attempts >= self.max_attempts else f"tried again after {self.retry_after_m:g} m"
        self.events.append(
            f"blacklisted {what} ({why}; attempt {attempts} of {self.max_attempts}, {again})"
        )
        if isinstance(key, _RegionKey):
            self.blacklisted_points_m.append(key.centroid_m)
            self._failed_views_m.append((key.centroid_m, target.position_m))
        else:
            self.blacklisted_links.add(key)  # type: ignore[arg-type]
        self._target = None


def _ending_at(waypoints: list[tuple[float, float]], target: tuple[float, float]) -> list[tuple[float, float]]:
    """The route with its last point replaced by the exact target (grid routes end on a cell centre)."""
    if waypoints and math.dist(waypoints[-1], target) < 0.05:
        return [*waypoints[:-1], target]
    return [*waypoints, target]


def _cells_of(
    xy_m: np.ndarray, shape: tuple[int, ...], origin_m: tuple[float, float], resolution_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The grid rows and columns of map points ``xy_m`` ((N, 2) x, y), those off the grid left out."""
    rows = np.floor((xy_m[:, 1] - origin_m[1]) / resolution_m).astype(np.int64)
    cols = np.floor((xy_m[:, 0] - origin_m[0]) / resolution_m).astype(np.int64)
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    return rows[inside], cols[inside]


def _known_free_at(
    grid: np.ndarray, origin_m: tuple[float, float], resolution_m: float, pose: tuple[float, float, float]
) -> bool:
    """True when the map holds the robot's position as known free space (3x3 cells around it)."""
    r = math.floor((pose[1] - origin_m[1]) / resolution_m)
    c = math.floor((pose[0] - origin_m[0]) / resolution_m)
    window = grid[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2]
    return bool(window.size) and bool((window == FREE).any())


def _heading_index(theta_rad: float, frame_angle_rad: float) -> int:
    """The maze direction (0 E, 1 N, 2 W, 3 S) closest to a map-frame heading."""
    return round(math.remainder(theta_rad - frame_angle_rad, math.tau) / (math.pi / 2)) % 4
