"""Passages the robot could not take: found on the local costmap, remembered for the global planner.

The cell graph says a link is open when the map sees no wall along it; the local planner then
needs a lane for the robot's body through it. A table leg or a cable beside a corner can leave
an open link with no lane: the robot's centre must keep the DWA's contact distance (footprint
plus safety margin) from every obstacle, and on a hand-built maze a leg 48 mm in from two post
lines leaves the body 2 mm to spare on the centre line. The DWA then finds no admissible arc,
recovers, gives up, and the global planner sends it the same way again.

When the local planner (or the stand-still watch) gives up, :func:`first_unreachable` asks the
local costmap the DWA used whether the path ahead has a lane at all: a flood fill over the
robot centres that keep the contact distance, from where the robot stands, in a window about
it. The lane is judged on the DWA's own costmap (the occupied map cells as discs of half their
diagonal), not on the exact surfaces: a lane the body fits but the local planner cannot drive
is no lane for this robot. Beside a table leg on a hand-built 8x8 maze the body would clear the
leg by 20.7 mm, but the DWA's map cells leave its centre 2.6 mm short of the contact distance:
a check on the exact surfaces would find a lane there and close nothing while the robot stands
beside it. A path point no such centre comes near marks a closed passage: the explorer then
remembers the passage (:class:`ClosedPassage`; the cell link crossed there in a maze, a short
segment across the path elsewhere) and plans round it. A path that still has a lane is a
passing trouble (a spurious map cell, a moment of bad luck in the DWA's samples) and nothing
is remembered: closing the way at every give-up made a detour of 33-42 s out of a passing
trouble on a hand-built 8x8 maze.

A closed passage is forgotten when the map there changes: when a quarter (at least two) of the
occupied cells that stood near it when it was closed are seen free (the map may have been wrong,
or the obstacle moved), and tried again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mazebot.planner.dwa import LocalCostmap
from mazebot.planner.maze_graph import Cell, Direction
from mazebot.slam.grid import FREE, OCCUPIED

#: The lane is searched in a square this far either side of the robot (metres): a cell and a third
#: of a 1 ft maze, enough to see past the next link, small enough for one give-up's CPU (~26 000 centres).
LANE_WINDOW_M = 0.4
#: The robot centres tried are this far apart (metres), 8-connected. The clearance changes by at most
#: the distance moved, so a lane is lost to the grid only where its centre line keeps less than
#: half a step's diagonal (3.5 mm) over the contact distance, and a lane found dips at most that far
#: below it between two centres. At 1 cm and 4-connected (7 mm, and a diagonal lane narrower than a
#: step's diagonal split in two) the check said "no lane" at a corner of a hand-built 8x8 maze whose
#: lane kept 4.1 mm over the contact distance on the DWA's own costmap, which drives through it.
LANE_STEP_M = 0.005
#: The path ahead is judged at points this far apart (metres).
PATH_STEP_M = 0.02
#: A path point counts as reached when a reachable centre lies within this of it (metres): the path
#: runs through cell centres, the robot may pass beside it (half the body's free play in a 1 ft corridor).
LANE_REACH_M = 0.05
#: Occupied map cells within this of a closed passage's point (metres) are what it was closed on: what
#: can touch a robot centre there (the DWA's contact distance, 0.1 m, and a lane's reach).
EVIDENCE_RADIUS_M = 0.15
#: Outside a maze, the blocked segment reaches this far either side of the path (metres): with the
#: robot's inflation it closes a 1 ft corridor.
SEGMENT_HALF_M = 0.05


def first_unreachable(
    costmap: LocalCostmap, path_robot: np.ndarray, contact_m: float, window_m: float = LANE_WINDOW_M
) -> int | None:
    """The index of the first point of ``path_robot`` (robot frame, (M, 2), in order along the path)
    that no lane reaches, or None when every point inside the window is reached.

    A lane is an 8-connected set of robot centres, ``LANE_STEP_M`` apart, each at least
    ``contact_m`` from every obstacle of ``costmap`` (the DWA's contact distance), starting at the
    centres within ``LANE_REACH_M`` of the robot. None of those: the robot is wedged, index 0.
    Points within ``LANE_REACH_M`` of the window's edge are not judged (a lane may leave it).
    """
    n = 2 * math.ceil(window_m / LANE_STEP_M) + 1
    axis = (np.arange(n) - n // 2) * LANE_STEP_M
    xx, yy = np.meshgrid(axis, axis)  # [row = y, col = x]
    clear = costmap.clearance_m(np.column_stack((xx.ravel(), yy.ravel())), upper_bound_m=contact_m + LANE_STEP_M)
    free = (clear >= contact_m).reshape(n, n)
    labels, _ = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))  # 8-connected: diagonal lanes too
    near_robot = np.hypot(xx, yy) <= LANE_REACH_M
    starts = np.unique(labels[near_robot & free])
    if starts.size == 0:
        return 0
    reached = np.isin(labels, starts)
    edge_m = window_m - LANE_REACH_M
    reach_cells = math.ceil(LANE_REACH_M / LANE_STEP_M)
    for k, (x, y) in enumerate(np.asarray(path_robot, dtype=np.float64).reshape(-1, 2)):
        if abs(x) > edge_m or abs(y) > edge_m:
            continue
        col, row = round(x / LANE_STEP_M) + n // 2, round(y / LANE_STEP_M) + n // 2
        r0, r1 = max(row - reach_cells, 0), min(row + reach_cells + 1, n)
        c0, c1 = max(col - reach_cells, 0), min(col + reach_cells + 1, n)
        near = np.hypot(xx[r0:r1, c0:c1] - x, yy[r0:r1, c0:c1] - y) <= LANE_REACH_M
        if not reached[r0:r1, c0:c1][near].any():
            return k
    return None


@dataclass(frozen=True)
class ClosedPassage:
    """A passage the robot could not take: where, which cell link (in a maze), and on what evidence.

    ``where_m`` the first path point no lane reached (map frame, metres); ``link`` the cell and
    side of the maze link crossed there (None outside a maze), for the log; ``cells_m`` the centres
    of the two cells that link joins (map frame), which name the link again after the maze frame is
    re-estimated (the cells' numbers may change, their places do not); ``segment_m`` the two ends of the
    segment the global grid planner treats as a wall (the link's boundary from post to post, or
    ``SEGMENT_HALF_M`` either side of the path); ``evidence_m`` the occupied map cells within
    ``EVIDENCE_RADIUS_M`` of ``where_m`` when it was closed ((K, 2), map frame).
    """

    where_m: tuple[float, float]
    link: tuple[Cell, Direction] | None
    cells_m: tuple[tuple[float, float], tuple[float, float]] | None
    segment_m: tuple[tuple[float, float], tuple[float, float]]
    evidence_m: np.ndarray

    def describe(self) -> str:
        where = f"({self.where_m[0]:.2f}, {self.where_m[1]:.2f})"
        if self.link is None:
            return f"the passage at {where}"
        cell, side = self.link
        return f"the passage {side.name} of cell {cell} at {where}"

    def map_changed(self, three_state: np.ndarray, origin_m: tuple[float, float], resolution_m: float) -> bool:
        """True when a quarter (at least two) of the occupied cells it was closed on are now seen free.

        Seen free, not merely unknown: a cell the lidar has not looked at again is no news.
        """
        k = self.evidence_m.shape[0]
        if k == 0:
            return False
        cols = np.floor((self.evidence_m[:, 0] - origin_m[0]) / resolution_m).astype(np.int64)
        rows = np.floor((self.evidence_m[:, 1] - origin_m[1]) / resolution_m).astype(np.int64)
        inside = (rows >= 0) & (rows < three_state.shape[0]) & (cols >= 0) & (cols < three_state.shape[1])
        freed = int(np.count_nonzero(three_state[rows[inside], cols[inside]] == FREE))
        return freed >= max(2, math.ceil(k / 4))


def occupied_near(
    three_state: np.ndarray, origin_m: tuple[float, float], resolution_m: float, xy_m: tuple[float, float],
    radius_m: float = EVIDENCE_RADIUS_M,
) -> np.ndarray:
    """Centres (K, 2, map frame, metres) of the occupied cells within ``radius_m`` of ``xy_m``."""
    r0 = max(math.floor((xy_m[1] - radius_m - origin_m[1]) / resolution_m), 0)
    r1 = min(math.floor((xy_m[1] + radius_m - origin_m[1]) / resolution_m) + 1, three_state.shape[0])
    c0 = max(math.floor((xy_m[0] - radius_m - origin_m[0]) / resolution_m), 0)
    c1 = min(math.floor((xy_m[0] + radius_m - origin_m[0]) / resolution_m) + 1, three_state.shape[1])
    if r0 >= r1 or c0 >= c1:
        return np.zeros((0, 2))
    rows, cols = np.nonzero(three_state[r0:r1, c0:c1] == OCCUPIED)
    x_m = (cols + c0 + 0.5) * resolution_m + origin_m[0]
    y_m = (rows + r0 + 0.5) * resolution_m + origin_m[1]
    xy = np.column_stack((x_m, y_m))
    return xy[np.hypot(xy[:, 0] - xy_m[0], xy[:, 1] - xy_m[1]) <= radius_m]


def across_path_m(
    path_m: np.ndarray, k: int, half_m: float = SEGMENT_HALF_M
) -> tuple[tuple[float, float], tuple[float, float]]:
    """A segment across the path at its point ``k`` ((M, 2) map frame), ``half_m`` either side."""
    pts = np.asarray(path_m, dtype=np.float64).reshape(-1, 2)
    a, b = pts[max(k - 1, 0)], pts[min(k + 1, len(pts) - 1)]
    dx, dy = float(b[0] - a[0]), float(b[1] - a[1])
    norm = math.hypot(dx, dy) or 1.0
    nx, ny = -dy / norm * half_m, dx / norm * half_m
    x, y = float(pts[k, 0]), float(pts[k, 1])
    return ((x - nx, y - ny), (x + nx, y + ny))


def rasterise_segments(
    segments_m: list[tuple[tuple[float, float], tuple[float, float]]],
    shape: tuple[int, int],
    origin_m: tuple[float, float],
    resolution_m: float,
) -> np.ndarray:
    """A (rows, cols) mask of the grid cells the segments pass through (sampled every half cell)."""
    mask = np.zeros(shape, dtype=bool)
    for (ax, ay), (bx, by) in segments_m:
        n = max(2, math.ceil(math.hypot(bx - ax, by - ay) / (0.5 * resolution_m)) + 1)
        t = np.linspace(0.0, 1.0, n)
        cols = np.floor((ax + t * (bx - ax) - origin_m[0]) / resolution_m).astype(np.int64)
        rows = np.floor((ay + t * (by - ay) - origin_m[1]) / resolution_m).astype(np.int64)
        inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
        mask[rows[inside], cols[inside]] = True
    return mask
