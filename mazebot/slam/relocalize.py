"""Noticing that the robot is lost, and finding it again in the map it has built.

A robot that is picked up and put down elsewhere (kidnapped), or whose wheel slipped
badly, or that was blind for a while, has an odometry that no longer says where it is.
SLAM would then match each new revolution from the wrong guess and, worse, paint it
into the map at the wrong place: the map would be spoiled for good. So before SLAM
sees a revolution, :class:`LocalizationGuard` checks it against the map at the pose the
odometry predicts:

- **fit**: each hit is looked up in the grid (de-skewed with the odometry at its own
  sample time). A hit deep inside space the map knows to be free (every cell within
  ``free_margin_cells`` free) contradicts the map; a hit next to a wall agrees. The
  contradiction ratio is ``contradicting / known`` (hits in unknown space say nothing,
  so exploring new corridors does not look like being lost). A cell the map once held
  occupied never contradicts, however free it is now: a board marked from close by and
  then worn free by far beams grazing it (:mod:`mazebot.slam.grid`) is still a board,
  while a kidnapped robot's hits fall on corridor cells that were never walls. Nor does a
  hit on a surface SLAM's local submap holds (a point of it within the same margin): the
  grid marks only hits within ``[slam.map] map_max_range_m`` and lets farther ones clear
  space, so a board seen only from beyond it, at a grazing angle, is free in the grid,
  never marked, though the keyframes hold its points (hits up to ``[slam.prepare] max_range_m``);
  the robot's first near hits on it are right, and a kidnapped robot's hits, deep in a
  corridor, are near no surface.
- **lost**: ``lost_after`` revolutions in a row contradicting the map more than
  ``max_contradiction`` mean the robot does not know where it is. Those revolutions
  never reach SLAM (the map stays as it was), the daemon raises a ``localization``
  fault (the wheels stop) and a search starts. A revolution between
  ``suspect_contradiction`` and ``max_contradiction`` goes to SLAM and counts towards
  the streak without ending it (the robot may have been picked up late in it).
- **search** (:func:`search_pose`), widened after each one that found nothing:
  correlative scan matching (Olson, "Real-time correlative scan matching", ICRA
  2009): every pose of a grid around the predicted
  one (±``search_xy_m``, ±``search_theta_rad``) is scored by how close the hits fall
  to the map's walls (a Gaussian of the distance to the nearest occupied cell), in one
  vectorised pass per heading; the best few are refined with ICP against the keyframes
  nearby, and among the acceptable matches the one with most hits on the walls wins,
  as in re-localizing a resumed run (:mod:`mazebot.persist.resume`). A found pose that
  also fits the map (low contradiction) becomes SLAM's pose (:meth:`Slam.relocalized`),
  the fault clears and the run goes on in the same map.
- **the known part**: an exploring robot faces the frontier, so put down a little further
  it sees about half its view where the map knows nothing, and no pose puts 60 % of the
  hits on known ground. The search's second pass matches each candidate on the hits the
  map knows there, with stricter limits (many known hits, nearly all on walls, hardly any
  contradicting, the pose fixed in every direction), and such a pose is only taken when
  the next revolution's search finds it again.
- **ambiguity**: a view that fits another pose of the window nearly as well (a corridor
  whose ends are out of sight, repeated cells) is not taken at all: staying lost only
  waits, a wrong pose spoils the map for good. While lost, every revolution is searched.

The guard also notes revolutions where ICP had to move the odometry's prediction far
(a wheel slipping): the robot still knows where it is, but the user should know why.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from mazebot.geometry import compose, inverse, transform_points, wrap_angle
from mazebot.io.scan import Scan
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.icp import IcpResult, Target, match_scan
from mazebot.slam.keyframes import build_target
from mazebot.slam.preprocess import PreparedScan
from mazebot.slam.slam import OdometrySource, Slam, odometry_pose_at

log = logging.getLogger(__name__)

#: Widest search, as a multiple of the first one's window (after searches that found nothing).
MAX_SEARCH_SCALE = 3.0


@dataclass(frozen=True)
class GuardParams:
    """Thresholds of the lost-robot check and the search (units in the names)."""

    min_keyframes: int = 3  # before that the map is too young to contradict anything
    min_known_hits: int = 30  # hits in known cells needed for a verdict
    free_margin_cells: int = 2  # a hit contradicts only this deep inside known free space
    # share of known hits in free space above which a revolution does not fit. Healthy revolutions
    # reach 0.006 in the simulated mazes; the one the robot is picked up in (part of it at each pose)
    # 0.16-0.24: at 0.25 it went to SLAM and the robot was said lost one revolution later (550 ms)
    max_contradiction: float = 0.10
    lost_after: int = 2  # revolutions in a row that do not fit
    # a revolution the robot was picked up in late shows the new place in its last samples only:
    # 0.097 with the last 58 % of it seen there (a 6x6 maze), so it fitted, and the robot was said
    # lost two whole revolutions later (550 ms). Above this, on the whole revolution or on its
    # later half alone (:func:`_later_half`), it starts the streak (goes to SLAM all the same): the
    # next that does not fit ends it. Healthy revolutions: 0.000 in every one of 1288 of a 6x6 run
    # and two hand-built 6x6 runs of the cheap robot
    suspect_contradiction: float = 0.05
    stride: int = 2  # every n-th sample is checked (a cheap check: ~180 lookups)
    search_xy_m: float = 0.32
    search_step_m: float = 0.04
    search_theta_rad: float = 0.7
    search_theta_step_rad: float = 0.035
    wall_sigma_m: float = 0.04  # spread of the wall likelihood (half the xy step of the grid, and then some)
    refine: int = 6  # best grid poses refined with ICP
    # a found pose may contradict the map this much at most: below max_contradiction, or the guard
    # calls the next revolution lost again (at 0.125 a kidnap run took a pose one cell off at 0.11,
    # was lost again 0.4 s later and took it again). Not much below: right poses were found at
    # 0.068-0.071 (one corner of the map free where there is wall; at 0.05 that robot stayed lost)
    found_max_contradiction: float = 0.09
    min_known_share: float = 0.6  # a found pose must put this share of the hits where the map knows
    # another pose with this share of the found one's hits on walls, contradicting the map hardly more
    # (the ratio, plus this): the view is ambiguous
    runner_up_share: float = 0.9
    runner_up_contradiction: float = 0.01
    # A robot put down at the edge of what it has mapped (an exploring robot faces the frontier)
    # sees half its view in unknown space: no pose meets min_known_share. Such a view is matched
    # on its known part alone (ICP on the hits the map knows at the candidate pose), and a pose it
    # gives must be much stricter: the known part large, on the walls, not contradicting, fixing
    # the pose in every direction, clearly better than any other pose, and found again from the
    # next revolution (see :meth:`LocalizationGuard.accept`).
    partial_min_known_hits: int = 80  # hits (of ~330 in a revolution) the map knows at the pose
    partial_min_known_share: float = 0.25
    partial_min_fitness: float = 0.8  # ICP inlier ratio of the known hits
    partial_min_wall_share: float = 0.9  # known hits next to a wall
    partial_max_contradiction: float = 0.03
    confirm_m: float = 0.03  # two revolutions' partial finds agree this well (the robot stands still)
    confirm_rad: float = math.radians(2.0)
    submap_radius_m: float = 1.2  # keyframes this close to the guess form the ICP target
    # ICP moved the odometry's prediction this far in one revolution, or turned it this much in
    # the last ``slip_scans`` together: a wheel slipped. On the simulated robot with 1 % slip the
    # largest were 3.3 mm and 0.43° per revolution (0.56° over three) in 106 revolutions.
    slip_m: float = 0.015
    slip_rad: float = math.radians(1.5)
    slip_scans: int = 3
    slip_sum_rad: float = math.radians(2.0)


@dataclass(frozen=True)
class ScanFit:
    """How one revolution at one pose agrees with the map."""

    known: int  # hits in known cells
    contradicting: int  # hits deep in known free space
    on_walls: int  # hits within one cell of an occupied cell

    @property
    def contradiction(self) -> float:
        return self.contradicting / max(1, self.known)

    @classmethod
    def count(cls, known: np.ndarray, contradicting: np.ndarray, on_walls: np.ndarray) -> ScanFit:
        """The fit of the hits :func:`hit_classes` classified (its three boolean arrays, or a part of each)."""
        return cls(int(known.sum()), int(contradicting.sum()), int(on_walls.sum()))


@dataclass(frozen=True)
class SearchResult:
    """What a search found: the map pose at the revolution's end, or None."""

    pose: np.ndarray | None
    odom: np.ndarray  # odometry pose at the revolution's end
    fit: ScanFit | None
    match: IcpResult | None
    tried: int
    guess: np.ndarray
    partial: bool = False  # found from the known part of the view only: to be confirmed by the next revolution


def scan_fit(
    grid: OccupancyGrid, hits_map: np.ndarray, free_margin_cells: int = 2, surfaces: Target | None = None
) -> ScanFit:
    """Look hits (N, 2, map frame) up in the grid (and ``surfaces``, see :func:`hit_classes`): see :class:`ScanFit`."""
    _, known, contradicting, on_walls = _classify(grid, hits_map, free_margin_cells, surfaces)
    return ScanFit.count(known, contradicting, on_walls)


def hit_classes(
    grid: OccupancyGrid, hits_map: np.ndarray, free_margin_cells: int = 2, surfaces: Target | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per hit (N, 2, map frame): (in known space, contradicting the map, on a wall), boolean (N,) each.

    Hits within ``free_margin_cells`` of the grid's edge are in none of the three. With
    ``surfaces`` (SLAM's local submap), a hit within the margin of one of its points does
    not contradict the map either (:func:`_off_surfaces`).
    """
    inside, known_in, contradicting_in, on_walls_in = _classify(grid, hits_map, free_margin_cells, surfaces)
    out = []
    for values in (known_in, contradicting_in, on_walls_in):
        full = np.zeros(inside.shape[0], dtype=bool)
        full[inside] = values
        out.append(full)
    return out[0], out[1], out[2]


def _classify(
    grid: OccupancyGrid, hits_map: np.ndarray, free_margin_cells: int, surfaces: Target | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(inside the grid's margin (N,), then known, contradicting, on a wall for the hits inside)."""
    hits_map = np.asarray(hits_map, dtype=np.float64).reshape(-1, 2)
    rows, cols = grid.to_cell(hits_map)
    shape = grid.shape
    lo = grid.log_odds
    m = free_margin_cells
    inside = (rows >= m) & (rows < shape[0] - m) & (cols >= m) & (cols < shape[1] - m)
    rows, cols = rows[inside], cols[inside]
    if rows.size == 0:
        empty = np.zeros(0, dtype=bool)
        return inside, empty, empty, empty
    dr, dc = _offsets(m)
    around = lo[rows[:, None] + dr, cols[:, None] + dc]  # (N, (2m+1)²): each hit's neighbourhood, one gather
    here = around[:, dr.size // 2]
    # free now and never a wall: a board worn free by far beams grazing it is still where the robot
    # saw it (:attr:`OccupancyGrid.ever_occupied`); a kidnapped robot's hits fall on corridor cells
    ever = grid.ever_occupied[rows[:, None] + dr, cols[:, None] + dc]
    free_all = ((around < grid.free_logodds) & ~ever).all(axis=1)
    near = (np.abs(dr) <= 1) & (np.abs(dc) <= 1)
    wall_near = (around[:, near] > grid.occupied_logodds).any(axis=1)
    known = (here < grid.free_logodds) | (here > grid.occupied_logodds) | wall_near
    contradicting = free_all & known
    if surfaces is not None and contradicting.any():
        margin_m = m * grid.resolution_m
        contradicting[contradicting] = _off_surfaces(surfaces, hits_map[inside][contradicting], margin_m)
    return inside, known, contradicting, wall_near


def _off_surfaces(surfaces: Target, hits_map: np.ndarray, margin_m: float) -> np.ndarray:
    """Per hit (N, 2, map frame): no point of ``surfaces`` lies within ``margin_m`` of it.

    The grid marks a wall only from hits within ``[slam.map] map_max_range_m`` (1.2 m); a
    farther hit becomes a ray that clears space and ends short of the wall by three times
    the range noise along its beam (:func:`mazebot.slam.keyframes.map_rays`). At a grazing
    angle that margin is mostly along the board, hardly across it, so the rays clear the
    board's own cells: a board seen only from far (a corridor's side wall, seen from its
    other end) is free in the grid and was never marked, while the keyframes hold its
    points. The robot's first near hits on it then fall "in free space" though SLAM's pose
    is right (a contest maze: 26 of 143 known hits, the robot within 5 mm of the truth,
    24 of them within 27 mm of a submap point). Only the few hits the grid calls
    contradicting are looked up, in the submap's own kd-tree.
    """
    if len(surfaces) == 0 or hits_map.shape[0] == 0:
        return np.ones(hits_map.shape[0], dtype=bool)
    dist_m, _ = surfaces.tree.query(hits_map, distance_upper_bound=margin_m)
    return np.asarray(~np.isfinite(dist_m), dtype=bool)


def _offsets(margin: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column offsets of the (2m+1)² cells around a cell, the cell itself in the middle."""
    dr, dc = np.meshgrid(np.arange(-margin, margin + 1), np.arange(-margin, margin + 1), indexing="ij")
    return dr.reshape(-1), dc.reshape(-1)


def hits_in_map(
    scan: Scan,
    map_from_odom: np.ndarray,
    odometry: OdometrySource,
    *,
    time_offset_s: float = 0.0,
    mount_xy_m: tuple[float, float] = (0.0, 0.0),
    stride: int = 1,
) -> np.ndarray:
    """The revolution's valid hits (N, 2) in the map frame, each from the odometry pose at its own time."""
    index = np.flatnonzero(scan.valid)[::stride]
    if index.size == 0:
        return np.zeros((0, 2))
    x, y, th = odometry.at(scan.time_s[index] - time_offset_s)
    poses = compose(np.asarray(map_from_odom, dtype=np.float64), np.column_stack((x, y, th)))
    px, py, pth = poses[:, 0], poses[:, 1], poses[:, 2]
    r, a = scan.range_m[index], scan.angle_rad[index]
    lx, ly = mount_xy_m[0] + r * np.cos(a), mount_xy_m[1] + r * np.sin(a)
    c, s = np.cos(pth), np.sin(pth)
    return np.column_stack((px + c * lx - s * ly, py + s * lx + c * ly))


def wall_likelihood(grid: OccupancyGrid, sigma_m: float) -> np.ndarray:
    """exp(-d² / 2σ²) of the distance d to the nearest occupied cell, per cell (Olson 2009)."""
    occupied = grid.occupied_mask()
    if not occupied.any():
        return np.zeros(grid.shape, dtype=np.float32)
    dist_m = ndimage.distance_transform_edt(~occupied) * grid.resolution_m
    return np.exp(-0.5 * (dist_m / sigma_m) ** 2).astype(np.float32)


def correlative_candidates(
    likelihood: np.ndarray,
    grid: OccupancyGrid,
    points_robot: np.ndarray,
    guess: np.ndarray,
    params: GuardParams,
) -> list[tuple[float, np.ndarray]]:
    """The best ``params.refine`` poses of the search grid around ``guess``, (score, pose), best first.

    The xy steps are whole cells, so for each heading the hits are rotated and put in
    cells once, and every translation is an index shift of the same cells.
    """
    res = grid.resolution_m
    step_cells = max(1, round(params.search_step_m / res))
    n = int(params.search_xy_m / (step_cells * res))
    shifts = np.arange(-n, n + 1) * step_cells  # cells
    thetas = np.arange(-params.search_theta_rad, params.search_theta_rad + 1e-9, params.search_theta_step_rad)
    rows_max, cols_max = likelihood.shape
    scored: list[tuple[float, float, int, int]] = []
    for dth in thetas:
        theta = guess[2] + dth
        c, s = math.cos(theta), math.sin(theta)
        xy = np.column_stack((guess[0] + c * points_robot[:, 0] - s * points_robot[:, 1],
                              guess[1] + s * points_robot[:, 0] + c * points_robot[:, 1]))
        rows, cols = grid.to_cell(xy)
        r = rows[None, None, :] + shifts[:, None, None]  # (dy, 1, N)
        q = cols[None, None, :] + shifts[None, :, None]  # (1, dx, N)
        r, q = np.broadcast_arrays(r, q)
        ok = (r >= 0) & (r < rows_max) & (q >= 0) & (q < cols_max)
        values = np.where(ok, likelihood[np.clip(r, 0, rows_max - 1), np.clip(q, 0, cols_max - 1)], 0.0)
        score = values.mean(axis=2)  # (dy, dx)
        flat = np.argsort(score, axis=None)[::-1][: params.refine]
        for k in flat.tolist():
            iy, ix = divmod(k, score.shape[1])
            scored.append((float(score[iy, ix]), float(dth), int(shifts[ix]), int(shifts[iy])))
    scored.sort(key=lambda t: -t[0])
    out: list[tuple[float, np.ndarray]] = []
    for value, dth, sx, sy in scored:
        pose = np.array([guess[0] + sx * res, guess[1] + sy * res, wrap_angle(guess[2] + dth)])
        # distinct candidates: not within two steps and 0.1 rad of one already kept
        if any(math.hypot(*(pose[:2] - p[:2])) < 2 * params.search_step_m
               and abs(wrap_angle(pose[2] - p[2])) < 0.1 for _, p in out):
            continue
        out.append((value, pose))
        if len(out) >= params.refine:
            break
    return out


def search_pose(
    slam: Slam,
    scan: Scan,
    odometry: OdometrySource,
    guess: np.ndarray,
    params: GuardParams,
    scale: float = 1.0,
) -> SearchResult:
    """Find the revolution in ``slam``'s map near ``guess`` (see the module docstring).

    ``scale`` widens the searched window (and coarsens its steps and the wall likelihood
    alike, so a search costs the same): the guard widens it after each search that found
    nothing, up to :data:`MAX_SEARCH_SCALE`. Reads the Slam (grid, keyframes) without
    changing it: run it while SLAM is held.
    """
    if scale != 1.0:
        params = replace(
            params,
            search_xy_m=params.search_xy_m * scale,
            search_step_m=params.search_step_m * scale,
            search_theta_rad=min(math.pi, params.search_theta_rad * scale),
            search_theta_step_rad=params.search_theta_step_rad * scale,
            wall_sigma_m=params.wall_sigma_m * scale,
            refine=round(params.refine * scale),
        )
    p = slam.params
    prepared, odom = slam.prepare(scan, odometry)
    guess = np.asarray(guess, dtype=np.float64)
    if prepared.points_full.shape[0] < params.min_known_hits or not slam.keyframes:
        return SearchResult(None, odom, None, None, 0, guess)
    likelihood = wall_likelihood(slam.grid, params.wall_sigma_m)
    candidates = correlative_candidates(likelihood, slam.grid, prepared.points_full, guess, params)
    poses = slam.keyframe_poses()
    dist = np.hypot(poses[:, 0] - guess[0], poses[:, 1] - guess[1])
    near = np.flatnonzero(dist <= params.submap_radius_m + params.search_xy_m)
    near = near[np.argsort(dist[near], kind="stable")[: max(p.submap_keyframes, 40)]]
    if near.size == 0:
        return SearchResult(None, odom, None, None, 0, guess)
    target = build_target([slam.keyframes[k] for k in sorted(near.tolist())], p.submap_voxel_m)
    if target is None:  # the keyframes nearby hold no points to match
        return SearchResult(None, odom, None, None, 0, guess)
    whole = _search_whole_view(slam, target, prepared, candidates, guess, params)
    if whole is not None:
        match, fit = whole
        return SearchResult(match.pose.copy(), odom, fit, match, len(candidates), guess)
    partial = _search_known_part(slam, target, prepared, candidates, guess, params)
    if partial is None:
        return SearchResult(None, odom, None, None, len(candidates), guess)
    match, fit = partial
    return SearchResult(match.pose.copy(), odom, fit, match, len(candidates), guess, partial=True)


def _search_whole_view(
    slam: Slam,
    target: Target,
    prepared: PreparedScan,
    candidates: list[tuple[float, np.ndarray]],
    guess: np.ndarray,
    params: GuardParams,
) -> tuple[IcpResult, ScanFit] | None:
    """The search's first pass: each candidate refined by ICP on the whole view; (match, fit) of the best, or None.

    A pose is kept if SLAM would accept the match, the hits do not contradict the map and
    most fall where the map knows; the one with most hits on the walls wins, unless another
    one fits nearly as well (:func:`_ambiguous`).
    """
    p = slam.params
    hits = prepared.points_full.shape[0]
    best: tuple[float, IcpResult, ScanFit] | None = None
    rivals: list[tuple[ScanFit, np.ndarray]] = []
    for _, start in candidates:
        match = match_scan(target, prepared.points_match, start, p.icp, sensor_xy=prepared.sensor_xy)
        if not match.converged or not _in_window(match.pose, guess, params):
            continue  # ICP slid out of the searched window: not what was searched for
        fit = scan_fit(slam.grid, transform_points(match.pose, prepared.points_full), params.free_margin_cells)
        if fit.contradiction > params.found_max_contradiction:
            continue  # contradicts the map
        rivals.append((fit, match.pose))
        if not slam.acceptable(match) or fit.known < params.min_known_share * hits:
            continue  # a poor match, or mostly falls where the map cannot confirm it
        score = fit.on_walls / max(1, hits)
        if best is None or score > best[0] + 1e-9 or (abs(score - best[0]) <= 1e-9 and match.rmse_m < best[1].rmse_m):
            best = (score, match, fit)
    if best is None or _ambiguous(best[1].pose, best[2], rivals, params):
        return None
    return best[1], best[2]


def _ambiguous(pose: np.ndarray, fit: ScanFit, rivals: list[tuple[ScanFit, np.ndarray]], params: GuardParams) -> bool:
    """Another pose, not the same, fits the map nearly as well: the view does not say which.

    Nearly as well: nearly as many hits on the walls, hardly more contradicting the map. A
    corridor seen without its ends, or a maze's repeated cells, fit several poses of the
    window; taking one of them would spoil the map for good, staying lost only waits.
    """
    for other_fit, other in rivals:
        if (_same_pose(other, pose, params) or other_fit.on_walls < params.runner_up_share * fit.on_walls
                or other_fit.contradiction > fit.contradiction + params.runner_up_contradiction):
            continue
        log.info("the view fits the map at (%.3f m, %.3f m, %.1f°) and nearly as well %.3f m / %.1f° from there: "
                 "ambiguous, not taken", pose[0], pose[1], math.degrees(pose[2]),
                 math.hypot(*(other[:2] - pose[:2])), math.degrees(wrap_angle(other[2] - pose[2])))
        return True
    return False


def _in_window(pose: np.ndarray, guess: np.ndarray, params: GuardParams) -> bool:
    """The pose lies in the searched window (with a margin for ICP's last steps)."""
    offset = pose - guess
    return bool(math.hypot(offset[0], offset[1]) <= params.search_xy_m + 0.05
                and abs(wrap_angle(offset[2])) <= params.search_theta_rad + 0.1)


def _search_known_part(
    slam: Slam,
    target: Target,
    prepared: PreparedScan,
    candidates: list[tuple[float, np.ndarray]],
    guess: np.ndarray,
    params: GuardParams,
) -> tuple[IcpResult, ScanFit] | None:
    """The search's second pass, for a view half in unknown space: (match, fit) of the one clear pose, or None.

    Each candidate is refined by ICP on the hits the map knows at the candidate (the rest
    say nothing about where the robot is, and would only lower the inlier ratio). A pose
    is kept if its known hits are many, fit the keyframes (inlier ratio, residual), lie on
    the walls and do not contradict the map, and if they fix the pose in every direction
    (a corridor seen alone slides along itself). The pose with most hits on the walls wins,
    unless another one, not the same, fits nearly as well: then the view is ambiguous and
    nothing is found (better lost than wrong: a wrong pose would spoil the map for good).
    """
    p = slam.params
    hits = prepared.points_full.shape[0]
    kept: list[tuple[int, IcpResult, ScanFit]] = []
    rivals: list[tuple[ScanFit, np.ndarray]] = []  # every plausible pose, for the ambiguity test
    for _, start in candidates:
        known, _, _ = hit_classes(slam.grid, transform_points(start, prepared.points_match), params.free_margin_cells)
        if int(known.sum()) < p.icp.min_correspondences:
            continue
        match = match_scan(target, prepared.points_match[known], start, p.icp, sensor_xy=prepared.sensor_xy)
        if not match.converged or not _in_window(match.pose, guess, params):
            continue
        fit = scan_fit(slam.grid, transform_points(match.pose, prepared.points_full), params.free_margin_cells)
        if fit.contradiction <= params.found_max_contradiction:
            rivals.append((fit, match.pose))
        if (match.degenerate or match.fitness < params.partial_min_fitness or match.rmse_m > p.max_match_rmse_m
                or fit.contradiction > params.partial_max_contradiction
                or fit.known < max(params.partial_min_known_hits, params.partial_min_known_share * hits)
                or fit.on_walls < params.partial_min_wall_share * fit.known):
            continue
        kept.append((fit.on_walls, match, fit))
    if not kept:
        return None
    _, match, fit = max(kept, key=lambda k: (k[0], -k[1].rmse_m))
    if _ambiguous(match.pose, fit, rivals, params):
        return None
    return match, fit


def _later_half(scan: Scan, stride: int) -> np.ndarray:
    """Which of the hits :func:`hits_in_map` gives (valid samples, every ``stride``-th) were taken in the
    revolution's later half.

    A robot picked up late in a revolution shows the new place in those samples only: on the
    whole revolution they are diluted by the first half's (a 6x6 run: 0.040 of the known hits
    contradicting the map, 0.17 of the later half's), and it was said lost two whole revolutions
    later (550 ms).
    """
    times_s = scan.time_s[np.flatnonzero(scan.valid)[::stride]]
    return times_s >= 0.5 * (float(scan.time_s[0]) + float(scan.end_time_s))


def _same_pose(a: np.ndarray, b: np.ndarray, params: GuardParams) -> bool:
    """Two found poses are one (ICP from two candidates converging to the same place)."""
    return bool(math.hypot(a[0] - b[0], a[1] - b[1]) < 2 * params.search_step_m and abs(wrap_angle(a[2] - b[2])) < 0.1)


class LocalizationGuard:
    """Holds revolutions that do not fit the map back from SLAM and says when the robot is lost.

    Example (what the SLAM task does with each revolution)::

        verdict = guard.check(slam, scan, odometry)   # "ok", "skip" or "lost"
        if verdict == "lost":
            result = search_pose(slam, scan, odometry, guard.guess, guard.params)   # in an executor
            guard.accept(slam, result)
    """

    def __init__(self, params: GuardParams | None = None) -> None:
        self.params = params or GuardParams()
        self.lost = False
        self._misfits = 0
        self.guess: np.ndarray | None = None  # the predicted map pose of the last checked revolution
        self.last_fit: ScanFit | None = None
        self.relocalizations = 0
        self.failed_searches = 0  # since the robot got lost: each one widens the next search
        self.unconfirmed: SearchResult | None = None  # a pose found from a partly known view, not yet found again
        self._turns: list[float] = []  # ICP's heading corrections of the last revolutions

    def predicted_pose(self, slam: Slam, scan: Scan, odometry: OdometrySource) -> np.ndarray:
        """Where the odometry says the robot is at the revolution's end, in the map frame."""
        odom = odometry_pose_at(odometry, scan.end_time_s - slam.time_offset.offset_s)
        return compose(slam.map_from_odom, odom)

    def check(self, slam: Slam, scan: Scan, odometry: OdometrySource) -> str:
        """``ok``: give it to SLAM; ``skip``: it does not fit (hold it back); ``lost``: search now."""
        p = self.params
        self.guess = self.predicted_pose(slam, scan, odometry)
        if len(slam.keyframes) < p.min_keyframes:
            return "ok"
        mount = (slam.params.prepare.mount_x_m, slam.params.prepare.mount_y_m)
        hits = hits_in_map(scan, slam.map_from_odom, odometry, time_offset_s=slam.time_offset.offset_s,
                           mount_xy_m=mount, stride=p.stride)
        # judged against the grid and the local submap's surfaces; the search judges its poses against
        # the grid alone: a pose it takes moves SLAM for good, so it keeps the stricter test
        known, contradicting, on_walls = hit_classes(slam.grid, hits, p.free_margin_cells, slam.target)
        fit = ScanFit.count(known, contradicting, on_walls)
        self.last_fit = fit
        if self.lost:
            # search with every revolution, even one the map hardly knows at the odometry's wrong
            # pose (it was held back, and the robot stood waiting for ever): the search looks around
            return "lost"
        if fit.known < p.min_known_hits // p.stride:
            return "ok"
        if fit.contradiction <= p.max_contradiction:
            # a suspect revolution counts towards the streak but never ends it: it may be the one
            # the robot was picked up in, or a healthy one with a few stray hits
            later = _later_half(scan, p.stride)
            later_fit = ScanFit.count(known[later], contradicting[later], on_walls[later])
            suspect = fit.contradiction > p.suspect_contradiction or (
                later_fit.known >= p.min_known_hits // p.stride and later_fit.contradiction > p.suspect_contradiction)
            self._misfits = min(self._misfits + 1, p.lost_after - 1) if suspect else 0
            return "ok"
        self._misfits += 1
        if self._misfits >= p.lost_after:
            self.lost = True
            return "lost"
        return "skip"

    def accept(self, slam: Slam, result: SearchResult) -> bool:
        """Put SLAM at the found pose (True), or stay lost (False: search again on the next revolution).

        A pose found from the known part of the view only (``result.partial``) is taken when
        the next revolution's search finds it again (the robot stands still while lost, so
        both must agree within ``confirm_m`` / ``confirm_rad`` after the odometry's motion in
        between): one revolution's noise can favour a wrong pose once, rarely twice.
        """
        if result.pose is None:
            self.unconfirmed = None
            self.failed_searches += 1
            return False
        if result.partial and not self._confirms(result):
            self.unconfirmed = result  # the next search must find it again; the window stays as it is
            return False
        slam.relocalized(result.pose, result.odom)
        self.lost = False
        self._misfits = 0
        self.failed_searches = 0
        self.unconfirmed = None
        self.relocalizations += 1
        log.info(
            "re-localized at (%.3f m, %.3f m, %.1f°), %.3f m / %.1f° from where the odometry thought%s",
            result.pose[0], result.pose[1], math.degrees(result.pose[2]),
            math.hypot(*(result.pose[:2] - result.guess[:2])),
            math.degrees(wrap_angle(result.pose[2] - result.guess[2])),
            " (from the part of the view the map knows, found twice)" if result.partial else "",
        )
        return True

    def _confirms(self, result: SearchResult) -> bool:
        """``result`` (partial) is where the previous partial find says the robot is now."""
        earlier = self.unconfirmed
        if earlier is None or earlier.pose is None or result.pose is None:
            return False
        expected = compose(earlier.pose, compose(inverse(earlier.odom), result.odom))
        d = result.pose - expected
        return bool(math.hypot(d[0], d[1]) <= self.params.confirm_m
                    and abs(wrap_angle(d[2])) <= self.params.confirm_rad)

    @property
    def search_scale(self) -> float:
        """How much wider than the first the next search is."""
        return min(MAX_SEARCH_SCALE, 1.0 + 0.5 * self.failed_searches)

    def slipped(self, predicted: np.ndarray, corrected: np.ndarray,
                at_rest: bool = False) -> tuple[float, float] | None:
        """(metres, radians) ICP moved the prediction, if that is more than the odometry's own error; else None.

        Call it once per matched revolution: the turns of the last ``slip_scans`` add up (a
        slipping tyre turns the robot the same way revolution after revolution). A revolution
        ``at_rest`` (the odometry stood still through it) is no slip, whatever ICP moved:
        wheels that do not turn cannot slip, and what ICP moves there is the filter's own
        error, which the next revolutions correct without the wheels. It also ends the
        revolutions whose turns add up: on a quota run the first revolutions of a stop were
        called slips by the 2-4° the turn before them had left in the sum.
        """
        p = self.params
        if at_rest:
            self._turns.clear()
            return None
        d = compose(inverse(predicted), corrected)
        moved_m, turned_rad = math.hypot(d[0], d[1]), float(wrap_angle(d[2]))
        self._turns.append(turned_rad)
        del self._turns[: -p.slip_scans]
        total_rad = abs(sum(self._turns))
        if moved_m > p.slip_m or abs(turned_rad) > p.slip_rad or total_rad > p.slip_sum_rad:
            return moved_m, max(abs(turned_rad), total_rad)
        return None
