"""The start seen again at rest at the end of a run: how far the map stands turned about the start.

The map is tied to the start: keyframe 0 is the map frame, and the wall grid's direction in
it (the anchor of the wall priors, :mod:`mazebot.slam.start_anchor`) is judged from the few
boards the start sees. Boards set by hand stand turned by a fraction of a degree each, so
that judgement can be off by a few tenths of a degree, and the whole map, held to the grid,
turns by as much about the start. A closure to the start taken moving cannot tell: its
revolution is de-skewed with the odometry, and its heading errs by as much.

When the maze is explored the robot comes back to its start cell and stops. Its
revolutions there need neither de-skew nor odometry (nothing moves), and neither do
keyframe 0's revolutions at rest: the two views of the same boards, from about the same
place, match at ICP's accuracy. Each revolution at home is matched against keyframe 0's
rest surface and verified as any loop closure to keyframe 0 is
(:func:`mazebot.slam.loop_closure.verify`, the inlier ratio counted where keyframe 0 saw);
the heading correction the matches agree on, against the pose the map gives the robot,
is the map's turn about the start (Lu and Milios, "Globally consistent range scan alignment
for environment mapping", Autonomous Robots 4, 1997: a scan pair's relative pose as a
constraint with its own covariance).

Example (what :class:`mazebot.slam.slam.LoopClosureJob` does with the final job's revolutions)::

    turn = measure_home_turn(rest_target, observed, home, prior, icp_params, loop_params)
    if turn is not None:
        turn.correction_rad, turn.std_rad   # the map stands turned by -correction about the start
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from mazebot.geometry import compose, relative_pose, wrap_angle
from mazebot.slam.icp import IcpParams, Target
from mazebot.slam.loop_closure import Candidate, LoopClosureParams, verify
from mazebot.slam.overlap import ObservedArea

#: Revolutions at rest taken at home before the final map is made: a second of the A1's, at a
#: robot that has arrived anyway. Five matches tell a revolution's noise from their agreement
#: (``MIN_AGREEING``) and cost a few milliseconds of ICP each.
HOME_REST_REVOLUTIONS = 5
#: Matches that must pass every closure test and agree before the turn is taken: a majority of
#: ``HOME_REST_REVOLUTIONS``, so one look-alike or one disturbed revolution cannot decide alone.
MIN_AGREEING = 3
#: How far (in units of a match's own heading std) a match may lie from the matches' median
#: and still count as agreeing with them: three standard deviations.
AGREE_SIGMAS = 3.0
#: Optimizations of the final graph run again with the turn re-expressed, at most, after the first
#: step (which also measures how far the robot follows the grid: ``HOME_MIN_FOLLOW``). The turn enters
#: the pose graph through the wall grid's anchor, as the snapshot's grid turned by it; but the keyframes
#: settle on the grid where their own boards say (each turned by a fraction of a degree), so the optimized
#: map gives the robot a heading a little off the one measured. Re-expressed against the optimized map
#: (secant steps on the one turn about the start), it is met within ``HOME_TURN_TOLERANCE_RAD`` after one
#: or two more.
HOME_RELINEARIZATIONS = 3
#: What is left of the measured turn in the optimized map that needs no further optimization: a
#: hundredth of a degree, a tenth of a millimetre a board's length (0.3 m) from the start.
HOME_TURN_TOLERANCE_RAD = math.radians(0.01)
#: How much of a turn of the wall grid the robot's heading at home must follow for its revolutions there
#: to say the map's turn: at least half, so that the turn it sees is for the most part the map's. Where
#: the keyframes around the start are held to keyframe 0 by closures, it follows a tenth or less of it.
HOME_MIN_FOLLOW = 0.5


@dataclass(frozen=True)
class HomeRevolution:
    """One revolution at rest at home: its match points (robot frame, (N, 2)), the lidar's position in
    the robot frame (2,), and the robot's map pose SLAM gave that revolution (3,)."""

    points: np.ndarray
    sensor_xy: np.ndarray
    pose: np.ndarray


@dataclass(frozen=True)
class HomeRest:
    """The robot's revolutions at rest at home, and how uncertain their poses are relative to keyframe 0.

    ``prior_covariance`` (3×3): the pose graph's chain from keyframe 0 to the newest keyframe,
    as a closure to keyframe 0 from there would be judged.
    """

    revolutions: tuple[HomeRevolution, ...]
    prior_covariance: np.ndarray

    @property
    def pose(self) -> np.ndarray:
        """The robot's map pose at the newest revolution: where it stands when the final job is made."""
        return self.revolutions[-1].pose


@dataclass(frozen=True)
class HomeTurn:
    """What the revolutions at home said: the heading correction (rad) of the map's pose of the robot
    in keyframe 0's frame, its std (rad), the position correction (m), and how many matches agreed of how many.

    ``applied_rad`` is the correction as the anchor takes it: the measured one at first, re-expressed
    against the optimized map (:func:`home_turn_left`) while the optimization does not meet it;
    ``follows`` how far the robot's heading at home followed a turn of the grid (None: not
    tried, the map met the turn at once), and ``used`` whether the final map was turned by it.
    """

    correction_rad: float
    std_rad: float
    shift_m: float
    agreeing: int
    revolutions: int
    applied_rad: float
    follows: float | None = None
    used: bool = True


def measure_home_turn(
    rest_target: Target | None,
    observed: ObservedArea | None,
    home: HomeRest,
    first_pose: np.ndarray,
    icp: IcpParams,
    loop: LoopClosureParams,
) -> HomeTurn | None:
    """The map's turn about the start from the revolutions at home, or None if they do not verify.

    ``rest_target`` is keyframe 0's rest surface in its frame; ``observed`` what keyframe 0
    saw (its inlier ratio is counted there); ``first_pose`` (3,) keyframe 0's map pose: each
    revolution starts from the robot's pose in keyframe 0's frame as the map had it. The std
    is the larger of a match's own (ICP's information, without the ``information_scale`` that
    discounts closures taken moving) and the matches' spread: the revolutions at home see the
    same boards from the same place, so their errors are not independent and averaging them
    buys nothing beyond the spread.
    """
    if rest_target is None or len(rest_target) == 0:
        return None
    loop = replace(loop, overlap_fitness=True)
    corrections, stds, shifts = [], [], []
    for revolution in home.revolutions:
        source, sensor_xy = revolution.points, revolution.sensor_xy
        if loop.max_range_m is not None:
            source = source[np.hypot(*(source - sensor_xy).T) <= loop.max_range_m]
        prior = relative_pose(first_pose, revolution.pose)
        distance_m = float(math.hypot(prior[0], prior[1]))
        candidate = Candidate(0, -1, prior, home.prior_covariance, distance_m)
        verdict = verify(candidate, rest_target, source, sensor_xy, icp, loop, observed)
        if not verdict.accepted or verdict.information[2, 2] <= 0:
            continue
        corrections.append(float(wrap_angle(verdict.measurement[2] - prior[2])))
        # the match's own information: information_scale discounts a closure's for the de-skew and motion of
        # a revolution taken moving, of which a revolution at rest has none
        stds.append(math.sqrt(loop.information_scale / float(verdict.information[2, 2])))
        shifts.append(float(np.hypot(*(verdict.measurement[:2] - prior[:2]))))
    if len(corrections) < MIN_AGREEING:
        return None
    values, own = np.array(corrections), np.array(stds)
    agree = np.abs(values - np.median(values)) <= AGREE_SIGMAS * own
    if int(agree.sum()) < MIN_AGREEING:
        return None
    values, own = values[agree], own[agree]
    spread = float(np.std(values, ddof=1))
    correction = float(values.mean())
    return HomeTurn(
        correction_rad=correction,
        std_rad=max(float(np.median(own)), spread),
        shift_m=float(np.median(np.array(shifts)[agree])),
        agreeing=int(agree.sum()),
        revolutions=len(home.revolutions),
        applied_rad=correction,
    )


def home_turn_left(snapshot: np.ndarray, optimized: np.ndarray, robot_pose: np.ndarray, turn: HomeTurn) -> float:
    """How much of the measured turn (rad) the optimized map still lacks at the robot's pose at home.

    ``snapshot`` and ``optimized`` (K, 3) are the keyframes' poses before and after the
    optimization; ``robot_pose`` the robot's map pose in the snapshot (its newest revolution's).
    The robot keeps its place relative to the newest keyframe; the measured heading in keyframe
    0's frame is the snapshot's corrected by ``turn.correction_rad``.
    """
    newest = len(snapshot) - 1
    robot = compose(optimized[newest], relative_pose(snapshot[newest], robot_pose))
    measured = float(relative_pose(snapshot[0], robot_pose)[2]) + turn.correction_rad
    return float(wrap_angle(measured - float(relative_pose(optimized[0], robot)[2])))
