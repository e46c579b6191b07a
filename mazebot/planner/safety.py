"""The safety layer: stops the wheels whatever the planner says.

The planner can be wrong (a map error, a bug, a stale pose); the safety layer uses only
the raw lidar returns, the command about to be applied and the clock, and runs in the
control loop so it acts within one control period. It is deliberately simple enough to
check by hand:

- :class:`CollisionGuard`: an **emergency stop** when any valid lidar return (the latest
  revolution's, and those the planner's :class:`BlindZoneMemory` keeps from inside the
  lidar's minimum range) lies in the region the robot will sweep before it can stop: within the
  footprint radius (plus a side margin) of the arc it is about to drive, forwards or in reverse,
  over the stopping distance ``|v| · latency + v² / (2 a)`` plus a front margin, and closer
  than the return is now. The whole sweep counts, beside the robot too: a tight arc carries
  the body sideways, and a robot reversing on one swept its side into a corridor wall with the
  guard silent when it looked only behind (a 16×16 contest maze under a Pi 4's CPU share).
  The margin is kept ahead, not beside: driving along a wall a few centimetres away is
  normal in a 1 ft maze, driving at one is not. Turning in place is always allowed (a
  round body sweeps nothing new) and so is any motion that takes the footprint no closer to
  each return, so the planner's recovery (rotate, back off) can still get the robot out.
- :class:`ControlWatchdog`: a **control deadline**: if the control loop has not ticked
  within ``deadline_s`` (an event loop blocked by heavy work), the next tick stops. This
  one is wall time on purpose: it measures how long the motors ran unsupervised.
- :class:`CommandGate`: a **stale-command stop**: a planner command older than its
  time-to-live is replaced by a stop.
- :class:`SafetyLayer` chains them (plus a lidar timeout) and says why it stopped. Its
  command and lidar ages count **control ticks run** since the command or the revolution
  was first seen, not seconds: a loop that could not run for 0.3 s (a slow core, a
  collector pause) aged neither, and its late tick is the deadline's business; a planner
  or a lidar that stopped while the loop runs is still caught within that many ticks.

Note on the lidar's minimum range: the RPLidar A1 reports nothing closer than 0.15 m
(``min_range_m``), which is more than the 0.09 m footprint; an obstacle can only be seen
while it is still that far away, which is why the guarded zone reaches a stopping
distance ahead and not only the footprint. At 0.27 m/s the guarded zone reaches 0.21 m
ahead of the centre, so a wall is in a revolution's returns only while it lies 0.15–0.21 m
ahead, a band the robot crosses in a fraction of a revolution: the guard therefore also
checks the returns the planner remembers from inside that range (a hand-built 8×8 maze:
the cheap robot drove into a wall it had turned beside, at 0.27 m/s, the guard silent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

import numpy as np

from mazebot.config import ControlConfig, RobotConfig
from mazebot.geometry import compose, inverse, transform_points

# the defaults below are the config's, each written once in mazebot.config
_CONTROL = ControlConfig()
_ROBOT = RobotConfig()

T = TypeVar("T")


@dataclass(frozen=True)
class SafetyVerdict:
    """Whether to stop now, and why (one human sentence; empty when all is well)."""

    stop: bool
    reason: str = ""
    nearest_m: float = math.inf  # distance of the closest offending return from the robot centre


OK = SafetyVerdict(False)


def reframe_points(
    points_then: np.ndarray, pose_then: tuple[float, float, float], pose_now: tuple[float, float, float]
) -> np.ndarray:
    """Robot-frame points (N, 2) seen at ``pose_then``, expressed in the robot frame at ``pose_now``.

    The lidar delivers a revolution every ~0.18 s and the guard runs at 20 Hz: between
    scans the robot moves up to a few centimetres towards what it saw, so the guard
    moves the last scan with the odometry (any frame works, as long as both poses are
    in it) instead of trusting stale ranges.
    """
    pts = np.asarray(points_then, dtype=np.float64).reshape(-1, 2)
    c0, s0 = math.cos(pose_then[2]), math.sin(pose_then[2])
    wx = pose_then[0] + c0 * pts[:, 0] - s0 * pts[:, 1]
    wy = pose_then[1] + s0 * pts[:, 0] + c0 * pts[:, 1]
    dx, dy = wx - pose_now[0], wy - pose_now[1]
    c1, s1 = math.cos(pose_now[2]), math.sin(pose_now[2])
    return np.column_stack((c1 * dx + s1 * dy, -s1 * dx + c1 * dy))


class PoseHistory(Protocol):
    """What :func:`deskewed_points_robot` reads of the odometry (``mazebot.slam.ekf.OdometryHistory``)."""

    def __len__(self) -> int: ...

    def at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def deskewed_points_robot(
    angle_rad: np.ndarray,
    range_m: np.ndarray,
    valid: np.ndarray,
    time_s: np.ndarray,
    history: PoseHistory | None,
    min_range_m: float,
    max_range_m: float,
    mount_xy_m: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """A revolution's valid returns (N, 2) in the robot frame at its last sample, each placed
    with the odometry pose at its own time ``time_s`` (without a history: as if the robot stood still).

    A revolution takes 0.18 s on an A1; a robot turning at 1.5 rad/s (the cheap robot's
    weak motor makes its heading swing that fast while it is told to drive straight) turns
    15° meanwhile, so a return from the revolution's start, placed as if seen from its
    end, lies 15° off: 5 cm sideways at 0.2 m, the difference between a wall ahead and
    free space beside it (a hand-built 8×8 maze: the end of a board 0.16 m ahead was shown
    at 0.95 m and the robot drove into it). SLAM de-skews its scans the same way
    (``mazebot.slam.preprocess``); the planner and the emergency stop take these points.
    Returns newer than the history's newest pose take that pose (the odometry runs at
    50 Hz: at most 20 ms of motion unaccounted for, while it catches up with the lidar).
    """
    a = np.asarray(angle_rad, dtype=np.float64).reshape(-1)
    r = np.asarray(range_m, dtype=np.float64).reshape(-1)
    ok = np.isfinite(r) & (r >= min_range_m) & (r <= max_range_m) & np.asarray(valid, dtype=bool).reshape(-1)
    lx = mount_xy_m[0] + r[ok] * np.cos(a[ok])
    ly = mount_xy_m[1] + r[ok] * np.sin(a[ok])
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    if history is None or len(history) == 0 or not ok.any():
        return np.column_stack((lx, ly))
    xs, ys, ths = history.at(np.concatenate((t[ok], t[-1:])))  # the samples' poses, then the end's
    xe, ye, the = xs[-1], ys[-1], ths[-1]
    c, s = math.cos(the), math.sin(the)
    dx, dy = xs[:-1] - xe, ys[:-1] - ye
    rx, ry, rth = c * dx + s * dy, -s * dx + c * dy, ths[:-1] - the  # each sample's pose in the end's frame
    cr, sr = np.cos(rth), np.sin(rth)
    return np.column_stack((rx + cr * lx - sr * ly, ry + sr * lx + cr * ly))


class BlindZoneMemory:
    """Lidar returns seen close by, kept while they lie inside the lidar's minimum range.

    Example::

        memory = BlindZoneMemory(min_range_m=0.15)
        memory.add_scan(points_robot, pose_at_scan, scan.end_time_s)   # once per revolution, odometry frame
        memory.fix(fix.revolution_end_s, fix.before, fix.after, fix.vouched)   # each of SLAM's fixes
        extra = memory.points_robot(pose_now)               # what the scan cannot show now

    The RPLidar A1 reports nothing closer than 0.15 m (datasheet), more than the 0.09 m
    footprint: a 2 cm table leg the robot stopped 12 cm from is in no scan at all, and a
    robot that turns there and drives off towards it has nothing in its latest scan to
    stop it (a hand-built 8×8 maze: contact 1 s after the turn, the leg gone from the map).
    So returns within ``reach_m`` of the lidar's minimum range are remembered (odometry
    frame), and a remembered return is dropped once a revolution's lidar stood farther
    than ``min_range_m + motion_margin_m`` from it: then that revolution could see it,
    and shows it again if it is still there. ``motion_margin_m`` covers the lidar's
    travel during one revolution (0.18 s at 0.3 m/s: 5 cm), since a return's beam may
    have swept past before the robot came that close.

    A return only the odometry placed is also dropped ``max_age_revolutions`` revolutions
    of motion after it was seen (40: 7 s of an A1 on the move): the odometry frame drifts,
    most of all in the cheap robot's turns in place (slip, backlash), and a robot stuck
    turning beside a wall otherwise gathers smeared copies of it that close in until
    nothing can move (a hand-built 6×6 maze: 40 recoveries in a row). A return SLAM placed
    (below) is not aged: its place is SLAM's pose of its revolution, matched against the
    map, whose error does not grow with the motion since (the odometry's does), so a robot
    that turns and edges beside a table leg for a minute keeps it for as long as no
    revolution could see it (a hand-built 8×8 maze: a 20 mm leg forgotten after 40
    revolutions of motion beside it, its map cell cleared by grazing rays, then driven
    into). Only revolutions over which the odometry moved (by ``still_m`` or turned by
    ``still_rad``) count: the frame does not drift while the wheels stand, and a robot that
    stood by a table leg for seconds must still know it is there when it turns towards it
    (a hand-built 8×8 maze: a leg in the blind zone while the robot stood and turned on the
    spot for 11 s, then driven into; its turns there still age what SLAM has not placed).
    Revolutions, not seconds, so a slow computer forgets after as much motion as a fast
    one. ``lidar_xy_m`` is the lidar's mount offset in the robot frame; one return is kept
    per ``voxel_m`` square, at most ``max_points`` of them.

    The odometry frame is only a frame while the odometry is right: a tyre that slips turns
    the odometry by degrees a revolution, and returns seen over those revolutions land
    beside where they were, smeared around the robot; at rest nothing ages them, and a robot
    that stopped between two posts found the way ahead closed by its own copies of them
    (the fault suite's slipping tyre: copies of a post 0.11-0.15 m away over 80 degrees of
    bearing, and the robot turning on the spot for 4-7 s until the stuck recovery backed it
    off). Forgetting everything whenever SLAM distrusts the odometry (it did, for a while)
    forgets a leg inside the minimum range too, and a healthy run distrusts it now and then
    (a disputed match at rest, a brief slip: 0-23 revolutions a run under a Pi 4's share,
    57-251 a run of the cheap robot on the hand-built mazes).
    So each revolution's returns are placed by **SLAM's own pose of that revolution**, as
    the scan matcher found it (:meth:`fix`, with SLAM's correction of the odometry frame,
    ``map_from_odom``, after its update of that revolution): until SLAM has taken the
    revolution in (a revolution or two later) they stand where the odometry put them; then
    SLAM's correction puts them where SLAM has the revolution, and from then on each
    correction keeps them in their place in the map (what the odometry drifted, the scan
    matches take out), so the odometry's errors do not carry into them. Returns of a
    revolution SLAM placed with nothing but the odometry it distrusted (held back, its scan
    match refused) or left out (it was behind, the revolution did not fit the map, the robot
    was lost) are dropped: nothing vouches for where they were seen. The memory's points stay
    in the odometry frame, so the control loop's guard reads them as before
    (:meth:`snapshot`); a loop closure, which moves the map around the robot's surroundings
    and not the odometry under them, leaves them alone.

    The previous revolution's near returns that the latest one could have seen are kept
    for that one revolution more: a thin thing (a 12 mm post standing alone, a board's
    end) is one to three samples of a revolution, and a dropout or the revolution's seam
    loses them (a hand-built 8×8 maze: a lone post 0.18–0.21 m ahead in no sample of the
    latest revolution, the robot turning into it).

    A remembered return deeper inside the robot's body (``body_radius_m``, the footprint)
    than one voxel cannot be where the memory has it: the body stands there. It is dropped
    with the revolution that finds it there. Such returns come from a pose SLAM vouched for
    that was wrong: a robot picked up and set down in the last milliseconds of a revolution
    has that revolution matched (most of it was seen before), its last samples, seen from
    the new place, placed from the old one; once SLAM finds the robot again they keep that
    place in the map, inside the body set down there, where no revolution can ever show
    the lidar past them (a 6×6 maze: 13 returns 0.05–0.07 m from the robot's centre, the
    nearest true wall 0.14 m from each; the local planner and the emergency stop refused
    every motion that came closer to one, and the robot stood for the rest of the run).
    A voxel of slack keeps a surface the body touches, its place a voxel off.
    """

    def __init__(
        self,
        min_range_m: float,
        reach_m: float = 0.1,
        motion_margin_m: float = 0.05,
        max_age_revolutions: int = 40,
        lidar_xy_m: tuple[float, float] = (0.0, 0.0),
        voxel_m: float = 0.01,
        max_points: int = 2000,
        still_m: float = 0.002,
        still_rad: float = 0.005,
        body_radius_m: float = 0.0,
    ) -> None:
        if min(min_range_m, reach_m, motion_margin_m, still_m, still_rad, body_radius_m) < 0:
            raise ValueError(f"need non-negative ranges, got {min_range_m}, {reach_m}, {motion_margin_m}, "
                             f"{still_m}, {still_rad}, {body_radius_m}")
        if voxel_m <= 0 or max_points < 1 or max_age_revolutions < 1:
            raise ValueError(f"need a positive voxel, age and point count, got {voxel_m}, {max_age_revolutions}, "
                             f"{max_points}")
        self.min_range_m = float(min_range_m)
        self.reach_m = float(reach_m)
        self.motion_margin_m = float(motion_margin_m)
        self.max_age_revolutions = int(max_age_revolutions)
        self.lidar_xy_m = (float(lidar_xy_m[0]), float(lidar_xy_m[1]))
        self.voxel_m = float(voxel_m)
        self.max_points = int(max_points)
        self.still_m = float(still_m)
        self.still_rad = float(still_rad)
        self.body_radius_m = float(body_radius_m)
        self.revolutions = 0  # revolutions over which the odometry moved: the returns' age
        self._last_pose: tuple[float, float, float] | None = None
        # each row: odometry frame x, y; the revolution it was seen in (the age's count); that
        # revolution's end time (what SLAM's fix names it by); 1 once SLAM placed it, else 0
        self._points = np.zeros((0, _COLUMNS))
        self._recent = np.zeros((0, _COLUMNS))  # the last revolution's own near returns (the scan shows them)
        self._previous = np.zeros((0, _COLUMNS))  # the one before's, which the last could have shown (once more)

    def __len__(self) -> int:
        return int(self._points.shape[0] + self._previous.shape[0])

    def clear(self) -> None:
        self._points = np.zeros((0, _COLUMNS))
        self._recent = np.zeros((0, _COLUMNS))
        self._previous = np.zeros((0, _COLUMNS))

    def add_scan(self, points_robot: np.ndarray, pose: tuple[float, float, float], time_s: float = math.nan) -> None:
        """One revolution's returns (robot frame, (N, 2)) seen from odometry ``pose``; ``time_s`` the
        revolution's end, by which SLAM's fix of it names it (:meth:`fix`; NaN: no fix will place them)."""
        if self._moved_since_last(pose):
            self.revolutions += 1
        lx, ly = transform_points(pose, self.lidar_xy_m)[0]
        old = np.concatenate((self._points, self._recent))
        outside = np.hypot(old[:, 0] - pose[0], old[:, 1] - pose[1]) >= self.body_radius_m - self.voxel_m
        unseen = np.hypot(old[:, 0] - lx, old[:, 1] - ly) < self.min_range_m + self.motion_margin_m
        unseen &= (old[:, 4] > 0) | (old[:, 2] > self.revolutions - self.max_age_revolutions)  # placed: no age
        self._previous = self._recent[~unseen[self._points.shape[0]:] & outside[self._points.shape[0]:]]
        kept = old[unseen & outside]
        if kept.shape[0]:  # one return per voxel: a robot standing beside a wall adds its returns every revolution
            kept = kept[np.argsort(-kept[:, 4], kind="stable")]  # a placed one before one SLAM may still drop
            _, first = np.unique(np.floor(kept[:, :2] / self.voxel_m).astype(np.int64), axis=0, return_index=True)
            kept = kept[np.sort(first)]
        self._points = kept[-self.max_points:]
        pts = np.asarray(points_robot, dtype=np.float64).reshape(-1, 2)
        rx, ry = pts[:, 0] - self.lidar_xy_m[0], pts[:, 1] - self.lidar_xy_m[1]
        near = pts[np.hypot(rx, ry) < self.min_range_m + self.reach_m]
        self._recent = np.column_stack((transform_points(pose, near), np.full(near.shape[0], float(self.revolutions)),
                                        np.full(near.shape[0], float(time_s)), np.zeros(near.shape[0])))

    def fix(
        self,
        revolution_end_s: float | None,
        before: tuple[float, float, float],
        after: tuple[float, float, float],
        vouched: bool,
    ) -> None:
        """SLAM moved the odometry frame under the map from ``before`` to ``after`` (``map_from_odom``,
        :class:`mazebot.state.OdometryFix`) with its update of the revolution that ended at
        ``revolution_end_s`` (None: it found the robot again; no revolution of its own).

        Returns SLAM placed before keep their place in the map: in the odometry frame they move
        by ``after⁻¹ ∘ before``. That revolution's own returns were put where the odometry had it
        at its end, which ``after`` maps to where SLAM has it: from now on they count as placed,
        if SLAM ``vouched`` for that pose, else they are dropped. Returns of earlier revolutions
        still unplaced are dropped: SLAM left those revolutions out.
        """
        move = compose(inverse(after), before)
        self._points = _fixed(self._points, move, revolution_end_s, vouched)
        self._recent = _fixed(self._recent, move, revolution_end_s, vouched)
        self._previous = _fixed(self._previous, move, revolution_end_s, vouched)

    def _moved_since_last(self, pose: tuple[float, float, float]) -> bool:
        """Whether the odometry moved or turned since the previous revolution (the first one counts)."""
        last, self._last_pose = self._last_pose, pose
        if last is None:
            return True
        turned_rad = abs(math.remainder(pose[2] - last[2], math.tau))
        return math.hypot(pose[0] - last[0], pose[1] - last[1]) >= self.still_m or turned_rad >= self.still_rad

    def points_robot(self, pose: tuple[float, float, float]) -> np.ndarray:
        """The remembered returns the last revolution could not show, in the robot frame at odometry ``pose``."""
        return transform_points(inverse(pose), np.concatenate((self._points[:, :2], self._previous[:, :2])))

    def snapshot(self) -> np.ndarray:
        """Every near return remembered, the last revolution's own included: (N, 2), odometry frame, read-only.

        What the planner publishes for the control loop's :class:`CollisionGuard`
        (``SharedState.blind_zone_points``). The guard pairs it with a revolution that may be
        newer than the one the memory last took in, from which the robot may have come
        closer than the minimum range to the last revolution's own near returns: so they are
        in too (a return the guard's scan also shows is only counted twice).
        """
        out = np.concatenate((self._points[:, :2], self._previous[:, :2], self._recent[:, :2]))
        out.setflags(write=False)
        return out


#: Columns of the blind-zone memory's rows: x, y (odometry frame), the revolution's count, its end time, placed.
_COLUMNS = 5


def _fixed(rows: np.ndarray, move: np.ndarray, revolution_end_s: float | None, vouched: bool) -> np.ndarray:
    """:meth:`BlindZoneMemory.fix` on one array of rows: placed rows moved, that revolution's placed or dropped."""
    placed = rows[:, 4] > 0
    out = rows.copy()
    out[placed, :2] = transform_points(move, rows[placed, :2])
    if revolution_end_s is None:  # a re-localization: what only the odometry placed is not where it says
        return out[placed]
    this = ~placed & (rows[:, 3] == revolution_end_s)
    earlier = ~placed & (rows[:, 3] < revolution_end_s)
    out[this, 4] = 1.0
    return out[~earlier & (vouched | ~this)]


def with_remembered(
    points_robot: np.ndarray, remembered_odom: np.ndarray | None, pose_now: tuple[float, float, float] | None
) -> np.ndarray:
    """The scan's robot-frame points (N, 2) and the remembered blind-zone returns (odometry frame,
    :meth:`BlindZoneMemory.snapshot`) moved into the robot frame at odometry ``pose_now``.

    Without a pose or a memory the scan's points are returned as they are.
    """
    if remembered_odom is None or pose_now is None or len(remembered_odom) == 0:
        return points_robot
    return np.concatenate((points_robot, transform_points(inverse(pose_now), remembered_odom)))


class CollisionGuard:
    """Emergency stop on lidar returns in the robot's path.

    Example::

        guard = CollisionGuard(footprint_radius_m=0.09, margin_m=0.03)
        verdict = guard.check(points_robot, v_mps=0.2, w_radps=0.0)
        if verdict.stop: ...

    ``footprint_radius_m`` the robot's radius; ``margin_m`` the distance kept beyond it in
    the direction of motion; ``side_margin_m`` the distance kept beside the path;
    ``brake_decel_mps2`` the deceleration the motors can be counted on for;
    ``latency_s`` the time until a stop takes effect (control period plus actuation);
    ``min_speed_mps`` below which the robot is treated as not translating.
    """

    def __init__(
        self,
        footprint_radius_m: float = _ROBOT.footprint_radius_m,
        margin_m: float = 0.03,
        side_margin_m: float = 0.0,
        brake_decel_mps2: float = _CONTROL.brake_decel_mps2,
        latency_s: float = 0.1,
        min_speed_mps: float = 0.005,
    ) -> None:
        if footprint_radius_m <= 0 or margin_m < 0 or brake_decel_mps2 <= 0 or latency_s < 0:
            raise ValueError(
                "need footprint_radius_m > 0, margin_m >= 0, brake_decel_mps2 > 0 and latency_s >= 0, got "
                f"{footprint_radius_m}, {margin_m}, {brake_decel_mps2}, {latency_s}"
            )
        self.footprint_radius_m = float(footprint_radius_m)
        self.margin_m = float(margin_m)
        self.side_margin_m = float(side_margin_m)
        self.brake_decel_mps2 = float(brake_decel_mps2)
        self.latency_s = float(latency_s)
        self.min_speed_mps = float(min_speed_mps)

    @property
    def radius_m(self) -> float:
        """Footprint plus side margin: the protected distance around the swept arc."""
        return self.footprint_radius_m + self.side_margin_m

    def stopping_distance_m(self, v_mps: float) -> float:
        """Distance travelled before a stop takes hold: latency at ``v``, then braking."""
        v = abs(v_mps)
        return v * self.latency_s + v * v / (2.0 * self.brake_decel_mps2)

    def check(self, points_robot: np.ndarray, v_mps: float, w_radps: float) -> SafetyVerdict:
        """Stop when the sweep of the arc ``(v_mps, w_radps)`` brings the guard onto a return (robot frame, (N, 2)).

        The robot centre's path is the arc from here over the stopping distance plus
        ``margin_m``, forwards or in reverse; a return stops the robot when that path comes
        within :attr:`radius_m` of it **and** closer than the centre is to it now (by more than
        :data:`APPROACH_TOL_M`). The second condition is what lets the robot always move
        away: a return already inside the guard (a wall it was pushed against, map noise)
        does not block a motion that takes the body no closer to it. Returns beside the
        robot count like any other: a tight arc, in reverse most of all, carries the body
        sideways into them.
        """
        if abs(v_mps) < self.min_speed_mps:
            return OK
        pts = np.asarray(points_robot, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] == 0:
            return OK
        length = self.stopping_distance_m(v_mps) + self.margin_m
        # every point of the path lies within ``length`` of the centre (an arc is never shorter
        # than its chord), so a return farther than length + radius cannot be reached: most of a
        # revolution's returns are left out before the exact distances
        reach = length + self.radius_m
        range2 = pts[:, 0] * pts[:, 0] + pts[:, 1] * pts[:, 1]
        near = range2 < reach * reach
        if not near.any():
            return OK
        cand = pts[near]
        ranges = np.sqrt(range2[near])
        d = arc_distance_m(cand, length, math.copysign(1.0, v_mps), w_radps / v_mps)
        inside = d < np.minimum(self.radius_m, ranges - APPROACH_TOL_M)
        if not inside.any():
            return OK
        hits, hit_ranges = cand[inside], ranges[inside]
        k = int(np.argmin(hit_ranges))
        bearing = math.degrees(math.atan2(hits[k, 1], hits[k, 0]))
        where = "ahead" if abs(bearing) <= 45.0 else "behind" if abs(bearing) >= 135.0 else (
            "on the left" if bearing > 0 else "on the right")
        motion = "forwards" if v_mps > 0 else "in reverse"
        return SafetyVerdict(
            True,
            f"emergency stop: obstacle {where} at {hit_ranges[k]:.2f} m, bearing {bearing:.0f}°, inside the "
            f"{self.radius_m:.2f} m guard of the next {length:.2f} m {motion} at {v_mps:.2f} m/s, {w_radps:.2f} rad/s",
            float(hit_ranges[k]),
        )


#: A return counts as approached when the sweep takes the robot centre this much closer to it
#: than it is now (metres): one passed exactly abeam is neither approached nor left, and the last
#: bits of a float must not decide which (the DWA's contact limit keeps the same 0.1 mm).
APPROACH_TOL_M = 1e-4

#: Below this curvature (1/m) the arc is taken as straight: over the longest stopping distance
#: (under 0.3 m) it bows out by less than 0.05 mm, and the circle's centre would lie kilometres off.
STRAIGHT_CURVATURE_PER_M = 1e-3


def arc_distance_m(points_robot: np.ndarray, length_m: float, direction: float, curvature_per_m: float) -> np.ndarray:
    """The smallest distance (N,) from each robot-frame point (N, 2) to the path of the robot centre
    over ``length_m`` of the arc driven forwards (``direction`` +1) or in reverse (−1) with the signed
    curvature ``w / v`` (1/m).

    The centre's path is ``x = direction · sin(κs) / κ``, ``y = (1 − cos(κs)) / κ`` for arc length
    ``s`` in ``[0, length_m]`` (κ = ``curvature_per_m``; a unicycle at constant ``(v, w)``).
    Mirrored to a forward left turn (x times ``direction``, y times the sign of κ), the path is
    part of a circle of radius ``ρ = 1/|κ|`` about ``(0, ρ)``, and the distance is exact: a
    point whose angle about the centre lies within the arc's is ``|r − ρ|`` from it, any
    other is nearest to one of the arc's ends. No samples: the result does not depend on a
    spacing, and it costs a few array operations per point whatever the arc's length.
    """
    pts = np.asarray(points_robot, dtype=np.float64).reshape(-1, 2)
    qx = pts[:, 0] * direction
    qy = pts[:, 1] if curvature_per_m >= 0 else -pts[:, 1]
    k = abs(curvature_per_m)
    if k < STRAIGHT_CURVATURE_PER_M:
        s = np.clip(qx, 0.0, length_m)
        return np.hypot(qx - s, qy)
    rho = 1.0 / k
    dy = qy - rho
    to_centre = np.hypot(qx, dy)
    sweep_rad = k * length_m
    if sweep_rad >= math.tau:  # a whole circle (a crawl turning fast): every angle is on it
        return np.abs(to_centre - rho)
    # the angle about the centre, measured like the arc's from the robot (0) onwards: c(φ) − O = ρ (sin φ, −cos φ)
    angle = np.mod(np.arctan2(qx, -dy), math.tau)
    end_x, end_y = rho * math.sin(sweep_rad), 2.0 * rho * math.sin(0.5 * sweep_rad) ** 2
    ends = np.minimum(np.hypot(qx, qy), np.hypot(qx - end_x, qy - end_y))
    return np.where(angle <= sweep_rad, np.abs(to_centre - rho), ends)


class ControlWatchdog:
    """Stops when the control loop misses its deadline.

    Example::

        watchdog = ControlWatchdog(deadline_s=0.1)
        verdict = watchdog.tick(clock.now_s())     # at the top of every control tick

    A tick that comes more than ``deadline_s`` after the previous one means the loop was
    blocked: the motors ran unsupervised for that long, so this tick stops them (and
    the planner starts again from rest on the next).
    """

    def __init__(self, deadline_s: float = _CONTROL.deadline_s) -> None:
        if deadline_s <= 0:
            raise ValueError(f"deadline_s must be positive, got {deadline_s}")
        self.deadline_s = float(deadline_s)
        self.last_tick_s: float | None = None
        self.misses = 0

    def tick(self, now_s: float) -> SafetyVerdict:
        """Record a control tick; a stop verdict when it came later than the deadline."""
        last, self.last_tick_s = self.last_tick_s, now_s
        if last is not None and now_s - last > self.deadline_s:
            self.misses += 1
            return SafetyVerdict(
                True,
                f"control loop missed its deadline: {now_s - last:.3f} s since the last tick (> {self.deadline_s} s)",
            )
        return OK

    def overdue(self, now_s: float) -> bool:
        """True when no tick has come within the deadline (for a monitor outside the loop)."""
        return self.last_tick_s is not None and now_s - self.last_tick_s > self.deadline_s


class CommandGate(Generic[T]):
    """Holds the latest planner command and hands it out only while it is fresh.

    Example::

        gate = CommandGate(ttl_s=0.5)
        gate.put((0.2, 0.0), now_s)
        gate.get(later_s)      # the command, or None once older than ttl_s
    """

    def __init__(self, ttl_s: float = 0.5) -> None:
        if ttl_s <= 0:
            raise ValueError(f"ttl_s must be positive, got {ttl_s}")
        self.ttl_s = float(ttl_s)
        self._command: T | None = None
        self._stamp_s = -math.inf

    def put(self, command: T, time_s: float) -> None:
        """Store a command made at clock time ``time_s``."""
        self._command, self._stamp_s = command, float(time_s)

    def age_s(self, now_s: float) -> float:
        """Seconds since the stored command was made (inf when none)."""
        return now_s - self._stamp_s

    def get(self, now_s: float) -> T | None:
        """The stored command if it is at most ``ttl_s`` old, else None (stop)."""
        if self._command is None or self.age_s(now_s) > self.ttl_s:
            return None
        return self._command

    def clear(self) -> None:
        self._command, self._stamp_s = None, -math.inf


class TickAge:
    """How many ticks have run since a stamp (a command's, a revolution's) was first seen.

    Example::

        age = TickAge()
        age.tick(1.0), age.tick(1.0), age.tick(1.2)   # 0, 1, 0: the stamp changed
    """

    def __init__(self) -> None:
        self.stamp: float | None = None
        self.ticks = 0

    def tick(self, stamp: float | None) -> int | None:
        """Count this tick for ``stamp``; its age in ticks (0 when new, None without one)."""
        if stamp is None:
            self.stamp, self.ticks = None, 0
            return None
        if stamp != self.stamp:
            self.stamp, self.ticks = stamp, 0
        else:
            self.ticks += 1
        return self.ticks


class SafetyLayer:
    """All stop conditions of one control tick, in one call.

    Example::

        safety = SafetyLayer(CollisionGuard(), ControlWatchdog(0.1), command_ttl_ticks=10, scan_timeout_ticks=20)
        verdict = safety.check(now_s, v_mps, w_radps, command_time_s, scan_points, scan_time_s)
        if verdict.stop:
            motors.stop()

    Checks, in order: the control deadline, the command's age (``command_ttl_ticks``
    control ticks since it was first seen), the lidar's age (``scan_timeout_ticks`` since
    the latest revolution was: without fresh returns the guard is blind, so only turning
    in place is allowed), then the collision guard on the latest returns. Call it (or
    :meth:`idle`) once per control tick: the ages are counted in those calls.
    ``stops`` counts verdicts that stopped, ``last`` is the latest verdict.
    """

    def __init__(
        self,
        guard: CollisionGuard | None = None,
        watchdog: ControlWatchdog | None = None,
        command_ttl_ticks: int = _CONTROL.command_ttl_ticks,
        scan_timeout_ticks: int = _CONTROL.scan_timeout_ticks,
    ) -> None:
        if command_ttl_ticks < 1 or scan_timeout_ticks < 1:
            raise ValueError(f"need ticks >= 1, got {command_ttl_ticks} and {scan_timeout_ticks}")
        self.guard = guard or CollisionGuard()
        self.watchdog = watchdog or ControlWatchdog()
        self.command_ttl_ticks = int(command_ttl_ticks)
        self.scan_timeout_ticks = int(scan_timeout_ticks)
        self.command_age = TickAge()
        self.scan_age = TickAge()
        self.stops = 0
        self.last = OK

    def idle(self, now_s: float, command_time_s: float | None, scan_time_s: float | None) -> None:
        """A control tick that drives nothing: the deadline clock and the ages still count.

        A command that waited through idle ticks (the planner died, then the user
        pressed start) is as stale as one that waited while driving.
        """
        self.watchdog.tick(now_s)
        self.command_age.tick(command_time_s)
        self.scan_age.tick(scan_time_s)

    def check(
        self,
        now_s: float,
        v_mps: float,
        w_radps: float,
        command_time_s: float | None,
        scan_points_robot: np.ndarray | None,
        scan_time_s: float | None,
    ) -> SafetyVerdict:
        """The verdict for applying ``(v_mps, w_radps)`` now (one call per control tick)."""
        verdict = self.watchdog.tick(now_s)
        command_ticks = self.command_age.tick(command_time_s)
        scan_ticks = self.scan_age.tick(scan_time_s)
        if not verdict.stop and (command_ticks is None or command_ticks >= self.command_ttl_ticks):
            age = "no command" if command_ticks is None else f"{command_ticks} control ticks since the command came"
            verdict = SafetyVerdict(True, f"stale command: {age} (ttl {self.command_ttl_ticks} ticks)")
        translating = abs(v_mps) >= self.guard.min_speed_mps
        if not verdict.stop and translating and (scan_ticks is None or scan_ticks >= self.scan_timeout_ticks):
            age = "no scan yet" if scan_ticks is None else f"{scan_ticks} control ticks since the last revolution"
            verdict = SafetyVerdict(True, f"lidar silent: {age} (timeout {self.scan_timeout_ticks} ticks)")
        if not verdict.stop and translating and scan_points_robot is not None:
            verdict = self.guard.check(scan_points_robot, v_mps, w_radps)
        if verdict.stop:
            self.stops += 1
        self.last = verdict
        return verdict
