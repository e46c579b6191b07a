"""A log-odds occupancy grid that grows as the robot explores.

Each cell holds the log odds ``l = log(p / (1 − p))`` that it is occupied, starting at
0 (p = 0.5, unknown). A scan adds ``l_hit`` to the cells holding a beam's endpoint and
``l_miss`` (negative) to the cells the beams cross on their way there: the inverse
sensor model update of Thrun, Burgard & Fox, *Probabilistic Robotics*, ch. 9
(Table 9.1, eq. 9.7), with the prior term 0. Values are clamped to
``[l_min, l_max]`` so a cell that changes (a door, a mapping error fixed after loop
closure) can flip back within a few scans.

Within one :meth:`OccupancyGrid.integrate` call a cell is updated at most once, and a
hit wins over a miss (the rule of Cartographer's probability grid): a beam grazing a
wall must not erase the cell another beam of the same scan hit, and cells near the
robot, crossed by hundreds of beams, count as one observation per scan.

Beams are traced by sampling each at ``trace_step`` of a cell (vectorized over all
beams with ``np.repeat``; no Python loop per beam or cell). The sample that falls in the
endpoint's cell and everything after it is not marked free.

Within ``blind_range_m`` of where it starts (the lidar's minimum range) a beam lowers
only cells not believed occupied: it can make the robot's own surroundings free and
settle a cell one stray hit left unknown, but never erases a wall or leg seen there. Inside that distance the sensor
cannot see an obstacle: a 2 cm table leg 10 cm from an RPLidar A1 (minimum range 0.15 m,
datasheet) gives no return at all, while the beams passing a degree beside it still cross
the 2 cm cells its face was painted in from farther away. Clearing there erased the leg
from the map within a second of the robot coming close (a hand-built 8×8 maze: the leg's
cells went from log odds 2.3 to -1.7 while the robot turned in place 12 cm from it, and it
then drove into the leg). What was seen from outside the blind zone now stays until the
robot sees the place again from outside it.

The array grows: when a scan reaches past its edge it is reallocated with a margin,
content kept at the same world coordinates. Frame: ``grid[row, col]``, row 0 south,
column 0 west, cell (row, col) spanning ``origin + (col, row) * resolution`` — the ROS
``map_server`` orientation. The origin is a multiple of the resolution plus the grid's
``cell_offset_m``, so cell boundaries never move between reallocations; a rebuild may
shift them by a fraction of a cell (:meth:`OccupancyGrid.rebuild`): a maze's thin walls
then lie along cell centres rather than on the boundaries, where each would blacken two
cells and take a cell's width of free space from the corridor beside it.

Beside the log odds each cell keeps whether it was ever believed occupied (:attr:`OccupancyGrid.ever_occupied`,
one byte a cell against the log odds' four). A board marked from close by can be worn to the free clamp
by far beams grazing it (a wall turned a degree to the rows of cells crosses them, and a grazing beam
clears a cell its face only partly fills); the map then holds free a place where the robot saw a wall.
The lost-robot guard (:mod:`mazebot.slam.relocalize`) does not count hits there as evidence of being lost.

For the websocket deltas, :meth:`OccupancyGrid.take_dirty` returns the cells whose
three-state value (-1 unknown, 0 free, 100 occupied) changed since the previous call;
``generation`` counts reallocations and rebuilds, after which clients need a full map.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

#: Keyframes moved into the world together when the grid is rebuilt: the rays of one chunk (~25 kB a
#: keyframe) exist at once, and the per-call cost of moving them is paid once a chunk.
REBUILD_CHUNK_KEYFRAMES = 16

UNKNOWN = -1
FREE = 0
OCCUPIED = 100


@dataclass(frozen=True)
class DirtyCells:
    """Cells whose three-state value changed: ``rows``, ``cols`` (int64) and new ``values`` (int8).

    Indices are in the grid of ``generation``; a client holding another generation
    needs the full map instead.
    """

    rows: np.ndarray
    cols: np.ndarray
    values: np.ndarray
    generation: int

    def __len__(self) -> int:
        return int(self.rows.shape[0])


def _logit(p: float) -> float:
    return float(np.log(p / (1.0 - p)))


class OccupancyGrid:
    """Log-odds occupancy grid in float32, growing on demand.

    Example::

        grid = OccupancyGrid(resolution_m=0.02)
        grid.integrate(sensor_pose, endpoints_world, hit_mask)
        walls = grid.occupied_mask()        # bool [row, col], row 0 south
        delta = grid.take_dirty()           # for the websocket

    Parameters: ``l_hit``/``l_miss`` are the log-odds increments, ``l_min``/``l_max`` the
    clamp, ``occupied_prob``/``free_prob`` the three-state thresholds (a cell is
    occupied above ``occupied_prob``, free below ``free_prob``), ``max_free_range_m``
    the length up to which a no-return beam clears space, ``margin_m`` the extra room
    added on each side when the grid grows, ``blind_range_m`` the stretch at the start of
    every beam that clears no occupied cell (the lidar's minimum range; module docstring).
    """

    def __init__(
        self,
        resolution_m: float = 0.02,
        l_hit: float = 0.85,
        l_miss: float = -0.4,
        l_min: float = -5.0,
        l_max: float = 5.0,
        occupied_prob: float = 0.65,
        free_prob: float = 0.25,
        max_free_range_m: float = 4.0,
        margin_m: float = 1.0,
        trace_step: float = 0.5,
        blind_range_m: float = 0.0,
    ) -> None:
        if resolution_m <= 0:
            raise ValueError(f"resolution_m must be positive, got {resolution_m}")
        if not (l_hit > 0 > l_miss and l_min < 0 < l_max):
            raise ValueError(f"need l_hit > 0 > l_miss and l_min < 0 < l_max, got {l_hit}, {l_miss}, {l_min}, {l_max}")
        if not 0.0 < free_prob <= 0.5 <= occupied_prob < 1.0:
            raise ValueError(f"need 0 < free_prob <= 0.5 <= occupied_prob < 1, got {free_prob}, {occupied_prob}")
        if not 0.0 < trace_step <= 1.0:
            raise ValueError(f"trace_step is a fraction of a cell in (0, 1], got {trace_step}")
        if not 0.0 <= blind_range_m < max_free_range_m:
            raise ValueError(f"need 0 <= blind_range_m < max_free_range_m, got {blind_range_m}, {max_free_range_m}")
        self.resolution_m = float(resolution_m)
        self.l_hit, self.l_miss = float(l_hit), float(l_miss)
        self.l_min, self.l_max = float(l_min), float(l_max)
        self.occupied_logodds = _logit(occupied_prob)
        self.free_logodds = _logit(free_prob)
        self.max_free_range_m = float(max_free_range_m)
        self.margin_m = float(margin_m)
        self.trace_step = float(trace_step)
        self.blind_range_m = float(blind_range_m)
        self.generation = 0
        self.cell_offset_m = (0.0, 0.0)  # where the cells' corners lie, modulo the resolution (rebuild)
        self._clear()

    def _clear(self) -> None:
        self.log_odds = np.zeros((0, 0), dtype=np.float32)
        self._origin_cells = (0, 0)  # (col, row) index of cell (0, 0) in the infinite lattice
        self._reported = np.zeros((0, 0), dtype=np.int8)  # three-state last handed out
        self._touched = np.zeros((0, 0), dtype=bool)  # cells updated since take_dirty (bounded memory)
        #: bool [row, col]: the cell's log odds rose above the occupied threshold at some time (module docstring)
        self.ever_occupied = np.zeros((0, 0), dtype=bool)

    def holding(
        self, log_odds: np.ndarray, origin_cells: tuple[int, int], cell_offset_m: tuple[float, float]
    ) -> OccupancyGrid:
        """A grid with this one's sensor model holding a map kept before (a saved run's).

        ``origin_cells`` and ``cell_offset_m`` place the array as :attr:`origin_cells` and
        ``cell_offset_m`` did when it was kept. Every cell counts as handed out already:
        clients of the new grid load it whole (a new generation), not as changes.
        """
        grid = copy.copy(self)
        grid._clear()
        grid.log_odds = np.array(log_odds, dtype=np.float32)
        grid._origin_cells = (int(origin_cells[0]), int(origin_cells[1]))
        grid.cell_offset_m = (float(cell_offset_m[0]), float(cell_offset_m[1]))
        grid._touched = np.zeros(grid.log_odds.shape, dtype=bool)
        grid._reported = grid.three_state()
        grid.ever_occupied = grid.occupied_mask()  # what was worn away before it was kept is not known
        return grid

    # -- frame -------------------------------------------------------------------------

    @property
    def origin_cells(self) -> tuple[int, int]:
        """(col, row) index of the array's cell (0, 0) in the infinite lattice of cells."""
        return (int(self._origin_cells[0]), int(self._origin_cells[1]))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the current array."""
        return self.log_odds.shape

    @property
    def origin_m(self) -> tuple[float, float]:
        """World (x, y) in metres of the south-west corner of cell (0, 0)."""
        return (self._origin_cells[0] * self.resolution_m + self.cell_offset_m[0],
                self._origin_cells[1] * self.resolution_m + self.cell_offset_m[1])

    def to_cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) int64 of the cells holding world points ``xy`` (N, 2); may be off the grid."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - np.asarray(self.cell_offset_m)
        col = np.floor(p[:, 0] / self.resolution_m).astype(np.int64) - self._origin_cells[0]
        row = np.floor(p[:, 1] / self.resolution_m).astype(np.int64) - self._origin_cells[1]
        return row, col

    def to_world(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World coordinates (N, 2) in metres of the centres of cells (rows, cols)."""
        r = np.asarray(rows, dtype=np.float64).reshape(-1)
        c = np.asarray(cols, dtype=np.float64).reshape(-1)
        ox, oy = self.origin_m
        return np.column_stack((ox + (c + 0.5) * self.resolution_m, oy + (r + 0.5) * self.resolution_m))

    # -- reading -----------------------------------------------------------------------

    def three_state(self) -> np.ndarray:
        """int8 [row, col]: -1 unknown, 0 free, 100 occupied (the ROS ``OccupancyGrid`` values)."""
        return self._classify(self.log_odds)

    def _classify(self, log_odds: np.ndarray) -> np.ndarray:
        out = np.full(log_odds.shape, UNKNOWN, dtype=np.int8)
        out[log_odds > self.occupied_logodds] = OCCUPIED
        out[log_odds < self.free_logodds] = FREE
        return out

    def occupied_mask(self) -> np.ndarray:
        """bool [row, col]: cells believed occupied."""
        return self.log_odds > self.occupied_logodds

    def known_free_mask(self) -> np.ndarray:
        """bool [row, col]: cells believed free (the numerator of coverage)."""
        return self.log_odds < self.free_logodds

    def probability(self) -> np.ndarray:
        """float32 [row, col]: occupancy probability ``1 − 1 / (1 + exp(l))``."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)

    # -- writing -----------------------------------------------------------------------

    def integrate(
        self,
        sensor_pose: np.ndarray,
        endpoints_world: np.ndarray,
        hit_mask: np.ndarray,
        origins_world: np.ndarray | None = None,
    ) -> None:
        """Add one scan: free along every beam, occupied at the endpoints of hits.

        ``sensor_pose`` (3,) (or (2,)) is the lidar's world pose; only its position is
        used, as the start of every beam unless ``origins_world`` (N, 2) gives one start
        per beam (de-skewed scans: the lidar moved during the revolution).
        ``endpoints_world`` (N, 2) in metres; ``hit_mask`` (N,) False for beams without
        a return, which clear space up to ``max_free_range_m`` and mark no hit.
        """
        starts, ends, hit = self._rays(sensor_pose, endpoints_world, hit_mask, origins_world)
        if ends.shape[0] == 0:
            return
        self._ensure_contains(np.concatenate((starts, ends)))
        # beams in continuous cell units of the current array: (col, row) = xy / res - origin
        origin = np.array(self._origin_cells, dtype=np.float64)
        offset = np.asarray(self.cell_offset_m)
        start_c = (starts - offset) / self.resolution_m - origin
        end_c = (ends - offset) / self.resolution_m - origin
        end_cell = np.floor(end_c).astype(np.int64)
        past_blind = self._past_blind_zone(start_c, end_c)
        free_c, free_r = self._trace_free(past_blind, end_c, end_cell, hit, drop_hit_cells=False)
        hit_c, hit_r = end_cell[hit, 0], end_cell[hit, 1]
        blind_c, blind_r = self._trace_free(start_c, past_blind, end_cell, hit, drop_hit_cells=False)

        # one update per cell per scan, a hit winning over a miss: mark a window, then update
        end_lo, end_hi = _xy_bounds(end_cell)
        start_lo, start_hi = _xy_bounds(start_c)
        lo = np.minimum(end_lo, np.floor(start_lo).astype(np.int64))
        hi = np.maximum(end_hi, np.floor(start_hi).astype(np.int64))
        shape = (int(hi[1] - lo[1]) + 1, int(hi[0] - lo[0]) + 1)
        is_free = np.zeros(shape, dtype=bool)
        is_hit = np.zeros(shape, dtype=bool)
        is_free.reshape(-1)[(free_r - lo[1]) * shape[1] + (free_c - lo[0])] = True  # flat: one index array
        is_hit[hit_r - lo[1], hit_c - lo[0]] = True
        is_free &= ~is_hit
        cols = self.shape[1]
        flat = self.log_odds.reshape(-1)
        if blind_c.size:  # crossed only within the blind zone: lowered unless believed occupied
            is_blind = np.zeros(shape, dtype=bool)
            is_blind.reshape(-1)[(blind_r - lo[1]) * shape[1] + (blind_c - lo[0])] = True
            br, bc = np.nonzero(is_blind & ~is_free & ~is_hit)
            lower = flat[(br + lo[1]) * cols + (bc + lo[0])] <= self.occupied_logodds
            is_free[br[lower], bc[lower]] = True
        fr, fc = np.nonzero(is_free)
        hr, hc = np.nonzero(is_hit)
        free_flat = (fr + lo[1]) * cols + (fc + lo[0])
        hit_flat = (hr + lo[1]) * cols + (hc + lo[0])
        flat[free_flat] = np.maximum(flat[free_flat] + self.l_miss, self.l_min)
        flat[hit_flat] = np.minimum(flat[hit_flat] + self.l_hit, self.l_max)
        # only a hit raises a cell: its cells are the only ones that can cross the threshold
        self.ever_occupied.reshape(-1)[hit_flat[flat[hit_flat] > self.occupied_logodds]] = True
        touched = self._touched.reshape(-1)
        touched[free_flat] = True
        touched[hit_flat] = True

    def _rays(
        self,
        sensor_pose: np.ndarray,
        endpoints_world: np.ndarray,
        hit_mask: np.ndarray,
        origins_world: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Checked (starts, ends, hit) arrays, no-return beams shortened to ``max_free_range_m``."""
        ends = np.asarray(endpoints_world, dtype=np.float64).reshape(-1, 2)
        hit = np.asarray(hit_mask, dtype=bool).reshape(-1)
        if hit.shape[0] != ends.shape[0]:
            raise ValueError(f"hit_mask has {hit.shape[0]} entries for {ends.shape[0]} endpoints")
        if origins_world is None:
            starts = np.broadcast_to(np.asarray(sensor_pose, dtype=np.float64).reshape(-1)[:2], ends.shape)
        else:
            starts = np.asarray(origins_world, dtype=np.float64).reshape(-1, 2)
            if starts.shape != ends.shape:
                raise ValueError(f"origins_world must have shape {ends.shape}, got {starts.shape}")
        vec = ends - starts
        length = np.hypot(vec[:, 0], vec[:, 1])
        cap = np.where(hit, length, np.minimum(length, self.max_free_range_m))
        scale = np.divide(cap, length, out=np.zeros_like(cap), where=length > 0)
        return starts, starts + vec * scale[:, None], hit

    def _past_blind_zone(self, start_c: np.ndarray, end_c: np.ndarray) -> np.ndarray:
        """Where each beam (cell units) leaves the blind zone: ``blind_range_m`` along it, at most its end."""
        if self.blind_range_m <= 0.0:
            return start_c
        vec = end_c - start_c
        length = np.hypot(vec[:, 0], vec[:, 1])
        skip = np.minimum(self.blind_range_m / self.resolution_m, length)
        scale = np.divide(skip, length, out=np.zeros_like(length), where=length > 0)
        return start_c + vec * scale[:, None]

    def _trace_free(
        self,
        start_c: np.ndarray,
        end_c: np.ndarray,
        end_cell: np.ndarray,
        hit: np.ndarray,
        drop_hit_cells: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Cells (cols, rows) crossed by the beams before their endpoint's cell.

        Beams are given in continuous cell units. Samples every ``trace_step`` cell along
        each beam, all beams at once (``np.repeat`` builds the flat sample list). A beam's
        samples inside its own endpoint cell are dropped for hits (that cell is the wall);
        no-return beams keep theirs. ``drop_hit_cells=False`` keeps them too, for a caller
        that lets hits win over misses anyway (:meth:`integrate`): the same cells result.
        """
        step = self.trace_step
        vec = end_c - start_c
        length = np.hypot(vec[:, 0], vec[:, 1])
        count = np.ceil(length / step).astype(np.int64)  # samples at 0, step, ... short of the end
        total = int(count.sum())
        if total == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        # per-beam values repeated per sample (np.repeat of a column is cheaper than a gather)
        k = np.arange(total, dtype=np.float64) - np.repeat(np.cumsum(count) - count, count)
        frac = np.repeat(np.divide(step, length, out=np.zeros_like(length), where=length > 0), count) * k  # in [0, 1)
        col = np.floor(np.repeat(start_c[:, 0], count) + np.repeat(vec[:, 0], count) * frac).astype(np.int64)
        row = np.floor(np.repeat(start_c[:, 1], count) + np.repeat(vec[:, 1], count) * frac).astype(np.int64)
        if not drop_hit_cells:
            return col, row
        keep = ~(
            (col == np.repeat(end_cell[:, 0], count))
            & (row == np.repeat(end_cell[:, 1], count))
            & np.repeat(hit, count)
        )
        return col[keep], row[keep]

    def _ensure_contains(self, xy: np.ndarray) -> None:
        """Grow the array (with ``margin_m`` on each side) so every point lies on it."""
        res = self.resolution_m
        xy_lo, xy_hi = _xy_bounds(xy)
        xy_lo, xy_hi = xy_lo - np.asarray(self.cell_offset_m), xy_hi - np.asarray(self.cell_offset_m)
        lo = np.floor(xy_lo / res).astype(np.int64)  # (col, row) in the lattice
        hi = np.floor(xy_hi / res).astype(np.int64)
        rows, cols = self.shape
        oc, orow = self._origin_cells
        if rows and cols and lo[0] >= oc and lo[1] >= orow and hi[0] < oc + cols and hi[1] < orow + rows:
            return
        margin = int(np.ceil(self.margin_m / res))
        if rows and cols:
            lo = np.minimum(lo, (oc, orow))
            hi = np.maximum(hi, (oc + cols - 1, orow + rows - 1))
        new_oc, new_or = int(lo[0]) - margin, int(lo[1]) - margin
        new_cols = int(hi[0]) + margin + 1 - new_oc
        new_rows = int(hi[1]) + margin + 1 - new_or
        grown = np.zeros((new_rows, new_cols), dtype=np.float32)
        reported = np.full((new_rows, new_cols), UNKNOWN, dtype=np.int8)
        touched = np.zeros((new_rows, new_cols), dtype=bool)
        ever = np.zeros((new_rows, new_cols), dtype=bool)
        dr, dc = orow - new_or, oc - new_oc
        if rows and cols:  # the content, what clients were told and pending changes move together
            grown[dr : dr + rows, dc : dc + cols] = self.log_odds
            reported[dr : dr + rows, dc : dc + cols] = self._reported
            touched[dr : dr + rows, dc : dc + cols] = self._touched
            ever[dr : dr + rows, dc : dc + cols] = self.ever_occupied
        self.log_odds = grown
        self._reported = reported
        self._touched = touched
        self.ever_occupied = ever
        self._origin_cells = (new_oc, new_or)
        self.generation += 1

    # -- deltas and rebuilds -----------------------------------------------------------

    def take_dirty(self) -> DirtyCells:
        """Cells whose three-state value changed since the last call, and forget them."""
        touched = np.flatnonzero(self._touched)
        self._touched[...] = False
        cols = self.shape[1]
        now = self._classify(self.log_odds.reshape(-1)[touched])
        reported = self._reported.reshape(-1)
        changed = touched[now != reported[touched]]
        values = now[now != reported[touched]]
        reported[changed] = values
        return DirtyCells(changed // max(cols, 1), changed % max(cols, 1), values, self.generation)

    def rebuild(
        self, keyframes: Iterable[Sequence[np.ndarray]], cell_offset_m: tuple[float, float] | None = None
    ) -> None:
        """Recompute the grid from scratch, e.g. after a loop closure moved the poses.

        Each keyframe is ``(pose (3,), endpoints (N, 2), hit_mask (N,))`` or with a fourth
        ``origins (N, 2)``, endpoints and origins in the keyframe's robot frame (the
        beams of :meth:`mazebot.slam.preprocess.PreparedScan.beams`); without origins
        beams start at the pose's position. The array is sized once for all keyframes;
        ``generation`` increments and the next :meth:`take_dirty` reports only later
        changes (clients reload the full map). ``cell_offset_m`` moves the cells' corners to
        that place modulo the resolution (None: where they were).
        """
        keyframes = list(keyframes)
        chunks = [keyframes[i : i + REBUILD_CHUNK_KEYFRAMES] for i in range(0, len(keyframes), REBUILD_CHUNK_KEYFRAMES)]
        # Two passes: the extent first, then the rays, a chunk of keyframes at a time. Holding every
        # keyframe's world rays at once costs ~17 kB per keyframe (60 MB for a 16x16 maze).
        corners = []
        for chunk in chunks:
            starts, ends, _, _ = self._world_rays(chunk)
            if ends.shape[0]:
                both = np.concatenate((starts, ends))
                corners += [both.min(axis=0), both.max(axis=0)]
        generation = self.generation
        self._clear()
        if cell_offset_m is not None:
            res = self.resolution_m
            self.cell_offset_m = (float(np.remainder(cell_offset_m[0], res)),
                                  float(np.remainder(cell_offset_m[1], res)))
        if corners:  # size the array once for all keyframes
            self._ensure_contains(np.array(corners))
        for chunk in chunks:
            starts, ends, hit, bounds = self._world_rays(chunk)
            for first, last in itertools.pairwise(bounds):
                if last > first:
                    self.integrate(starts[first], ends[first:last], hit[first:last], starts[first:last])
        self.generation = generation + 1
        self._touched[...] = False
        self._reported = self.three_state()

    def _world_rays(
        self, keyframes: Sequence[Sequence[np.ndarray]]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The keyframes' beams in the world as :meth:`_rays` checks them: ``(starts, ends, hit, bounds)``.

        Keyframe ``k``'s beams are rows ``bounds[k]:bounds[k + 1]``. All keyframes are moved in
        one vectorized pass, each point with its keyframe's cosine, sine and translation: the
        arithmetic of :func:`mazebot.geometry.transform_points` point by point, so the result
        is the same to the bit.
        """
        poses = np.array([np.asarray(kf[0], dtype=np.float64)[:3] for kf in keyframes]).reshape(-1, 3)
        counts = np.array([np.asarray(kf[1]).reshape(-1, 2).shape[0] for kf in keyframes], dtype=np.int64)
        cos = np.repeat([math.cos(float(t)) for t in poses[:, 2]], counts)
        sin = np.repeat([math.sin(float(t)) for t in poses[:, 2]], counts)
        x, y = np.repeat(poses[:, 0], counts), np.repeat(poses[:, 1], counts)

        def moved(local: np.ndarray) -> np.ndarray:
            px, py = local[:, 0], local[:, 1]
            return np.column_stack((cos * px - sin * py + x, sin * px + cos * py + y))

        ends = moved(np.concatenate([np.asarray(kf[1], dtype=np.float64).reshape(-1, 2) for kf in keyframes]))
        hit = np.concatenate([np.asarray(kf[2], dtype=bool).reshape(-1) for kf in keyframes])
        # beams without their own origins start at the pose's position: (0, 0) moved, to the bit
        origins = moved(np.concatenate([
            np.asarray(kf[3], dtype=np.float64).reshape(-1, 2) if len(kf) >= 4 else np.zeros((int(n), 2))
            for kf, n in zip(keyframes, counts, strict=True)
        ]))
        starts, ends, hit = self._rays(origins[:1], ends, hit, origins)
        return starts, ends, hit, np.concatenate(([0], np.cumsum(counts)))


def _xy_bounds(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column minimum and maximum of an (N, 2) array: ``xy.min(axis=0)``, ``xy.max(axis=0)``.

    Column by column, because numpy reduces along a length-2 axis element by element:
    ~20 µs against ~5 µs for a revolution's points, and the grid takes bounds per scan.
    """
    x, y = xy[:, 0], xy[:, 1]
    return np.array((x.min(), y.min())), np.array((x.max(), y.max()))
