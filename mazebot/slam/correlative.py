"""Correlative scan matching: the best pose over a whole window, not the nearest local optimum.

ICP converges to the alignment nearest its start; once the prediction is off by more
than about half a corridor or ten degrees (an in-place turn with slipping wheels, a
metre between two scans of a laser log, a loop closure whose prior drifted) it settles
in a wrong one. The correlative matcher of Olson ("Real-Time Correlative Scan
Matching", ICRA 2009) instead scores *every* pose of a window of ``x``, ``y`` and
heading against a lookup table rasterised from the reference points, and keeps the
best; ICP then refines it.

**The table** (:class:`LikelihoodTable`). Each cell holds ``exp(−d²/2σ²)``, ``d`` the
distance from the cell's centre to the nearest reference point (Olson's rasterised
likelihood, the Gaussian of the point's position error; here from an exact Euclidean
distance transform, ``scipy.ndimage.distance_transform_edt``). A scan's score at a pose
is the mean table value under its points: 1 when every point lies on a reference
surface, 0 when none is within a few ``σ``.

**The search.** Headings are tried ``Δθ`` apart, with ``Δθ`` such that a point at the
scan's far range moves by about one cell between two of them (Olson, section III.C);
for each heading the points are rotated once, and every translation is an integer
shift of their cell indices (no transform per candidate: a gather from the table).
Translations are searched by **branch and bound** (Hess, Kohler, Rapp & Andor,
"Real-Time Loop Closure in 2D LIDAR SLAM", ICRA 2016, section V.C): level ``h`` of the
table holds, for every cell, the maximum of the fine table over the ``2^h × 2^h`` block
starting there, so the score of a level-``h`` table under the scan bounds from above
the score of every translation in the block. Blocks are expanded depth first, best
first; a block whose bound is not better than the best fine score found so far is
pruned. The answer is exactly the exhaustive search's (``exhaustive=True`` computes
that one, for tests), at a fraction of the lookups. With one coarse level this is
Olson's two-resolution search (a coarse max table to prune, the fine one to pick).

Everything is counted in table lookups (``CorrelativeResult.lookups``): what the search
did does not depend on the CPU.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mazebot.slam_config import CorrelativeParams as CorrelativeParams  # the [slam.search] section


@dataclass(frozen=True)
class CorrelativeResult:
    """The best pose (3,) of the window, its score (mean likelihood, 0..1), and what the search cost.

    ``lookups`` counts table reads (points × candidates scored at any level);
    ``candidates`` the number of poses a fine exhaustive search would have scored.
    """

    pose: np.ndarray
    score: float
    lookups: int
    candidates: int
    headings: int


class LikelihoodTable:
    """The smoothed likelihood of reference points on a grid, with its branch-and-bound max levels.

    ``points_xy`` (M, 2) in the frame the search poses are in. The grid covers the points'
    bounding box (cropped to ``crop = (centre (2,), radius_m)`` if given) plus a margin
    of 3σ, and a zero border wide enough for the coarsest block, so a point that falls
    off the grid reads 0 at every level. Tables are indexed ``[ix, iy]``.
    """

    def __init__(
        self,
        points_xy: np.ndarray,
        resolution_m: float,
        sigma_m: float,
        levels: int = 2,
        crop: tuple[np.ndarray, float] | None = None,
    ) -> None:
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        if crop is not None:
            centre, radius = np.asarray(crop[0], dtype=np.float64).reshape(2), float(crop[1])
            pts = pts[np.hypot(*(pts - centre).T) <= radius]
        self.resolution_m = float(resolution_m)
        self.levels = int(levels)
        self.points = pts
        border = 2**self.levels
        margin = math.ceil(3.0 * sigma_m / resolution_m) + 1
        if pts.shape[0] == 0:
            self.origin = np.zeros(2)
            self.tables = [np.zeros((2 * border + 1, 2 * border + 1))] * (self.levels + 1)
            return
        low = np.floor(pts.min(axis=0) / resolution_m).astype(np.int64) - margin - border
        high = np.floor(pts.max(axis=0) / resolution_m).astype(np.int64) + margin + border
        self.origin = low * resolution_m  # the corner of cell [0, 0]
        shape = tuple((high - low + 1).tolist())
        cells = np.floor((pts - self.origin) / resolution_m).astype(np.int64)
        empty = np.ones(shape, dtype=bool)
        empty[cells[:, 0], cells[:, 1]] = False
        dist_m = ndimage.distance_transform_edt(empty) * resolution_m
        fine = np.exp(-0.5 * (dist_m / sigma_m) ** 2)
        fine[:border] = fine[-border:] = 0.0
        fine[:, :border] = fine[:, -border:] = 0.0
        tables = [fine]
        for h in range(1, self.levels + 1):
            # level h at cell c: max of the fine table over [c, c + 2^h)², from level h-1 (a doubling step)
            prev, step = tables[-1], 2 ** (h - 1)
            shifted = np.zeros_like(prev)
            shifted[:-step] = prev[step:]
            rows = np.maximum(prev, shifted)
            shifted = np.zeros_like(rows)
            shifted[:, :-step] = rows[:, step:]
            tables.append(np.maximum(rows, shifted))
        self.tables = tables

    @property
    def shape(self) -> tuple[int, int]:
        return self.tables[0].shape

    def score(self, poses: np.ndarray, source_xy: np.ndarray) -> np.ndarray:
        """Scores (K,) of the source points (N, 2, robot frame) at poses (K, 3) on the fine table."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        src = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
        if src.shape[0] == 0:
            return np.zeros(poses.shape[0])
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        x = c * src[None, :, 0] - s * src[None, :, 1] + poses[:, 0:1]
        y = s * src[None, :, 0] + c * src[None, :, 1] + poses[:, 1:2]
        ix, iy = self._cells(x, y)
        return self.tables[0][ix, iy].mean(axis=1)

    def _cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        shape = self.shape
        ix = np.clip(np.floor((x - self.origin[0]) / self.resolution_m).astype(np.int64), 0, shape[0] - 1)
        iy = np.clip(np.floor((y - self.origin[1]) / self.resolution_m).astype(np.int64), 0, shape[1] - 1)
        return ix, iy


def select_points(source_xy: np.ndarray, sensor_xy: np.ndarray | None, params: CorrelativeParams) -> np.ndarray:
    """The scan points the search uses: within ``max_range_m`` of the lidar, at most ``max_points``, evenly spread."""
    src = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    sensor = np.zeros(2) if sensor_xy is None else np.asarray(sensor_xy, dtype=np.float64).reshape(2)
    src = src[np.hypot(*(src - sensor).T) <= params.max_range_m]
    if src.shape[0] > params.max_points:
        src = src[np.linspace(0, src.shape[0] - 1, params.max_points).round().astype(np.int64)]
    return src


def heading_step_rad(source_xy: np.ndarray, sensor_xy: np.ndarray | None, resolution_m: float) -> float:
    """Olson's heading step: the scan's far points (90th percentile of range) move about one cell per step."""
    src = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    sensor = np.zeros(2) if sensor_xy is None else np.asarray(sensor_xy, dtype=np.float64).reshape(2)
    far = float(np.percentile(np.hypot(*(src - sensor).T), 90)) if src.shape[0] else 1.0
    return min(0.05, resolution_m / max(far, resolution_m))


def correlative_match(
    table: LikelihoodTable,
    source_xy: np.ndarray,
    initial_pose: np.ndarray,
    window_xy_m: float,
    window_theta_rad: float,
    sensor_xy: np.ndarray | None = None,
    *,
    theta_step_rad: float | None = None,
    exhaustive: bool = False,
    exclude: Sequence[tuple[np.ndarray, float]] = (),
    floor: float = -1.0,
) -> CorrelativeResult:
    """The best-scoring pose of ``source_xy`` (N, 2, robot frame) within the window about ``initial_pose``.

    Translations are multiples of the table's resolution from ``initial_pose`` (up to
    ``± window_xy_m``), headings multiples of ``theta_step_rad`` (default
    :func:`heading_step_rad`) up to ``± window_theta_rad``. Branch and bound over the
    table's levels unless ``exhaustive`` (every candidate scored on the fine table; the
    same best pose, ties aside, at many more lookups). Ties go to the candidate nearest
    the initial pose (smallest turn, then smallest shift).

    ``exclude``, discs ``(centre (2,), radius_m)``, leaves out every translation within
    ``radius_m`` of a ``centre`` (at any heading), and only candidates scoring above ``floor`` count:
    :func:`runner_up` asks this for the best *other* alignment. Nothing above the floor
    gives score 0 at ``initial_pose``. The bounds stay bounds of the candidates left in,
    so branch and bound still returns the exhaustive answer, and the floor prunes from the
    start.
    """
    src = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    pose0 = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    res = table.resolution_m
    step = heading_step_rad(src, sensor_xy, res) if theta_step_rad is None else float(theta_step_rad)
    n_theta = math.floor(window_theta_rad / step + 1e-9) if step > 0 else 0
    # headings in the order of their distance from the initial one: ties keep the smaller turn
    k = np.array([0] + [s * i for i in range(1, n_theta + 1) for s in (1, -1)], dtype=np.float64)
    thetas = pose0[2] + k * step
    w = math.floor(window_xy_m / res + 1e-9)
    side = 2 * w + 1
    candidates = len(thetas) * side * side
    if src.shape[0] == 0:
        return CorrelativeResult(pose0.copy(), 0.0, 0, candidates, len(thetas))
    n = src.shape[0]
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    x = c * src[None, :, 0] - s * src[None, :, 1] + pose0[0]
    y = s * src[None, :, 0] + c * src[None, :, 1] + pose0[1]
    # every point's cell at the window's corner (shift -w, -w); a translation adds whole cells
    ix = np.floor((x - table.origin[0]) / res).astype(np.int64) - w
    iy = np.floor((y - table.origin[1]) / res).astype(np.int64) - w
    shape = table.shape

    def scores(level: int, heading: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        gx = np.clip(ix[heading][:, :] + a[:, None], 0, shape[0] - 1)
        gy = np.clip(iy[heading][:, :] + b[:, None], 0, shape[1] - 1)
        return table.tables[level][gx, gy].mean(axis=1)

    def excluded(level: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        # a block of 2^level cells from (a, b) is left out when all its corners lie in one disc (a disc is convex)
        out = np.zeros(np.shape(a), dtype=bool)
        for centre_xy, radius_m in exclude:
            centre, radius = np.asarray(centre_xy, dtype=np.float64).reshape(2), float(radius_m)
            inside = np.ones(np.shape(a), dtype=bool)
            for da in (0, 2**level - 1):
                for db in (0, 2**level - 1):
                    x0 = pose0[0] + (np.asarray(a) + da - w) * res - centre[0]
                    y0 = pose0[1] + (np.asarray(b) + db - w) * res - centre[1]
                    inside &= np.hypot(x0, y0) <= radius
            out |= inside
        return out

    if exhaustive or table.levels == 0:
        grid_a, grid_b = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
        best_key, best = None, float(floor)
        kept = ~excluded(0, grid_a.ravel(), grid_b.ravel())
        for h in range(len(thetas)):
            heads = np.full(side * side, h)
            sc = np.where(kept, scores(0, heads, grid_a.ravel(), grid_b.ravel()), -np.inf)
            keys = _tie_keys(grid_a.ravel(), grid_b.ravel(), w)
            order = np.lexsort((keys, -sc))
            top = order[0]
            if sc[top] > best + 1e-12:
                best, best_key = float(sc[top]), (h, int(grid_a.ravel()[top]), int(grid_b.ravel()[top]))
        if best_key is None:
            return CorrelativeResult(pose0.copy(), 0.0, candidates * n, candidates, len(thetas))
        h, a0, b0 = best_key
        return CorrelativeResult(
            np.array([pose0[0] + (a0 - w) * res, pose0[1] + (b0 - w) * res, float(thetas[h])]),
            best, candidates * n, candidates, len(thetas),
        )

    top = table.levels
    block = 2**top
    starts = np.arange(0, side, block)
    ha, hb = np.meshgrid(starts, starts, indexing="ij")
    heads = np.repeat(np.arange(len(thetas)), ha.size)
    a = np.tile(ha.ravel(), len(thetas))
    b = np.tile(hb.ravel(), len(thetas))
    kept = ~excluded(top, a, b)
    heads, a, b = heads[kept], a[kept], b[kept]
    bound = scores(top, heads, a, b)
    lookups = bound.size * n
    # depth first, best first: a stack of (level, heading, a, b, bound), the best on top
    order = np.argsort(bound, kind="stable")
    stack = [(top, int(heads[i]), int(a[i]), int(b[i]), float(bound[i])) for i in order]
    best, best_key = float(floor), None
    while stack:
        level, h, a0, b0, bd = stack.pop()
        if bd <= best:
            continue
        if level == 0:
            if bd > best + 1e-12:
                best, best_key = bd, (h, a0, b0)
            continue
        half = 2 ** (level - 1)
        ca = np.array([a0, a0, a0 + half, a0 + half])
        cb = np.array([b0, b0 + half, b0, b0 + half])
        inside = (ca < side) & (cb < side)
        ca, cb = ca[inside], cb[inside]
        inside = ~excluded(level - 1, ca, cb)
        ca, cb = ca[inside], cb[inside]
        sc = scores(level - 1, np.full(ca.size, h), ca, cb)
        lookups += sc.size * n
        # pushed worst first (popped best first); among equal scores the one nearest the centre is popped first
        keys = _tie_keys(ca, cb, w) if level == 1 else np.zeros(ca.size)
        for i in np.lexsort((-keys, sc)):
            if sc[i] > best:
                stack.append((level - 1, h, int(ca[i]), int(cb[i]), float(sc[i])))
    if best_key is None:  # nothing above the floor
        return CorrelativeResult(pose0.copy(), 0.0, lookups, candidates, len(thetas))
    h, a0, b0 = best_key
    return CorrelativeResult(
        np.array([pose0[0] + (a0 - w) * res, pose0[1] + (b0 - w) * res, float(thetas[h])]),
        max(best, 0.0), lookups, candidates, len(thetas),
    )


def runner_up(
    table: LikelihoodTable,
    source_xy: np.ndarray,
    initial_pose: np.ndarray,
    window_xy_m: float,
    window_theta_rad: float,
    best: CorrelativeResult,
    separation_m: float,
    ratio: float,
    sensor_xy: np.ndarray | None = None,
) -> CorrelativeResult:
    """The best *distinct* peak of the window other than ``best``, if it scores ``ratio`` of it.

    A ratio test of the best match against the second-best distinct one (Lowe,
    "Distinctive image features from scale-invariant keypoints", IJCV 2004, section 7.1,
    for image features): a window that holds two alignments scoring alike (the same
    corridor seen from two places along it, two identical doorways) cannot say which one
    is right, however good the best one looks. Poses within ``separation_m`` of the best
    are its own peak's shoulder; so is a pose farther away joined to it by a ridge, the
    score on the straight path between them never falling under ``ratio`` of the pose's
    own (:func:`one_ridge`): along a corridor the table's score falls slowly away from the
    right alignment, and the Intel log's right closures had their "runner-up" a metre along
    that ridge at 0.91 of the best. Such a pose is left out with its own disc and the
    search goes on. Score 0: no distinct peak reaches ``ratio`` of the best (the search is
    pruned at that floor). Each round leaves out a disc of ``separation_m`` about a pose
    outside every earlier one, so the rounds end within the window's area.
    """
    discs = [(best.pose[:2], separation_m)]
    while True:
        other = correlative_match(
            table, source_xy, initial_pose, window_xy_m, window_theta_rad, sensor_xy,
            exclude=discs, floor=ratio * best.score,
        )
        if other.score <= 0 or not one_ridge(table, source_xy, best.pose, other, ratio):
            return other
        discs.append((other.pose[:2], separation_m))


def one_ridge(
    table: LikelihoodTable, source_xy: np.ndarray, best_pose: np.ndarray, other: CorrelativeResult, ratio: float
) -> bool:
    """Does the score on the straight path from ``best_pose`` to ``other`` stay at ``ratio`` of ``other``'s or above?

    Then no valley parts them: one peak, stretched (a corridor's walls fit all along it,
    only its door frames say where), not two places. The path is sampled at the table's
    resolution, the heading turned evenly along it.
    """
    delta = np.asarray(other.pose, dtype=np.float64) - np.asarray(best_pose, dtype=np.float64)
    delta[2] = math.remainder(float(delta[2]), 2.0 * math.pi)
    steps = max(2, math.ceil(math.hypot(delta[0], delta[1]) / table.resolution_m))
    path = np.asarray(best_pose, dtype=np.float64) + np.linspace(0.0, 1.0, steps + 1)[:, None] * delta
    return bool(np.min(table.score(path, source_xy)) >= ratio * other.score)


def _tie_keys(a: np.ndarray, b: np.ndarray, w: int) -> np.ndarray:
    """Squared distance (cells) of shifts from the window's centre: among equal scores the smaller shift wins."""
    return (np.asarray(a) - w) ** 2 + (np.asarray(b) - w) ** 2
