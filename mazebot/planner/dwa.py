"""The local planner: Dynamic Window Approach, path following and recovery.

Why one module of ~850 lines: the local costmap, the path tracker, the Dynamic Window planner
and the :class:`LocalPlanner` that wraps it with in-place turns and recovery are the four parts
of one local planner, each used only by the next; the planner's admissibility test, the
tracker's progress and the recovery's time-outs are tuned together and read together.

The Dynamic Window Approach (Fox, Burgard & Thrun 1997, "The dynamic window approach to
collision avoidance", IEEE RA Magazine 4(1)) searches velocities, not paths: it samples
the body velocities ``(v, ω)`` the motors can reach within the next control interval
(the *dynamic window*: the current velocity ± acceleration × interval, inside the speed
limits), rolls each out as a circular arc, discards those on which the robot could not
stop before an obstacle (*admissible* velocities: ``v ≤ sqrt(2 · dist(v, ω) · v̇_b)``,
here with the actuation latency added to the stopping distance), and picks the best of
the rest by a weighted sum of objectives. Fox et al. weigh heading, clearance and
velocity; following a global path through a maze (Nayak et al., "2D Autonomous Mapping", III.C: "distance of the
resulting position to the local goal, and … normal distance from the simulated path to
the desired global path") this planner scores

- **progress** along the global path (arc length gained by the end of the rollout),
- **path distance** (how far the end lies from the path polyline),
- **heading** (the end heading against the direction to a carrot point ahead on the path),
- **clearance** (the smallest obstacle distance along the rollout, capped),
- **speed** (``v / v_max``),

each on a fixed scale so the weights mean the same thing in every situation.

Obstacles (:class:`LocalCostmap`) are the points of the latest scan, the occupied cells
of the map near the robot and, in a maze, the wall outlines the maze graph knows
(:meth:`~mazebot.planner.maze_graph.MazeGraph.wall_points_m`), all in the robot frame:
the scan sees what moved, the map and the walls cover what the lidar cannot see (closer
than its 0.15 m minimum range, and behind), the walls also the post ends a log-odds map
loses. Distances are exact nearest-point distances (a k-d tree), not a raster: in a 1 ft
maze a 0.09 m robot has 36 mm to spare on each side of a cell centre, which a raster's
half-cell error would eat. The inflation is the footprint radius plus a safety margin
(hard: a rollout closer than that is in contact) plus a clearance band (soft: scored).
Map cells count with half their diagonal added, since the wall may lie anywhere inside
an occupied cell.

:class:`LocalPlanner` wraps the DWA with what a maze needs around it: an in-place turn
(:class:`~mazebot.planner.wheel_control.HeadingAligner`) when the path leaves behind the
robot (dead ends), a goal stop, and recovery when stuck (turn in place, back off or
drive out along the most open direction, re-plan; the lesson of Embedded Motion Control 2017 Group 4
(Beurskens, Janssen, Schouten et al.) that a robot must never stand still).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from mazebot.config import ControlConfig, DriveConfig, LidarConfig, PlannerConfig, RobotConfig
from mazebot.planner.wheel_control import DriveMode, HeadingAligner
from mazebot.slam.grid import OCCUPIED
from mazebot.steps import all_at_once_method

# the defaults below are the config's, each written once in mazebot.config
_CONTROL = ControlConfig()
_DRIVE = DriveConfig()
_LIDAR = LidarConfig()
_PLANNER = PlannerConfig()
_ROBOT = RobotConfig()

XY = tuple[float, float]

#: Rollout points per clearance query between two stages of a DWA step (under a millisecond here, quiet).
CLEARANCE_BLOCK = 256


# -- obstacles ---------------------------------------------------------------------------


def scan_points_robot(
    angle_rad: np.ndarray,
    range_m: np.ndarray,
    valid: np.ndarray | None = None,
    min_range_m: float = _LIDAR.min_range_m,
    max_range_m: float = _LIDAR.max_range_m,
    mount_xy_m: XY = (0.0, 0.0),
) -> np.ndarray:
    """Valid scan returns as points (N, 2) in the robot frame (metres).

    ``angle_rad`` counter-clockwise from the robot's heading (the :class:`~mazebot.io.scan.Scan`
    convention), ``valid`` the driver's flags; returns outside ``[min_range_m,
    max_range_m]`` are dropped too. ``mount_xy_m`` is the lidar's offset from the axle
    centre.
    """
    a = np.asarray(angle_rad, dtype=np.float64).reshape(-1)
    r = np.asarray(range_m, dtype=np.float64).reshape(-1)
    ok = np.isfinite(r) & (r >= min_range_m) & (r <= max_range_m)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool).reshape(-1)
    return np.column_stack((mount_xy_m[0] + r[ok] * np.cos(a[ok]), mount_xy_m[1] + r[ok] * np.sin(a[ok])))


def to_robot_frame(points_map: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    """Map-frame points (N, 2) in the frame of a robot at map ``pose`` (x_m, y_m, theta_rad)."""
    pts = np.asarray(points_map, dtype=np.float64).reshape(-1, 2)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = pts[:, 0] - pose[0], pts[:, 1] - pose[1]
    return np.column_stack((c * dx + s * dy, -s * dx + c * dy))


def map_points_robot(
    three_state: np.ndarray,
    origin_m: XY,
    resolution_m: float,
    pose: tuple[float, float, float],
    radius_m: float = 1.0,
) -> np.ndarray:
    """Centres of the occupied map cells within ``radius_m`` of the robot, in the robot frame (N, 2)."""
    grid = np.asarray(three_state)
    x, y, th = pose
    c0 = max(math.floor((x - radius_m - origin_m[0]) / resolution_m), 0)
    c1 = min(math.floor((x + radius_m - origin_m[0]) / resolution_m) + 1, grid.shape[1])
    r0 = max(math.floor((y - radius_m - origin_m[1]) / resolution_m), 0)
    r1 = min(math.floor((y + radius_m - origin_m[1]) / resolution_m) + 1, grid.shape[0])
    if c0 >= c1 or r0 >= r1:
        return np.zeros((0, 2))
    rows, cols = np.nonzero(grid[r0:r1, c0:c1] == OCCUPIED)
    wx = origin_m[0] + (cols + c0 + 0.5) * resolution_m - x
    wy = origin_m[1] + (rows + r0 + 0.5) * resolution_m - y
    keep = wx * wx + wy * wy <= radius_m * radius_m
    c, s = math.cos(th), math.sin(th)
    return np.column_stack((c * wx[keep] + s * wy[keep], -s * wx[keep] + c * wy[keep]))


def cells_without_hits(
    map_xy: np.ndarray,
    hits_xy: np.ndarray,
    pose: tuple[float, float, float],
    origin_m: XY,
    resolution_m: float,
) -> np.ndarray:
    """The occupied map cells of ``map_xy`` (their centres, robot frame (N, 2)) that hold none of ``hits_xy``.

    A map cell stands for an obstacle somewhere inside it, so the local costmap counts it as a disc
    of half its diagonal: up to 14 mm of a 2 cm cell in front of the surface. Where a hit of the
    latest revolution (robot frame (M, 2), the robot at ``pose`` in the map frame) lies in the cell,
    the surface is measured there and the hit stands for it; cells without one keep their disc.
    """
    cells = np.asarray(map_xy, dtype=np.float64).reshape(-1, 2)
    hits = np.asarray(hits_xy, dtype=np.float64).reshape(-1, 2)
    if cells.shape[0] == 0 or hits.shape[0] == 0:
        return cells

    def keys(points: np.ndarray) -> np.ndarray:
        x, y, th = pose
        c, s = math.cos(th), math.sin(th)
        col = np.floor((x + c * points[:, 0] - s * points[:, 1] - origin_m[0]) / resolution_m).astype(np.int64)
        row = np.floor((y + s * points[:, 0] + c * points[:, 1] - origin_m[1]) / resolution_m).astype(np.int64)
        return row * (1 << 32) + col

    return cells[~np.isin(keys(cells), keys(hits))]


class LocalCostmap:
    """Robot-centred obstacles with exact clearance queries, inflated by the robot.

    Example::

        costmap = LocalCostmap(scan_xy, map_xy, map_point_radius_m=0.014)
        costmap.clearance_m(np.array([[0.1, 0.0]]))     # metres to the nearest obstacle surface

    ``scan_points`` and ``map_points`` are (N, 2) robot-frame metres. A map point stands
    for an occupied cell, so it counts as a disc of ``map_point_radius_m`` (half the
    cell's diagonal). ``footprint_radius_m`` is the hard inflation (a centre closer than
    that to an obstacle means contact), ``clearance_m`` the soft band beyond it.
    """

    def __init__(
        self,
        scan_points: np.ndarray,
        map_points: np.ndarray | None = None,
        map_point_radius_m: float = 0.0,
        footprint_radius_m: float = _ROBOT.footprint_radius_m,
        clearance_m: float = _ROBOT.clearance_m,
    ) -> None:
        self.scan_points = np.asarray(scan_points, dtype=np.float64).reshape(-1, 2)
        self.map_points = np.zeros((0, 2)) if map_points is None else np.asarray(map_points, np.float64).reshape(-1, 2)
        self.map_point_radius_m = float(map_point_radius_m)
        self.footprint_radius_m = float(footprint_radius_m)
        self.inflation_m = float(footprint_radius_m + clearance_m)
        self._scan_tree = _tree(self.scan_points)
        self._map_tree = _tree(self.map_points)

    def clearance_m(self, xy: np.ndarray, upper_bound_m: float = np.inf) -> np.ndarray:
        """Distance (M,) from robot-frame points (M, 2) to the nearest obstacle surface.

        Values above ``upper_bound_m`` may be returned as inf (a faster query).
        """
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = np.full(q.shape[0], np.inf)
        if self._scan_tree is not None:
            d, _ = self._scan_tree.query(q, distance_upper_bound=upper_bound_m)
            out = np.minimum(out, d)
        if self._map_tree is not None:
            d, _ = self._map_tree.query(q, distance_upper_bound=upper_bound_m + self.map_point_radius_m)
            out = np.minimum(out, d - self.map_point_radius_m)
        return out

    def cost(self, xy: np.ndarray) -> np.ndarray:
        """Inflation cost (M,): inf in contact, 1 → 0 across the clearance band, 0 beyond."""
        d = self.clearance_m(xy)
        band = max(self.inflation_m - self.footprint_radius_m, 1e-9)
        cost = np.clip((self.inflation_m - d) / band, 0.0, 1.0)
        cost[d < self.footprint_radius_m] = np.inf
        return cost


def _tree(points: np.ndarray) -> cKDTree | None:
    """A k-d tree of ``points`` (None when there are none), built for one planner tick.

    Split at the middle of each cell's extent instead of the median of its points, and
    without shrinking each cell to its points' bounding box: a third less to build for the
    ~1 300 points of a tick, and its queries take as long. A nearest-point distance is the
    same whatever the tree's shape (each candidate's distance is computed the same way).
    """
    return cKDTree(points, balanced_tree=False, compact_nodes=False) if len(points) else None


# -- the path ----------------------------------------------------------------------------


class PathTrack:
    """A global path as a polyline with arc length, for progress and carrot lookups.

    Points are map-frame metres. :meth:`project` finds the arc length of the path point
    nearest to a position, searching only near the last projection so a path that runs
    back past itself (a return along a parallel corridor) cannot make progress jump.
    """

    def __init__(self, waypoints_m: Sequence[XY]) -> None:
        pts = np.asarray(waypoints_m, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] == 0:
            raise ValueError("a path needs at least one waypoint")
        keep = np.concatenate(([True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9))
        self.points = pts[keep]
        seg = np.diff(self.points, axis=0)
        self.seg_len = np.hypot(seg[:, 0], seg[:, 1])
        self.cum = np.concatenate(([0.0], np.cumsum(self.seg_len)))
        self.length_m = float(self.cum[-1])
        self.progress_m = 0.0

    def point_at(self, s_m: float) -> XY:
        """The path point at arc length ``s_m`` (clamped to the path)."""
        if self.points.shape[0] == 1 or s_m <= 0:
            return (float(self.points[0, 0]), float(self.points[0, 1]))
        if s_m >= self.length_m:
            return (float(self.points[-1, 0]), float(self.points[-1, 1]))
        k = int(np.searchsorted(self.cum, s_m, side="right") - 1)
        t = (s_m - self.cum[k]) / self.seg_len[k]
        p = self.points[k] + t * (self.points[k + 1] - self.points[k])
        return (float(p[0]), float(p[1]))

    def points_at(self, s_m: np.ndarray) -> np.ndarray:
        """:meth:`point_at` for many arc lengths at once, (M,) -> (M, 2): the same arithmetic, element by element."""
        s = np.asarray(s_m, dtype=np.float64).reshape(-1)
        out = np.empty((s.size, 2))
        if self.points.shape[0] == 1:
            out[:] = self.points[0]
            return out
        inside = (s > 0) & (s < self.length_m)
        out[s <= 0] = self.points[0]
        out[s >= self.length_m] = self.points[-1]
        si = s[inside]
        k = np.searchsorted(self.cum, si, side="right") - 1
        t = (si - self.cum[k]) / self.seg_len[k]
        out[inside] = self.points[k] + t[:, None] * (self.points[k + 1] - self.points[k])
        return out

    def project(self, xy: np.ndarray, s_min: float = -np.inf, s_max: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """``(s, d)``: arc length of the nearest path point and the distance to it, for points (M, 2).

        Only the part of the path with arc length in ``[s_min, s_max]`` is considered.
        """
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.points.shape[0] == 1:
            d = np.hypot(q[:, 0] - self.points[0, 0], q[:, 1] - self.points[0, 1])
            return np.zeros(q.shape[0]), d
        a = self.points[:-1]
        ab = self.points[1:] - a
        t = ((q[:, None, 0] - a[None, :, 0]) * ab[None, :, 0] + (q[:, None, 1] - a[None, :, 1]) * ab[None, :, 1]) / (
            self.seg_len[None, :] ** 2
        )
        s = self.cum[None, :-1] + np.clip(t, 0.0, 1.0) * self.seg_len[None, :]
        s = np.clip(s, max(s_min, 0.0), min(s_max, self.length_m))
        # the point at arc length s on each segment (clamped into the allowed window)
        tt = np.clip((s - self.cum[None, :-1]) / self.seg_len[None, :], 0.0, 1.0)
        px = a[None, :, 0] + tt * ab[None, :, 0]
        py = a[None, :, 1] + tt * ab[None, :, 1]
        d = np.hypot(q[:, None, 0] - px, q[:, None, 1] - py)
        k = np.argmin(d, axis=1)
        rows = np.arange(q.shape[0])
        return s[rows, k], d[rows, k]


# -- the dynamic window ------------------------------------------------------------------


@dataclass(frozen=True)
class Rollouts:
    """All sampled velocities of one DWA step and what became of them (for tests and display).

    ``v_mps``/``w_radps`` (K,), ``admissible`` (K,) bool, ``score`` (K,) (−inf when not
    admissible), ``free_m`` (K,) free arc length before contact, ``points`` (K, S, 2) the
    rollout positions in the robot frame. An arc the coarse-to-fine search never tried
    (:meth:`DynamicWindowPlanner.plan_steps`) is not admissible, its score −inf, its free
    length and points NaN.
    """

    v_mps: np.ndarray
    w_radps: np.ndarray
    admissible: np.ndarray
    score: np.ndarray
    free_m: np.ndarray
    points: np.ndarray


@dataclass(frozen=True)
class DwaChoice:
    """The chosen velocity, or a stop when nothing is admissible (``blocked``)."""

    v_mps: float
    w_radps: float
    blocked: bool
    rollouts: Rollouts


class DynamicWindowPlanner:
    """One DWA step: sample the window, reject inadmissible arcs, score the rest.

    Example::

        dwa = DynamicWindowPlanner()
        choice = dwa.plan(pose, (v_now, w_now), costmap, PathTrack(waypoints))
        choice.v_mps, choice.w_radps

    Limits: ``max_speed_mps`` / ``min_speed_mps`` (negative allows reversing; default
    forward only), ``max_yaw_rate_radps``, ``max_accel_mps2``, ``max_yaw_accel_radps2``,
    ``brake_decel_mps2`` (deceleration assumed for the stopping distance). Timing:
    ``window_s`` the interval the dynamic window spans (the planner period),
    ``latency_s`` the time travelled at the chosen speed before braking can start: the
    planner period (the next chance to choose a stop) plus the actuation latency;
    ``horizon_s`` the rollout length, ``step_m`` the largest spacing of rollout points.
    Safety: ``safety_margin_m`` added to the footprint for contact
    (at least ``step_m / 2``: clearance changes no faster than position, so between two
    rollout points it cannot dip more than half their spacing below theirs),
    ``stop_margin_m`` extra free distance beyond the stopping distance. Sampling:
    ``v_samples`` × ``w_samples`` velocities, searched coarse to fine (``coarse_step``:
    see :meth:`plan_steps`; 1 rolls out and scores every one). Scoring weights ``w_progress``,
    ``w_path``, ``w_heading``, ``w_clearance``, ``w_speed``; ``lookahead_m`` where the
    heading carrot sits ahead on the path, ``clearance_cap_m`` the clearance beyond which
    more is not better, ``path_scale_m`` the path distance that costs one unit.
    """

    def __init__(
        self,
        max_speed_mps: float = _DRIVE.max_speed_mps,
        min_speed_mps: float = 0.0,
        max_yaw_rate_radps: float = _DRIVE.max_yaw_rate_radps,
        max_accel_mps2: float = _DRIVE.max_accel_mps2,
        max_yaw_accel_radps2: float = _DRIVE.max_yaw_accel_radps2,
        brake_decel_mps2: float = _CONTROL.brake_decel_mps2,
        footprint_radius_m: float = _ROBOT.footprint_radius_m,
        clearance_m: float = _ROBOT.clearance_m,
        window_s: float = 0.2,
        latency_s: float = 0.25,
        horizon_s: float = _PLANNER.horizon_s,
        step_m: float = 0.01,
        safety_margin_m: float = 0.01,
        stop_margin_m: float = _CONTROL.stop_margin_m,
        v_samples: int = 7,
        w_samples: int = 15,
        w_progress: float = 1.0,
        w_path: float = 0.4,
        w_heading: float = 0.4,
        w_clearance: float = 0.3,
        w_speed: float = 0.2,
        lookahead_m: float = 0.25,
        clearance_cap_m: float = 0.03,
        path_scale_m: float = 0.15,
        coarse_step: int = 2,
    ) -> None:
        if max_speed_mps <= 0 or max_yaw_rate_radps <= 0:
            raise ValueError(f"speed limits must be positive, got {max_speed_mps} m/s, {max_yaw_rate_radps} rad/s")
        if max_accel_mps2 <= 0 or max_yaw_accel_radps2 <= 0 or brake_decel_mps2 <= 0:
            raise ValueError("acceleration and deceleration limits must be positive")
        if safety_margin_m < 0.5 * step_m:
            raise ValueError(
                f"safety_margin_m ({safety_margin_m} m) must be at least half of step_m ({step_m} m), "
                "or a rollout could pass an obstacle between two of its points"
            )
        if v_samples < 2 or w_samples < 3:
            raise ValueError(f"need at least 2 speed and 3 turn-rate samples, got {v_samples}, {w_samples}")
        if coarse_step < 1:
            raise ValueError(f"coarse_step must be 1 (every sample) or more, got {coarse_step}")
        self.max_speed_mps = float(max_speed_mps)
        self.min_speed_mps = float(min_speed_mps)
        self.max_yaw_rate_radps = float(max_yaw_rate_radps)
        self.max_accel_mps2 = float(max_accel_mps2)
        self.max_yaw_accel_radps2 = float(max_yaw_accel_radps2)
        self.brake_decel_mps2 = float(brake_decel_mps2)
        self.footprint_radius_m = float(footprint_radius_m)
        self.clearance_m = float(clearance_m)
        self.window_s = float(window_s)
        self.latency_s = float(latency_s)
        self.horizon_s = float(horizon_s)
        self.step_m = float(step_m)
        self.safety_margin_m = float(safety_margin_m)
        self.stop_margin_m = float(stop_margin_m)
        self.v_samples = int(v_samples)
        self.w_samples = int(w_samples)
        self.weights = (float(w_progress), float(w_path), float(w_heading), float(w_clearance), float(w_speed))
        self.lookahead_m = float(lookahead_m)
        self.clearance_cap_m = float(clearance_cap_m)
        self.path_scale_m = float(path_scale_m)
        self.coarse_step = int(coarse_step)

    @property
    def contact_m(self) -> float:
        """Centre-to-obstacle distance that counts as contact: footprint plus safety margin."""
        return self.footprint_radius_m + self.safety_margin_m

    def stopping_distance_m(self, v_mps: float | np.ndarray) -> float | np.ndarray:
        """Distance covered after choosing ``v``: latency at ``v``, then braking, plus the margin."""
        v = np.abs(v_mps)
        return v * self.latency_s + v * v / (2.0 * self.brake_decel_mps2) + self.stop_margin_m * (v > 1e-6)

    def window(
        self, v_now_mps: float, w_now_radps: float, v_cap_mps: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sampled ``(v, w)`` pairs (K,) of the dynamic window around the current velocity.

        The window holds the velocities reachable within ``window_s`` and inside the
        limits (and below ``v_cap_mps``, the goal-braking cap). Zero speed and zero turn
        rate are always included when inside it, and so is the best stopping command.
        """
        v_hi = min(self.max_speed_mps, v_now_mps + self.max_accel_mps2 * self.window_s)
        if v_cap_mps is not None:
            v_hi = min(v_hi, max(v_cap_mps, 0.0))
        v_lo = max(self.min_speed_mps, v_now_mps - self.brake_decel_mps2 * self.window_s)
        v_lo = min(v_lo, v_hi)
        w_hi = min(self.max_yaw_rate_radps, w_now_radps + self.max_yaw_accel_radps2 * self.window_s)
        w_lo = max(-self.max_yaw_rate_radps, w_now_radps - self.max_yaw_accel_radps2 * self.window_s)
        if w_lo > w_hi:  # only when the current rate exceeds the limit: come back towards it
            w_lo = w_hi = max(-self.max_yaw_rate_radps, min(self.max_yaw_rate_radps, w_now_radps))
        vs = np.linspace(v_lo, v_hi, self.v_samples)
        ws = np.linspace(w_lo, w_hi, self.w_samples)
        if v_lo < 0.0 < v_hi:
            vs = np.union1d(vs, [0.0])
        if w_lo < 0.0 < w_hi:
            ws = np.union1d(ws, [0.0])
        vv, ww = np.meshgrid(np.unique(vs), np.unique(ws), indexing="ij")
        return vv.reshape(-1), ww.reshape(-1)

    def _coarse_samples(self, v: np.ndarray, w: np.ndarray, velocity: tuple[float, float]) -> np.ndarray:
        """Indices into the window's ``(v, w)`` grid (:meth:`window`'s order) of the coarse search.

        Every ``coarse_step``-th speed and turn rate, the window's edges (full braking,
        the sharpest turns), zero speed and zero turn rate where the window holds them,
        and the sample nearest the current ``velocity`` (the last step's choice, as the
        wheels carried it out: where the best arc usually is again).
        """
        n_w = int(np.count_nonzero(v == v[0]))  # the grid is speed-major: the first speed's row
        n_v = v.size // n_w
        step = self.coarse_step
        rows = set(range(0, n_v, step)) | {n_v - 1}
        cols = set(range(0, n_w, step)) | {n_w - 1}
        grid_v, grid_w = v.reshape(n_v, n_w)[:, 0], w.reshape(n_v, n_w)[0]
        rows |= set(np.flatnonzero(grid_v == 0.0).tolist())
        cols |= set(np.flatnonzero(grid_w == 0.0).tolist())
        now = int(np.argmin(np.abs(grid_v - velocity[0]))) * n_w + int(np.argmin(np.abs(grid_w - velocity[1])))
        return np.array(sorted({r * n_w + c for r in rows for c in cols} | {now}), dtype=np.intp)

    def _neighbours(self, best: int, shape: tuple[int, int]) -> np.ndarray:
        """The grid indices around sample ``best`` (its 8 neighbours of the fine grid, inside it)."""
        n_v, n_w = shape
        r, c = divmod(best, n_w)
        near = [
            (r + dr) * n_w + (c + dc)
            for dr in (-1, 0, 1)
            for dc in (-1, 0, 1)
            if 0 <= r + dr < n_v and 0 <= c + dc < n_w
        ]
        return np.array(near, dtype=np.intp)

    def _clearance_until_contact(
        self, pts: np.ndarray, costmap: LocalCostmap, start_clear_m: float | None = None
    ) -> Generator[None, None, tuple[np.ndarray, float]]:
        """Clearance (K, S) of the rollout points up to each rollout's first contact, and the contact limit.

        A rollout's points after its first contact are never scored (its objectives stop
        just before it), so they are left at inf and not queried: the points are asked in
        slices of time steps, each slice only for the rollouts still free, and the result
        is the same as querying all of them. In 1 ft corridors most turning rollouts meet
        a wall early, so this asks far fewer than all the points. It yields after about
        ``CLEARANCE_BLOCK`` queried points. The limit is the contact distance, or a hair
        less than the start's clearance when the robot is already that close (map noise,
        a bump): it must not get any closer. ``start_clear_m`` is point 0's clearance when
        the caller asked it already (:meth:`start_clearance_m`).
        """
        k, s_count, _ = pts.shape
        bound_m = self.clearance_cap_m + self.contact_m
        clear = np.full((k, s_count), np.inf)
        if start_clear_m is None:
            start_clear_m = self.start_clearance_m(pts[0, 0], costmap)
        clear[:, 0] = start_clear_m  # point 0: the robot
        limit = min(self.contact_m, float(clear[0, 0]) - 1e-4)
        # a rollout that stays where the robot is (turning in place, v = 0) has every point at
        # point 0: its clearance is the start's all along, no need to ask again
        standing = (pts[:, 1:] == pts[:, :1]).all(axis=(1, 2))
        clear[standing] = clear[0, 0]
        free = np.flatnonzero(~standing)  # rollouts not yet in contact (the limit lies below the start's clearance)
        first = 1
        since_yield = 0
        while first < s_count and free.size:
            cols = max(1, CLEARANCE_BLOCK // free.size)
            last = min(s_count, first + cols)
            block = pts[free, first:last].reshape(-1, 2)
            clear[free, first:last] = costmap.clearance_m(block, upper_bound_m=bound_m).reshape(free.size, -1)
            free = free[(clear[free, first:last] >= limit).all(axis=1)]
            first = last
            since_yield += block.shape[0]
            if since_yield >= CLEARANCE_BLOCK and first < s_count and free.size:
                since_yield = 0
                yield
        return clear, limit

    def start_clearance_m(self, robot_xy: np.ndarray, costmap: LocalCostmap) -> float:
        """The clearance of the rollouts' point 0 (the robot), as :meth:`_clearance_until_contact` asks it."""
        bound_m = self.clearance_cap_m + self.contact_m
        return float(costmap.clearance_m(np.asarray(robot_xy)[None, :], upper_bound_m=bound_m)[0])

    def _free_beyond_the_rollout(
        self,
        pts: np.ndarray,
        v_mps: np.ndarray,
        never_hit: np.ndarray,
        need_m: np.ndarray,
        free_m: np.ndarray,
        costmap: LocalCostmap,
        limit_m: float,
    ) -> np.ndarray:
        """``free_m`` with the slow rollouts that end before their stopping distance measured on.

        A rollout spans ``horizon_s`` of travel; at a crawl that is shorter than the stop
        margin the safety layer keeps ahead, so a wall just past its end would go unseen and
        the arc be called admissible although the emergency stop refuses it. Such a rollout
        is free for its length plus its end point's clearance beyond the contact limit: the
        arc, continued, stays within its own length of the end point.
        """
        arc_m = np.abs(v_mps) * self.horizon_s
        short = np.flatnonzero(never_hit & (arc_m < need_m) & (np.abs(v_mps) > 1e-6))
        if short.size == 0:
            return free_m
        reach_m = float(np.max(need_m[short] - arc_m[short])) + limit_m
        end_clear = costmap.clearance_m(pts[short, -1], upper_bound_m=reach_m)
        out = free_m.copy()
        out[short] = arc_m[short] + (end_clear - limit_m)  # inf stays inf: free beyond the need
        return out

    def rollout(self, v_mps: np.ndarray, w_radps: np.ndarray, top_speed_mps: float | None = None) -> np.ndarray:
        """Robot-frame positions (K, S, 2) along the arcs of constant ``(v, w)`` for ``horizon_s``.

        ``S`` is chosen so consecutive points are at most ``step_m`` apart at the top speed
        (of ``v_mps``, or ``top_speed_mps``: the window's, when rolling out part of it).
        Point 0 is the robot itself. Exact arcs: ``x = v/w sin(w t)``, ``y = v/w (1 − cos(w t))``.
        """
        if top_speed_mps is None:
            top_speed_mps = float(np.max(np.abs(v_mps), initial=0.0))
        reach = max(top_speed_mps, 1e-6) * self.horizon_s
        steps = max(2, math.ceil(reach / self.step_m))
        t = np.linspace(0.0, self.horizon_s, steps + 1)[None, :]
        v = np.asarray(v_mps, dtype=np.float64)[:, None]
        w = np.asarray(w_radps, dtype=np.float64)[:, None]
        straight = np.abs(w) < 1e-6
        w_safe = np.where(straight, 1.0, w)
        x = np.where(straight, v * t, v / w_safe * np.sin(w_safe * t))
        y = np.where(straight, 0.0, v / w_safe * (1.0 - np.cos(w_safe * t)))
        return np.stack((x, y), axis=-1)

    def plan_steps(
        self,
        pose: tuple[float, float, float],
        velocity: tuple[float, float],
        costmap: LocalCostmap,
        path: PathTrack,
        v_cap_mps: float | None = None,
    ) -> Generator[None, None, DwaChoice]:
        """:meth:`plan` in stages (:mod:`mazebot.steps`): it yields between blocks of clearance queries.

        The clearance of the rollout points is most of a DWA step (~2 900 points for the
        window's ~105 arcs: 3 ms on a quiet machine, 20 ms on a loaded one); asked
        ``CLEARANCE_BLOCK`` points at a time, the same per-point queries give the same
        result with the loop free in between.

        The window is searched coarse to fine: every ``coarse_step``-th speed and turn
        rate first (with the window's edges and zero speed and turn rate), then the fine
        grid's neighbours of the best arc so far, again around each new best, until the best
        has no neighbour left to try: a local maximum of the fine grid, found with about
        half the arcs. The score (progress, path distance, heading, speed; clearance the
        one that is not smooth) changes little between neighbouring arcs, which is what
        lets the coarse grid find the best one's neighbourhood. Each arc is judged alone,
        so one that is rolled out gets the same admissibility and score as in a full
        search; the arcs never tried are inadmissible in :class:`Rollouts` (score −inf,
        free length NaN). When no coarse arc is admissible every arc is tried, so
        ``blocked`` (the stuck timers' input) means what it did: no arc of the window
        is admissible.
        """
        v, w = self.window(velocity[0], velocity[1], v_cap_mps)
        top_speed_mps = float(np.max(np.abs(v)))
        k = v.size
        s_count = self.rollout(v[:1], w[:1], top_speed_mps).shape[1]
        pts = np.full((k, s_count, 2), np.nan)  # (K, S, 2), rolled out as arcs are tried
        admissible = np.zeros(k, dtype=bool)
        score = np.full(k, -np.inf)
        free_m = np.full(k, np.nan)
        tried = np.zeros(k, dtype=bool)

        start_clear_m = self.start_clearance_m(np.zeros(2), costmap)

        def judge(idx: np.ndarray) -> Generator[None, None, None]:
            idx = idx[~tried[idx]]
            if idx.size == 0:
                return
            tried[idx] = True
            pts[idx] = arcs = self.rollout(v[idx], w[idx], top_speed_mps)
            ok, sc, free = yield from self._judge_arcs(pose, v[idx], w[idx], arcs, costmap, path, start_clear_m)
            admissible[idx], score[idx], free_m[idx] = ok, sc, free

        if self.coarse_step > 1:
            yield from judge(self._coarse_samples(v, w, velocity))
        if self.coarse_step == 1 or not admissible.any():
            yield from judge(np.arange(k))
        n_w = int(np.count_nonzero(v == v[0]))
        shape = (k // n_w, n_w)
        while admissible.any():
            best = int(np.argmax(score))
            near = self._neighbours(best, shape)
            if tried[near].all():
                break
            yield from judge(near)

        rollouts = Rollouts(v, w, admissible, score, free_m, pts)
        if not admissible.any():
            return DwaChoice(0.0, 0.0, True, rollouts)
        best = int(np.argmax(score))
        return DwaChoice(float(v[best]), float(w[best]), False, rollouts)

    def _judge_arcs(
        self,
        pose: tuple[float, float, float],
        v: np.ndarray,
        w: np.ndarray,
        pts: np.ndarray,
        costmap: LocalCostmap,
        path: PathTrack,
        start_clear_m: float,
    ) -> Generator[None, None, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``(admissible, score, free_m)`` (K,) of the arcs ``(v, w)`` whose rollout points are ``pts`` (K, S, 2).

        Each arc's figures depend on that arc alone (and the robot's start, point 0).
        """
        k, s_count, _ = pts.shape
        step_len = np.abs(v) * self.horizon_s / (s_count - 1)  # (K,)

        # 1. Admissibility (Fox et al. 1997, section 4.2): free arc length before contact.
        clear, limit = yield from self._clearance_until_contact(pts, costmap, start_clear_m)
        start_clear = float(clear[0, 0])
        hit = clear < limit
        first_hit = np.where(hit.any(axis=1), np.argmax(hit, axis=1), s_count)
        free_m = np.where(first_hit >= s_count, np.inf, np.maximum(first_hit - 1, 0) * step_len)
        need_m = np.asarray(self.stopping_distance_m(v))
        free_m = self._free_beyond_the_rollout(pts, v, first_hit >= s_count, need_m, free_m, costmap, limit)
        admissible = free_m >= need_m
        turning_in_place = np.abs(v) < 1e-6
        admissible |= turning_in_place & (start_clear >= limit)  # a round body turns freely

        # 2. Objectives, evaluated up to the end of the rollout (or just before contact).
        last = np.minimum(first_hit - 1, s_count - 1).clip(min=0)
        end = pts[np.arange(k), last]  # (K, 2) robot frame
        heading_end = w * last * (self.horizon_s / (s_count - 1))
        c, s_ = math.cos(pose[2]), math.sin(pose[2])
        end_map = np.column_stack((pose[0] + c * end[:, 0] - s_ * end[:, 1], pose[1] + s_ * end[:, 0] + c * end[:, 1]))
        s0 = path.progress_m
        s_end, d_end = path.project(end_map, s0 - 0.05, s0 + self.max_speed_mps * self.horizon_s + 0.1)
        progress = (s_end - s0) / (self.max_speed_mps * self.horizon_s)
        carrot = path.points_at(s_end + self.lookahead_m)
        to_carrot = np.arctan2(carrot[:, 1] - end_map[:, 1], carrot[:, 0] - end_map[:, 0])
        near_carrot = np.hypot(carrot[:, 0] - end_map[:, 0], carrot[:, 1] - end_map[:, 1]) < 0.02
        heading_err = np.abs(np.remainder(to_carrot - (pose[2] + heading_end) + np.pi, 2 * np.pi) - np.pi) / np.pi
        heading_err[near_carrot] = 0.0
        valid = np.where(np.arange(s_count)[None, :] <= last[:, None], clear, np.inf)
        min_clear = np.min(valid, axis=1) - self.contact_m
        clearance = np.clip(min_clear / max(self.clearance_cap_m, 1e-6), 0.0, 1.0)
        speed = v / self.max_speed_mps
        wp, wd, wh, wc, wv = self.weights
        score = wp * progress - wd * d_end / self.path_scale_m - wh * heading_err + wc * clearance + wv * speed
        return admissible, np.where(admissible, score, -np.inf), free_m

    plan = all_at_once_method(
        plan_steps,
        """The best admissible velocity for the robot at map ``pose`` moving at ``velocity``.

        ``velocity`` is the measured ``(v_mps, w_radps)``; ``path`` the global path
        (map frame), whose :attr:`PathTrack.progress_m` is where the robot is along it.
        """,
    )


# -- the local planner ---------------------------------------------------------------------


class LocalStatus(enum.StrEnum):
    """What the local planner is doing."""

    IDLE = "idle"  # no path
    FOLLOWING = "following"  # DWA along the path
    ALIGNING = "aligning"  # turning in place towards the path
    RECOVERING = "recovering"  # rotate / back off after getting stuck
    REACHED = "reached"  # at the goal, stopped


@dataclass(frozen=True)
class MotionCommand:
    """A body velocity for the wheel controller, with the mode and planner status.

    ``give_up`` is True once recovery has failed ``max_recoveries`` times on this path:
    the caller should blacklist the goal (``Explorer.report_unreachable``) and re-plan.
    """

    v_mps: float
    w_radps: float
    mode: DriveMode
    status: LocalStatus
    give_up: bool = False
    choice: DwaChoice | None = field(default=None, repr=False)


#: A robot counts as free of where it had to be helped (recovered, or acted on by the stand-still
#: watch) once it is this far from there (metres): a cell of a 1 ft maze.
FREED_M = 0.3


class _Recovery(enum.Enum):
    ROTATE = "rotate"
    BACK_OFF = "back_off"


class LocalPlanner:
    """Follows a global path: DWA, in-place turns, goal stop, and recovery when stuck.

    Example::

        local = LocalPlanner(DynamicWindowPlanner())
        local.set_path(goal.waypoints_m)
        cmd = local.step(pose, (v_now, w_now), scan_xy, map_xy, map_point_radius_m, now_s)
        wheels.update(cmd.v_mps, cmd.w_radps, cmd.mode, measured, dt)

    ``goal_tolerance_m`` how close counts as arrived; ``align_enter_rad`` the heading error
    beyond which the robot first turns in place, towards the path point
    ``align_lookahead_m`` ahead (at a corner waypoint: the next corridor), until
    :class:`HeadingAligner` reports the heading within its band (a turn that takes longer
    than ``align_timeout_s`` counts as stuck);
    ``stuck_timeout_s`` how long progress along the path may stay below
    ``stuck_progress_m`` (or the window stay blocked for ``blocked_timeout_s``) before
    recovery. Recovery turns in place, then drives ``escape_m`` straight (forwards or
    backwards, at ``escape_speed_mps``) along the direction that opens up the most space
    without closing in on anything (see :meth:`_escape_move`), then re-plans;
    ``max_recoveries`` recoveries on one path make it give up. With ``recoveries_per_place`` they
    count on one *place* instead, whatever the paths: the count starts again only once the robot
    is ``FREED_M`` from where its first recovery began (or at a give-up, whose recovery move is the
    first of the next count and runs on while the caller keeps the path). A way home re-planned
    every tick gives new waypoints each time, and a count per path never reached its limit there.
    """

    def __init__(
        self,
        dwa: DynamicWindowPlanner | None = None,
        aligner: HeadingAligner | None = None,
        goal_tolerance_m: float = 0.04,
        align_enter_rad: float = math.radians(70.0),
        align_lookahead_m: float = 0.1,
        align_timeout_s: float = 8.0,
        stuck_timeout_s: float = _PLANNER.stuck_timeout_s,
        stuck_progress_m: float = 0.03,
        blocked_timeout_s: float = 0.6,
        escape_m: float = 0.06,
        escape_speed_mps: float = 0.06,
        max_recoveries: int = _PLANNER.max_recoveries,
        recoveries_per_place: bool = _PLANNER.close_passages,
    ) -> None:
        self.dwa = dwa or DynamicWindowPlanner()
        # the turn is re-decided once per planner period: predict the heading that far ahead
        self.aligner = aligner or HeadingAligner(
            max_yaw_rate_radps=self.dwa.max_yaw_rate_radps, latency_s=self.dwa.window_s
        )
        self.goal_tolerance_m = float(goal_tolerance_m)
        self.align_enter_rad = float(align_enter_rad)
        self.align_lookahead_m = float(align_lookahead_m)
        self.align_timeout_s = float(align_timeout_s)
        self.stuck_timeout_s = float(stuck_timeout_s)
        self.stuck_progress_m = float(stuck_progress_m)
        self.blocked_timeout_s = float(blocked_timeout_s)
        self.escape_m = float(escape_m)
        self.escape_speed_mps = float(escape_speed_mps)
        self.max_recoveries = int(max_recoveries)
        self.recoveries_per_place = bool(recoveries_per_place)
        self._recoveries_at: XY | None = None  # where the first recovery of the count began (per place)
        self.path: PathTrack | None = None
        self.status = LocalStatus.IDLE
        self.recoveries = 0
        self._align_target: float | None = None
        self._align_since = 0.0
        self._progress_mark: tuple[float, float] | None = None  # (progress_m, time_s)
        self._blocked_since: float | None = None
        self._recovery: _Recovery | None = None
        self._recovery_heading: float | None = None
        self._backoff_start: XY | None = None
        self._backoff_since = 0.0
        self._escape_direction = -1.0

    def set_path(self, waypoints_m: Sequence[XY]) -> None:
        """Follow a new path; the same path again (same waypoints) keeps the progress and timers."""
        new = PathTrack(waypoints_m)
        same = self.path is not None and new.points.shape == self.path.points.shape
        if same and np.allclose(new.points, self.path.points, atol=1e-3):  # type: ignore[union-attr]
            return
        self.path = new
        if not self.recoveries_per_place:
            self.recoveries = 0
        self._progress_mark = None
        self._blocked_since = None
        self._recovery = None
        self._align_target = None
        self.status = LocalStatus.FOLLOWING

    def clear(self) -> None:
        """No path: stop."""
        self.path = None
        self.status = LocalStatus.IDLE
        self._recovery = None
        self._align_target = None
        self.aligner.reset()

    def step_steps(
        self,
        pose: tuple[float, float, float],
        velocity: tuple[float, float],
        scan_points: np.ndarray,
        map_points: np.ndarray | None,
        map_point_radius_m: float,
        now_s: float,
        wall_points: np.ndarray | None = None,
    ) -> Generator[None, None, MotionCommand]:
        """The command for this tick, in stages (:mod:`mazebot.steps`; the DWA's are the long ones).

        All points are robot-frame (N, 2) metres: ``scan_points`` the latest returns,
        ``map_points`` occupied map cells (each counted as a disc of
        ``map_point_radius_m``), ``wall_points`` known wall surfaces, e.g.
        :meth:`MazeGraph.wall_points_m <mazebot.planner.maze_graph.MazeGraph.wall_points_m>`
        moved with :func:`to_robot_frame` (the posts a map misses, closer than the lidar
        sees).
        """
        if wall_points is not None and len(wall_points):
            scan_points = np.concatenate(
                (np.asarray(scan_points).reshape(-1, 2), np.asarray(wall_points).reshape(-1, 2))
            )
        if self.path is None:
            self.status = LocalStatus.IDLE
            return MotionCommand(0.0, 0.0, DriveMode.STOP, self.status)
        at = self._recoveries_at
        if at is not None and math.dist(at, (pose[0], pose[1])) >= FREED_M:  # free of that place: count afresh
            self.recoveries, self._recoveries_at = 0, None
        path = self.path
        xy = np.array([[pose[0], pose[1]]])
        s, _ = path.project(xy, path.progress_m - 0.1, path.progress_m + 0.5)
        path.progress_m = max(path.progress_m, float(s[0]))
        goal = path.point_at(path.length_m)
        to_goal = math.dist((pose[0], pose[1]), goal)
        if to_goal <= self.goal_tolerance_m and (path.length_m - path.progress_m) <= self.goal_tolerance_m + 0.05:
            self.status = LocalStatus.REACHED
            self._recovery = None
            return MotionCommand(0.0, 0.0, DriveMode.STOP, self.status)

        costmap = LocalCostmap(
            scan_points, map_points, map_point_radius_m, self.dwa.footprint_radius_m, self.dwa.clearance_m
        )
        if self._recovery is not None:
            return self._recover(pose, velocity, costmap, now_s)

        carrot = path.point_at(path.progress_m + self.align_lookahead_m)
        if math.dist(carrot, (pose[0], pose[1])) < 0.02:
            carrot = goal
        bearing = math.atan2(carrot[1] - pose[1], carrot[0] - pose[0])
        error = math.remainder(bearing - pose[2], math.tau)
        if self.status is LocalStatus.ALIGNING or abs(error) > self.align_enter_rad:
            if self.status is not LocalStatus.ALIGNING or self._align_target is None:
                self._align_target = bearing
                self._align_since = now_s
                self.aligner.reset()
            w, done = self.aligner.command(pose[2], self._align_target, velocity[1])
            if not done and now_s - self._align_since > self.align_timeout_s:  # wedged: cannot even turn
                self._align_target = None
                self.status = LocalStatus.FOLLOWING
                return self._begin_recovery(pose, velocity, costmap, now_s, None)
            if not done:
                self.status = LocalStatus.ALIGNING
                self._progress_mark = (path.progress_m, now_s)  # turning is progress
                return MotionCommand(0.0, w, DriveMode.TURN, self.status)
            self._align_target = None
        self.status = LocalStatus.FOLLOWING

        # goal braking: never faster than what stops at the end of the path
        remaining = max(0.0, path.length_m - path.progress_m, to_goal) - 0.5 * self.goal_tolerance_m
        v_cap = math.sqrt(2.0 * self.dwa.brake_decel_mps2 * max(remaining, 0.0))
        v_cap = max(v_cap, 0.03)  # keep creeping: the last centimetres need some speed
        yield
        choice = yield from self.dwa.plan_steps(pose, velocity, costmap, path, v_cap)
        if self._stuck(choice, path, now_s):
            return self._begin_recovery(pose, velocity, costmap, now_s, choice)
        mode = DriveMode.DRIVE if not choice.blocked else DriveMode.STOP
        return MotionCommand(choice.v_mps, choice.w_radps, mode, self.status, choice=choice)

    step = all_at_once_method(step_steps, "The command for this tick.")

    # -- stuck detection and recovery ----------------------------------------------------

    def _stuck(self, choice: DwaChoice, path: PathTrack, now_s: float) -> bool:
        if choice.blocked:
            self._blocked_since = now_s if self._blocked_since is None else self._blocked_since
        else:
            self._blocked_since = None
        if self._progress_mark is None or path.progress_m >= self._progress_mark[0] + self.stuck_progress_m:
            self._progress_mark = (path.progress_m, now_s)
        blocked = self._blocked_since is not None and now_s - self._blocked_since >= self.blocked_timeout_s
        stalled = now_s - self._progress_mark[1] >= self.stuck_timeout_s
        return blocked or stalled

    def _begin_recovery(
        self,
        pose: tuple[float, float, float],
        velocity: tuple[float, float],
        costmap: LocalCostmap,
        now_s: float,
        choice: DwaChoice | None,
    ) -> MotionCommand:
        self.recoveries += 1
        if self.recoveries_per_place and self._recoveries_at is None:
            self._recoveries_at = (pose[0], pose[1])
        self._blocked_since = None
        self._progress_mark = None
        self.status = LocalStatus.RECOVERING
        give_up = self.recoveries > self.max_recoveries
        if give_up and not self.recoveries_per_place:
            self._recovery = None
            return MotionCommand(0.0, 0.0, DriveMode.STOP, self.status, give_up=True, choice=choice)
        if give_up:  # counted per place: said, and this recovery is the first of the next count
            self.recoveries, self._recoveries_at = 1, (pose[0], pose[1])
        turn, direction = self._escape_move(pose, costmap)
        self._recovery = _Recovery.ROTATE
        self._recovery_heading = pose[2] + turn
        self._escape_direction = direction
        self.aligner.reset()
        command = self._recover(pose, velocity, costmap, now_s)
        # the caller re-plans on a give-up; a path it keeps (the same waypoints) goes on with the recovery
        return replace(command, give_up=True, choice=choice) if give_up else command

    def _escape_move(self, pose: tuple[float, float, float], costmap: LocalCostmap) -> tuple[float, float]:
        """The short straight move that best opens up space: ``(turn_rad, +1 forward or -1 back)``.

        Every direction is probed for ``escape_m``; a move qualifies when the clearance
        along it never drops below where it starts (or the contact distance, if lower),
        and the one ending farthest from obstacles wins, nudged towards the path. It is
        driven forwards or backwards, whichever needs the smaller turn, so a robot that
        drifted too close to a post backs straight out instead of turning on the spot.
        """
        angles = np.linspace(-math.pi, math.pi, 36, endpoint=False)
        steps = np.linspace(0.0, self.escape_m, max(2, math.ceil(self.escape_m / 0.01) + 1))
        probe = steps[None, :, None] * np.stack((np.cos(angles), np.sin(angles)), axis=-1)[:, None, :]
        clear = costmap.clearance_m(probe.reshape(-1, 2)).reshape(angles.size, steps.size)
        floor = min(self.dwa.contact_m, float(clear[0, 0]) - 1e-3)
        ok = clear.min(axis=1) >= floor
        assert self.path is not None
        carrot = self.path.point_at(self.path.progress_m + self.dwa.lookahead_m)
        bearing = math.atan2(carrot[1] - pose[1], carrot[0] - pose[0]) - pose[2]
        gain = np.minimum(clear[:, -1], self.dwa.contact_m + self.dwa.clearance_cap_m)
        score = np.where(ok, gain + 0.01 * np.cos(angles - bearing), -np.inf)
        best = float(angles[int(np.argmax(score))]) if ok.any() else bearing
        if abs(best) <= math.pi / 2:
            return best, 1.0
        return math.remainder(best + math.pi, math.tau), -1.0

    def _recover(
        self, pose: tuple[float, float, float], velocity: tuple[float, float], costmap: LocalCostmap, now_s: float
    ) -> MotionCommand:
        self.status = LocalStatus.RECOVERING
        if self._recovery is _Recovery.ROTATE:
            assert self._recovery_heading is not None
            w, done = self.aligner.command(pose[2], self._recovery_heading, velocity[1])
            if not done:
                return MotionCommand(0.0, w, DriveMode.RECOVER, self.status)
            self._recovery = _Recovery.BACK_OFF
            self._backoff_start = (pose[0], pose[1])
            self._backoff_since = now_s
        if self._recovery is _Recovery.BACK_OFF:
            assert self._backoff_start is not None
            moved = math.dist(self._backoff_start, (pose[0], pose[1]))
            # the rest of the move (2 cm past its end), and never less than its stopping distance with the
            # emergency stop's margin (as for the DWA's arcs), every step_m: judged only 2 cm ahead near
            # its end, the move ran into the guard's stop when a wall stood 3-5 cm past it
            stop_m = float(self.dwa.stopping_distance_m(self.escape_speed_mps))
            reach_m = max(max(self.escape_m - moved, 0.0) + 0.02, stop_m)
            n = max(2, math.ceil(reach_m / self.dwa.step_m) + 1)
            ahead = self._escape_direction * np.linspace(0.0, reach_m, n)
            clear = costmap.clearance_m(np.column_stack((ahead, np.zeros(n))))
            still_opening = bool(np.all(clear >= min(self.dwa.contact_m, float(clear[0]) - 1e-3)))
            # a slipping or blocked robot may never cover the distance: give it twice the time it needs
            in_time = now_s - self._backoff_since <= 2.0 * self.escape_m / self.escape_speed_mps + 0.5
            if moved < self.escape_m and in_time and still_opening:
                return MotionCommand(
                    self._escape_direction * self.escape_speed_mps, 0.0, DriveMode.RECOVER, self.status
                )
        # done: back to following; the caller re-plans from here
        self._recovery = None
        self._progress_mark = (self.path.progress_m if self.path else 0.0, now_s)
        self.status = LocalStatus.FOLLOWING
        return MotionCommand(0.0, 0.0, DriveMode.STOP, self.status)
