"""Accuracy of one run against the simulator's ground truth: poses, map, revisits, loop closures.

Plain functions of a run's record (no daemon, no simulator object beyond the world and its
cell layout), shared by :mod:`mazebot.bench.runner`, :mod:`mazebot.bench.fault_metrics` and
:mod:`mazebot.bench.quota_run`. The metrics are defined in :mod:`mazebot.bench.runner`'s docstring.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mazebot.geometry import relative_pose

#: A loop closure this far from the true relative pose is counted as false (a maze cell is 0.3 m).
FALSE_CLOSURE_M = 0.1
FALSE_CLOSURE_RAD = 0.1
#: Cells of the map metrics' truth raster beyond the world's bounds on every side.
MARGIN_CELLS = 2


def relative_poses(base: tuple[float, float, float], poses: np.ndarray) -> np.ndarray:
    """Poses expressed in the frame of ``base`` (the robot's start: the map frame)."""
    return relative_pose(np.asarray(base, dtype=np.float64), poses)


#: How far (metres) the robot must be inside a cell before :func:`count_revisits` counts an entry.
REVISIT_DEPTH_M = 0.03


def count_revisits(layout: Any, xy: np.ndarray, depth_m: float = REVISIT_DEPTH_M) -> int:
    """Cell entries beyond the first visit of each cell, from the true trajectory.

    An entry counts once the robot's centre is more than ``depth_m`` inside the new cell
    (hysteresis): a robot following a corridor's centre line sways a centimetre or two,
    and where it passes close to a cell border (turning a corner, braking at a cell
    centre) every sway across the border would otherwise count as leaving and
    re-entering a cell, which is no back-tracking at all.
    """
    seen: set[tuple[int, int]] = set()
    last = None
    count = 0
    half_m = 0.5 * layout.cell_size_m
    for x, y in xy:
        cell = layout.cell_at(float(x), float(y))
        if cell is None or cell == last:
            continue
        cx, cy = layout.cell_center_m(cell)
        if half_m - max(abs(float(x) - cx), abs(float(y) - cy)) <= depth_m:
            continue  # at the border: not in the new cell yet
        if cell in seen:
            count += 1
        seen.add(cell)
        last = cell
    return count


def turn_about_start(est_xy: np.ndarray, true_xy: np.ndarray) -> tuple[float, float] | None:
    """The turn (radians) about the start that best carries the true positions onto the estimated
    ones, and the RMS position error (metres) left once the estimate is turned back by it.

    Both trajectories are in the map frame, whose origin is the start. The least-squares rotation
    about that origin in closed form: the orthogonal Procrustes problem in the plane (Umeyama, "Least-
    squares estimation of transformation parameters between two point patterns", IEEE PAMI 1991,
    without translation or scale), ``atan2(Σ t × e, Σ t · e)``. A map turned about the start as a
    whole shows a turn and a small RMS left; errors of its own, an RMS near the ATE's. None without
    positions. (:func:`mazebot.slam.trajectory_metrics.rigid_alignment` fits a shift too, for logs
    whose frames share no origin; here both start at the start, and the turn about it is the question.)
    """
    est = np.asarray(est_xy, dtype=np.float64).reshape(-1, 2)
    true = np.asarray(true_xy, dtype=np.float64).reshape(-1, 2)
    if est.shape[0] == 0 or est.shape != true.shape:
        return None
    dot = float(np.sum(true[:, 0] * est[:, 0] + true[:, 1] * est[:, 1]))
    cross = float(np.sum(true[:, 0] * est[:, 1] - true[:, 1] * est[:, 0]))
    turn = math.atan2(cross, dot) if dot or cross else 0.0
    c, s = math.cos(turn), math.sin(turn)
    turned = np.column_stack((c * true[:, 0] - s * true[:, 1], s * true[:, 0] + c * true[:, 1]))
    return turn, float(np.sqrt(np.mean(np.sum((est - turned) ** 2, axis=1))))


def map_to_world(start: tuple[float, float, float], xy: np.ndarray) -> np.ndarray:
    """Map-frame points (N, 2) in the world frame, the map frame being the start pose."""
    c, s = math.cos(start[2]), math.sin(start[2])
    return np.column_stack((start[0] + c * xy[:, 0] - s * xy[:, 1], start[1] + s * xy[:, 0] + c * xy[:, 1]))


def map_metrics(grid: Any, world: Any, start: tuple[float, float, float], footprint_radius_m: float) -> dict[str, Any]:
    """``coverage`` and ``map_f1`` (with precision and recall) of SLAM's grid against the world.

    Beside ``coverage`` (the share of the reachable cell centres the map knows free), where the rest
    falls: ``uncovered_occupied`` on cells the map holds occupied (walls painted thick, or the map turned
    or shifted so that the free space beside a wall lands on it), ``uncovered_unknown`` on cells it
    holds neither free nor occupied, or off the map (never seen). The three add up to 1.
    """
    from scipy import ndimage

    from mazebot.sim.raster import free_reachable, true_occupancy

    if grid is None or grid.shape[0] == 0:
        return {"coverage": None, "uncovered_occupied": None, "uncovered_unknown": None,
                "map_f1": None, "map_precision": None, "map_recall": None}
    res = grid.resolution_m
    # the truth raster reaches MARGIN_CELLS beyond the world's bounds: a map cell on the outer
    # wall whose centre lies just outside them is within the one-cell tolerance, not off the grid
    bounds, bounds_origin = true_occupancy(world, res)
    bounds_shape = bounds.shape
    origin = (bounds_origin[0] - MARGIN_CELLS * res, bounds_origin[1] - MARGIN_CELLS * res)
    shape = (bounds_shape[0] + 2 * MARGIN_CELLS, bounds_shape[1] + 2 * MARGIN_CELLS)
    truth, origin = true_occupancy(world, res, origin, shape)
    reach, _ = free_reachable(world, res, footprint_radius_m, origin, truth.shape)
    rows, cols = truth.shape
    # coverage: look every reachable cell centre up in the map
    rr, cc = np.nonzero(reach)
    centres = np.column_stack((origin[0] + (cc + 0.5) * res, origin[1] + (rr + 0.5) * res))
    c, s = math.cos(start[2]), math.sin(start[2])
    dx, dy = centres[:, 0] - start[0], centres[:, 1] - start[1]
    in_map = np.column_stack((c * dx + s * dy, -s * dx + c * dy))
    mr, mc = grid.to_cell(in_map)
    inside = (mr >= 0) & (mr < grid.shape[0]) & (mc >= 0) & (mc < grid.shape[1])
    free = grid.known_free_mask()
    known = np.zeros(len(mr), dtype=bool)
    known[inside] = free[mr[inside], mc[inside]]
    coverage = float(known.sum() / max(1, len(known)))
    # what the rest falls on: cells the map holds occupied (a wall painted there, or the map turned or
    # shifted onto the free space beside a wall), or cells it has no word for (never seen, or off the map)
    walls = grid.occupied_mask()
    on_walls = np.zeros(len(mr), dtype=bool)
    on_walls[inside] = walls[mr[inside], mc[inside]]
    uncovered_occupied = float(on_walls.sum() / max(1, len(on_walls)))
    # walls: the map's occupied cells rasterized into the world grid
    er, ec = np.nonzero(walls)
    est_xy = map_to_world(start, grid.to_world(er, ec))
    wc = np.floor((est_xy[:, 0] - origin[0]) / res).astype(int)
    wr = np.floor((est_xy[:, 1] - origin[1]) / res).astype(int)
    on = (wr >= 0) & (wr < rows) & (wc >= 0) & (wc < cols)
    est = np.zeros_like(truth)
    est[wr[on], wc[on]] = True
    near = ndimage.generate_binary_structure(2, 2)  # one cell, diagonals included
    truth_near = ndimage.binary_dilation(truth, near)
    precision = float(truth_near[wr[on], wc[on]].sum() / max(1, len(er)))  # off-grid cells are false
    visible = truth & ndimage.binary_dilation(reach, near, iterations=2)
    recall = float((visible & ndimage.binary_dilation(est, near)).sum() / max(1, visible.sum()))
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "coverage": round(coverage, 4),
        "uncovered_occupied": round(uncovered_occupied, 4),
        "uncovered_unknown": round(max(0.0, 1.0 - coverage - uncovered_occupied), 4),
        "map_f1": round(f1, 4),
        "map_precision": round(precision, 4),
        "map_recall": round(recall, 4),
    }


def false_closures(closures: list, trajectory: list[tuple[float, float, float, float]]) -> int:
    """Accepted loop closures whose relative pose disagrees with the true trajectory."""
    if not closures or len(trajectory) < 2:
        return 0
    traj = np.asarray(trajectory, dtype=float)
    t, th = traj[:, 0], np.unwrap(traj[:, 3])

    def true_pose(time_s: float) -> np.ndarray:
        return np.array([np.interp(time_s, t, traj[:, 1]), np.interp(time_s, t, traj[:, 2]), np.interp(time_s, t, th)])

    count = 0
    for old_s, new_s, z in closures:
        a, b = true_pose(old_s), true_pose(new_s)
        c, s = math.cos(a[2]), math.sin(a[2])
        d = b[:2] - a[:2]
        rel = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], math.remainder(b[2] - a[2], math.tau)])
        err_t = math.hypot(rel[0] - z[0], rel[1] - z[1])
        err_r = abs(math.remainder(rel[2] - z[2], math.tau))
        count += err_t > FALSE_CLOSURE_M or err_r > FALSE_CLOSURE_RAD
    return count
