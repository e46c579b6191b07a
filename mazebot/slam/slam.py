"""The SLAM façade: one ``update(scan, odometry)`` per lidar revolution.

Why one module of ~1150 lines: the steps already live in modules of their own (below), the
parameters in :mod:`mazebot.slam.params` and the walls' priors in :mod:`mazebot.slam.wall_priors`;
what is left here is the state they share (keyframes, submap, pose graph, grid, calibration)
and the two places that must agree on it: :class:`Slam`, which runs the steps in order, and
:class:`LoopClosureJob`, which carries a copy of that state to a worker and back
(:meth:`Slam.apply`). Apart, one piece of state would be described in two files. The
public ways in that a resumed run and the recorder use (:meth:`Slam.continue_map`,
:meth:`Slam.start_in_map`, :class:`SlamTaps`) stay beside the state they touch.

``Slam.update`` reads as the ICP pose-graph SLAM of Nayak, Chiang and Kanupriyaa, *2D
Autonomous Mapping* (CMU 18-500 report), section III.B, with an EKF (Thrun, Burgard & Fox,
*Probabilistic Robotics*, 3.3) in front of it; every step lives in its own module:

1. **predict** the pose at the end of the revolution with the odometry increment since
   the last scan, its heading corrected by the online calibration
   (:mod:`mazebot.slam.ekf`);
2. **de-skew** and filter the scan with the odometry at each sample's time, shifted by
   the learned lidar time offset (:mod:`mazebot.slam.preprocess`);
3. **match** it against the local submap (the recent keyframes and older ones nearby),
   starting from the prediction, retrying from turned guesses if the match is poor or, with
   ``match_heading_sigmas``, turned further from the prediction than its uncertainty allows
   (:mod:`mazebot.slam.icp`, :mod:`mazebot.slam.keyframes`);
4. **correct** the filter with the match (information form: a corridor's unobserved
   direction keeps the odometry; with ``basin_probe_m`` also a direction along which ICP's
   basin does not hold, :mod:`mazebot.slam.basin_probe`; a moving revolution's match loosened
   along the direction of travel by the de-skew's error, :mod:`mazebot.slam.deskew_variance`),
   and feed the calibrations;
5. **keyframe**: after 0.10 m or 0.15 rad the scan is kept, added to the pose graph
   with an edge from the previous keyframe (odometry + ICP information), and the local
   submap is refreshed (:mod:`mazebot.slam.posegraph`);
6. **update the grid** with the scan's rays at the corrected pose (:mod:`mazebot.slam.grid`);
7. **close loops**: old keyframes within the drift-scaled radius are candidates,
   verified by strict ICP tests; accepted ones join the graph, which is optimized
   (Levenberg–Marquardt), and the grid is rebuilt from the optimized keyframes
   (:mod:`mazebot.slam.loop_closure`).

Step 7 is heavy (tens to hundreds of milliseconds). With ``background=True`` (the
daemon) ``update`` only packs it into a :class:`LoopClosureJob` (a snapshot, safe to run
in another thread) and returns it in :class:`SlamUpdate`; the caller runs ``job.run()``
in an executor and hands the result to :meth:`Slam.apply`, which merges it with the
keyframes added meanwhile. With ``background=False`` (offline tools, tests) ``update``
runs and applies it at once.

Steps 1–6 still take a few milliseconds per revolution, up to ~20 ms for a keyframe scan
that rebuilds the local submap; on the daemon's event loop that is as long as the 20 Hz
control tick may run late. :meth:`Slam.update_steps` and :meth:`Slam.apply_steps` are the
same methods as generators that yield between their stages (:mod:`mazebot.steps`): the
SLAM task lets the loop run in between, offline tools call ``update``/``apply``, which run
every stage at once. Same stages, same order: the same result.

Frames: the map frame is the robot's pose at the start (``initial_pose``, default the
origin: x forward, y left); the odometry frame is wherever the encoders started.
``SlamUpdate.map_from_odom`` is the correction between them (ROS' ``map → odom``): the
robot's map pose at any later time is ``map_from_odom ⊕ odometry``.

Example::

    slam = Slam(SlamParams.from_config(config.slam, config.lidar, config.planner))
    update = slam.update(scan, odometry_history)     # one revolution
    update.pose, update.covariance, slam.grid.three_state()
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from mazebot.geometry import compose, inverse, relative_pose, transform_points, wrap_angle
from mazebot.io.scan import Scan
from mazebot.slam.basin_probe import probed_steps
from mazebot.slam.closure_set import ACCEPTED_BY_SET, Chain, judge
from mazebot.slam.correlative import LikelihoodTable, correlative_match, select_points
from mazebot.slam.deskew_variance import deskew_information
from mazebot.slam.distance_calibration import DistanceCalibration, fixes_travel
from mazebot.slam.ekf import HeadingCalibration, PoseEkf, TimeOffsetCalibration, rotate_information
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.icp import IcpResult, Target, match_scan_steps
from mazebot.slam.keyframes import (
    Keyframe,
    KeyframeSelector,
    build_target,
    build_target_steps,
    map_rays,
    smoothed_match_points,
)
from mazebot.slam.lattice_fit import PitchFit, cell_offset_on_lattice
from mazebot.slam.lever_arm import LeverArmCalibration
from mazebot.slam.loop_closure import Candidate, ObservedDirections, Verdict, find_candidates, keyframe_gap, verify
from mazebot.slam.match_residuals import MatchResiduals
from mazebot.slam.odometry_noise import OdometryNoiseEstimate
from mazebot.slam.overlap import ObservedArea
from mazebot.slam.params import GridParams as GridParams  # re-exported: the façade's parameter objects
from mazebot.slam.params import SlamParams as SlamParams
from mazebot.slam.posegraph import OptimizeResult, PoseGraph
from mazebot.slam.preprocess import PoseAtTime, PreparedScan, prepare_scan, voxel_downsample
from mazebot.slam.robust_closures import optimize_dcs
from mazebot.slam.start_anchor import (
    BOARD_TURN_STD_RAD,
    StartFit,
    heading_links,
    joined_with_view,
    start_anchor_fit,
    start_view_rad,
)
from mazebot.slam.submap_error import with_covariance_floor
from mazebot.slam.wall_faces import Faces, face_spread, quarter_turns, wall_faces
from mazebot.slam.wall_priors import LATTICE_REFIT_GROWTH, wall_priors, wrap_quarter
from mazebot.steps import all_at_once_method
from mazebot.taps import notify

log = logging.getLogger(__name__)

#: Loop-closure candidates kept while a job runs (the newest).
PENDING_CANDIDATES = 4

#: A degenerate match's free direction is a slide along a corridor when its position part is at least this
#: share of the unit pose step (the rest a turn): only then is it matched again along it
#: (:meth:`Slam._degenerate_retry_steps`).
DEGENERATE_POSITION_SHARE = 0.5
#: ... and a restart replaces it only with a residual under this share of its: the RMS of a scan's ~100 point-to-line
#: residuals varies by about 1/√(2N) ≈ 7 % from one alignment to the next, so a residual 5 % smaller says nothing
#: (along the ACES log's featureless corridors restarts end 3-11 % under the degenerate match, 50-170 mm off the
#: corrected poses), one three of those smaller says the degenerate match sat off the scan's own walls.
DEGENERATE_RETRY_RMSE_SHARE = 0.8


#: Decides, once a revolution is matched, whether SLAM paints it: ``decide(match, matched)``.
PaintDecision = Callable[["IcpResult | None", bool], bool]


class OdometrySource(Protocol):
    """What SLAM needs from odometry: poses at any recent time (``OdometryHistory`` has this)."""

    def at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class LoopClosureResult:
    """What a :class:`LoopClosureJob` found: verdicts, and if one was accepted the optimized poses.

    ``poses`` (K, 3) are the optimized poses of the K keyframes of the snapshot (None if
    nothing was accepted); ``grid`` a grid rebuilt from them (None if no keyframe moved
    enough to need it); ``moved_m``/``turned_rad`` the largest change; ``wall_reference_rad`` the
    wall grid's direction estimated with them (None without wall priors).
    """

    verdicts: list[Verdict]
    poses: np.ndarray | None = None
    grid: OccupancyGrid | None = None
    optimization: OptimizeResult | None = None
    moved_m: float = 0.0
    turned_rad: float = 0.0
    wall_reference_rad: float | None = None  # the wall grid's direction estimated with the poses
    lattice_fit: PitchFit | None = None  # the lattice the walls were fitted to (None: not looked for)
    lattice_fit_keyframes: int = 0  # how many keyframes the job had when that lattice was fitted
    cpu_s: float = 0.0  # thread CPU time the job took (where it ran: a thread or a worker process)
    downweighted: int = 0  # loop closures in the graph whose robust weight fell below 0.1 (robust_closures)
    # closures waiting for a set (``tentative`` verdicts, of this job or before) that the set accepted
    set_accepted: tuple[Verdict, ...] = ()
    # the wall grid's direction in keyframe 0's frame and its std, measured by each closure to keyframe 0's
    # revolutions at rest so far (this job's and before): the anchor (LoopClosureJob.start_turns)
    start_turns: tuple[tuple[float, float], ...] = ()


@dataclass
class LoopClosureJob:
    """Step 7 on a snapshot: verify candidates, optimize, rebuild the grid. Thread-safe to run.

    Keyframe arrays are never modified after creation, and every pose and edge the job
    uses is copied when the job is made, so ``run()`` may execute in another thread
    while SLAM goes on with new scans.
    """

    candidates: list[Candidate]
    keyframes: list[Keyframe]
    poses: np.ndarray
    integrated_poses: np.ndarray
    edges: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    params: SlamParams
    wall_reference_rad: float | None = None  # the wall grid's direction in the map frame, if known
    optimize_anyway: bool = False  # optimize even if no candidate is accepted (periodic wall priors)
    # keyframe 0's wall direction in its own frame, averaged at rest, and how tightly it ties the wall vertex
    anchor_wall: tuple[float, float] | None = None  # (direction_rad, std_rad); None: keyframe 0 is no anchor
    # keyframe 0's faces at rest (its frame) where they turn apart: the anchor is then the maze's grid
    # judged from every keyframe's faces together (mazebot.slam.start_anchor), with anchor_wall's trust
    start_faces: Faces | None = None
    # keyframe 0's revolutions at rest pooled (points, normals; its frame): a closure to keyframe 0 is matched
    # against them alone (None: against the keyframes around it, as any closure)
    rest_surface: tuple[np.ndarray, np.ndarray] | None = None
    # the wall grid's direction in keyframe 0's frame and its std as closures to the rest surface measured it
    # (earlier jobs'; this job adds its own): counted in the anchor beside the faces' (_anchor)
    start_turns: tuple[tuple[float, float], ...] = ()
    rebuild_anyway: bool = False  # rebuild the grid however little the keyframes moved (the end of exploration)
    # set by the run once the exploration is over: with [slam.graph] rebuild_after_exploration, a job that
    # moves any keyframe rebuilds the grid (the map the robot keeps, not lagging the graph by the thresholds)
    exploration_over: bool = False
    lattice_fit: PitchFit | None = None  # set by the run: the lattice the walls were fitted to
    # the last lattice fitted and the keyframes it was fitted with: taken again while the keyframes
    # grew by less than wall_priors.LATTICE_REFIT_GROWTH (None: fit it)
    known_fit: tuple[PitchFit, int] | None = None
    lattice_fit_keyframes: int = 0  # set by the run: the keyframes ``lattice_fit`` was fitted with
    # closures verified as a set ([slam.loop] set_verify): recent closures in the graph (support), and
    # tentative ones waiting for support (mazebot.slam.closure_set)
    set_members: tuple[Verdict, ...] = ()
    set_waiting: tuple[Verdict, ...] = ()

    def __call__(self) -> LoopClosureResult:
        """The job as a callable, so any executor runs it (``loop.run_in_executor(executor, job)``)."""
        return self.run()

    def run(self) -> LoopClosureResult:
        start_s = time.thread_time()
        result = self._run()
        return replace(result, cpu_s=time.thread_time() - start_s)

    def _run(self) -> LoopClosureResult:
        p = self.params
        verdicts = []
        for found in self.candidates:
            # the prior from this snapshot: an optimization may have moved both ends since it was found
            cand = replace(found, prior=relative_pose(self.poses[found.old], self.poses[found.new]))
            lo = max(0, cand.old - p.loop.submap_half_width)
            gap = keyframe_gap(self.poses, cand.new, p.loop)
            hi = min(cand.new - gap // 2, cand.old + p.loop.submap_half_width) + 1
            window = range(lo, max(hi, cand.old + 1))
            # both sides within the same range of the new keyframe's lidar: the inlier ratio then
            # measures agreement, not how much farther one scan happened to see than the other
            new_kf = self.keyframes[cand.new]
            source = new_kf.match_points.astype(np.float64)
            lidar_in_old = compose(cand.prior, np.array([*new_kf.sensor_xy, 0.0]))[:2]
            if p.loop.max_range_m is not None:
                source = source[np.hypot(*(source - new_kf.sensor_xy).T) <= p.loop.max_range_m]
            clip = None if p.loop.max_range_m is None else (lidar_in_old, p.loop.max_range_m + 0.3)
            loop = p.loop
            if cand.old == 0 and self.rest_surface is not None:
                # the start's own view: its inlier ratio counted where keyframe 0 saw (the new keyframe
                # sees more than one scan of the start did)
                window = range(1)
                target = self._rest_target(clip)
                loop = replace(loop, overlap_fitness=True)
            else:
                target = build_target(
                    [self.keyframes[k] for k in window],
                    p.submap_voxel_m,
                    frame=self.poses[cand.old],
                    poses=[self.poses[k] for k in window],
                    clip=clip,
                )
            observed = None
            if loop.overlap_fitness:
                observed = ObservedArea.from_keyframes(
                    [relative_pose(self.poses[cand.old], self.poses[k]) for k in window],
                    [self.keyframes[k].sensor_xy for k in window],
                    [self.keyframes[k].ray_ends for k in window],
                )
            verdicts.append(verify(cand, target, source, new_kf.sensor_xy, p.icp, loop, observed))
        set_accepted: list[Verdict] = []
        if p.loop.set_verify:
            verdicts, set_accepted = self._judged_as_set(verdicts)
        accepted = [v for v in verdicts if v.accepted] + set_accepted
        if not accepted and not self.optimize_anyway:
            return LoopClosureResult(verdicts, set_accepted=tuple(set_accepted), start_turns=self.start_turns)
        # this job's own, not kept in the job: a job computes the same whether it ran before or not
        start_turns = self.start_turns + self._turns_at_rest(accepted)
        # optimize the graph with the new constraints (first keyframe fixed), loop closures robust
        count = self.poses.shape[0]
        ei, ej, z, omega = self.edges
        parts: list[tuple[np.ndarray, ...]] = [(ei, ej, z, omega)]
        if accepted:
            parts.append((
                np.array([v.candidate.old for v in accepted], dtype=np.intp),
                np.array([v.candidate.new for v in accepted], dtype=np.intp),
                np.array([v.measurement for v in accepted]),
                np.array([v.information for v in accepted]),
            ))
        vertices = self.poses
        reused = self._fit_to_reuse()
        priors, fit = wall_priors(
            self.keyframes, self.poses, self.wall_reference_rad, p, p.lattice, self._anchor(start_turns),
            known_fit=None if reused is None else reused[0],
        )
        if fit is not None:
            self.lattice_fit = fit
            self.lattice_fit_keyframes = len(self.keyframes) if reused is None else reused[1]
        if priors is not None:  # vertex ``count``: the wall grid's direction, estimated with the poses
            vertices = np.vstack([self.poses, priors.vertex])
            parts.append((priors.i, priors.j, priors.z, priors.information))
        edges = tuple(np.concatenate([np.asarray(part[k]) for part in parts]) for k in range(4))
        ai, aj = edges[0].astype(np.intp), edges[1].astype(np.intp)
        closure = (aj - ai > 1) & (aj < count) & (ai < count)  # the chain's edges join k - 1 and k
        robust = optimize_dcs(
            vertices, (ai, aj, edges[2], edges[3]), closure, p.loop.dcs_phi, max_iterations=p.optimize_iterations
        )
        optimization = robust.optimization
        wall_reference = None if priors is None else wrap_quarter(float(robust.vertices[count, 2]))
        poses = robust.vertices[:count].copy()
        # rebuild the grid from the optimized keyframes if any moved noticeably
        delta = relative_pose(self.integrated_poses, poses)
        moved = float(np.max(np.hypot(delta[:, 0], delta[:, 1])))
        turned = float(np.max(np.abs(delta[:, 2])))
        grid = None
        if self._rebuild_due(moved, turned):
            grid = p.grid.new_grid()
            offset = cell_offset_on_lattice(self.lattice_fit, self.wall_reference_rad, grid.resolution_m)
            grid.rebuild((kf.rays(poses[k]) for k, kf in enumerate(self.keyframes)), cell_offset_m=offset)
        return LoopClosureResult(
            verdicts,
            poses,
            grid,
            optimization,
            moved,
            turned,
            wall_reference,
            lattice_fit=self.lattice_fit,
            lattice_fit_keyframes=self.lattice_fit_keyframes,
            downweighted=int(np.sum(robust.weights < 0.1)),
            set_accepted=tuple(set_accepted),
            start_turns=start_turns,
        )

    def _turns_at_rest(self, accepted: list[Verdict]) -> tuple[tuple[float, float], ...]:
        """The wall grid's direction in keyframe 0's frame (and its std) that each accepted closure to the rest
        surface says.

        The map's keyframes sit on the wall grid (the wall priors hold every one of them to it), so the
        map turns about the start with the grid's vertex: a closure from keyframe ``n`` to keyframe 0's
        revolutions at rest that turns ``n`` by ``ε`` against this snapshot (its correction's heading) says
        the whole map, grid and all, stands turned by ``-ε`` about the start. The grid's direction in
        keyframe 0's frame is then the snapshot's turned by ``ε``, with the match's heading std (its
        information; :meth:`_anchor` trusts it less). Nothing in it depends on the angle the boards
        around the start stand at.
        """
        if self.rest_surface is None or self.wall_reference_rad is None:
            return ()
        turns = []
        for v in accepted:
            if v.candidate.old != 0 or v.information[2, 2] <= 0:
                continue
            correction = float(wrap_angle(v.measurement[2] - v.candidate.prior[2]))
            direction = wrap_quarter(self.wall_reference_rad - float(self.poses[0, 2]) + correction)
            turns.append((direction, 1.0 / math.sqrt(float(v.information[2, 2]))))
        return tuple(turns)

    def _rest_target(self, clip: tuple[np.ndarray, float] | None) -> Target | None:
        """Keyframe 0's revolutions at rest as a submap (its frame), within ``clip`` of the new keyframe's lidar.

        The start's own view, measured while nothing moved: no de-skew, no odometry, and none of
        the keyframes after it, whose headings carry the first turns' errors (the cheap robot's
        slip), blurs it. A closure to it ties the map's turn to the start itself, through the
        walls both scans see, whatever angle those boards stand at.
        """
        assert self.rest_surface is not None
        points, normals = self.rest_surface
        if clip is not None:
            near = np.hypot(*(points - np.asarray(clip[0]).reshape(1, 2)).T) <= clip[1]
            points, normals = points[near], normals[near]
        if not len(points):
            return None
        return Target(points, self.keyframes[0].sensor_xy, normals)

    def _rebuild_due(self, moved_m: float, turned_rad: float) -> bool:
        """Whether the optimized keyframes are painted into a new grid.

        While exploring, only when a keyframe moved beyond the thresholds (a rebuild costs tens of
        milliseconds on a 16×16 maze, and the next ones come soon). Once the exploration is over the
        map is the one the robot keeps, and a keyframe moved 5–8 mm (under the 1 cm threshold) leaves
        stretches of wall a 2 cm cell over where they were painted, so with ``rebuild_after_exploration``
        any move rebuilds it (an option: on the bench's coverage it helped one contest maze and cost another).
        """
        p = self.params
        if self.rebuild_anyway or moved_m > p.rebuild_threshold_m or turned_rad > p.rebuild_threshold_rad:
            return True
        return self.exploration_over and p.rebuild_after_exploration and (moved_m > 0.0 or turned_rad > 0.0)

    def _judged_as_set(self, verdicts: list[Verdict]) -> tuple[list[Verdict], list[Verdict]]:
        """This job's verdicts with the closures the set refused, and the waiting closures it accepted.

        :func:`mazebot.slam.closure_set.judge` on the closures in the graph, the tentative
        ones (waiting from before and of this job) and this job's accepted ones.
        """
        new = [v for v in verdicts if v.accepted]
        waiting = list(self.set_waiting) + [v for v in verdicts if v.tentative]
        if not new and not waiting:
            return verdicts, []
        chain = Chain.from_edges(self.edges, self.poses.shape[0])
        decision = judge(list(self.set_members), waiting, new, chain, self.params.loop)
        refused = {(v.candidate.old, v.candidate.new): v for v in decision.refused}
        judged = [refused.get((v.candidate.old, v.candidate.new), v) if v.accepted else v for v in verdicts]
        return judged, decision.accepted


    def _anchor(self, start_turns: tuple[tuple[float, float], ...]) -> tuple[float, float] | None:
        """Keyframe 0's wall direction and std for the wall priors: as given, or judged from every board,
        together with what the closures to the start at rest measured (``start_turns``).

        Judged from every board, it is trusted as far as that fit says (never more than the
        anchor of exact walls): tied at ``wall_anchor_std_rad`` a direction 0.5° off turned the
        whole map by as much (the bench's hand-built 8×8 seeds 3 and 6). A closure to the start at
        rest counts as one keyframe's view of the walls (``wall_prior_std_rad``), whatever its
        match's information: the new keyframe's scan is taken moving and de-skewed by odometry (in
        the bench's exact 6×6 scripted seed 3, turning at 0.93 rad/s, its heading stood 0.54° off the
        truth where ICP said 0.14°, and taken at that std it turned the whole map by 0.5°).
        """
        anchor = self.anchor_wall
        if self.start_faces is not None and self.wall_reference_rad is not None:
            links = heading_links(self.edges, len(self.keyframes)) if self.params.anchor_links else None
            judged = start_anchor_fit(self.start_faces, self.keyframes, self.poses, self.wall_reference_rad, links,
                                      judge_boards=self.params.anchor_start_view)
            floor = self.params.wall_anchor_std_rad
            anchor = None if judged is None else (judged.direction_rad, max(judged.std_rad, floor))
            anchor = self._with_start_view(anchor, judged)
        turns = [(direction, max(std, self.params.wall_prior_std_rad)) for direction, std in start_turns]
        if not turns:
            return anchor
        return _mean_turn(turns + ([] if anchor is None else [anchor]), self.params.wall_anchor_std_rad)

    def _with_start_view(
        self, anchor: tuple[float, float] | None, judged: StartFit | None
    ) -> tuple[float, float] | None:
        """The anchor judged from every board, joined by the start's own view of square walls (``anchor_start_view``).

        Where keyframe 0's faces at rest lie on one grid, their mean is a reading of the maze's grid
        with a std of its own (:func:`mazebot.slam.start_anchor.start_view_rad`), the boards' own turn
        as every keyframe's faces show it included (before the fit has any, a board set by hand's).
        The judged fit reads the start's boards too: the two are joined at the covariance of that
        shared turn (:func:`mazebot.slam.start_anchor.joined_with_view`). Faces that turn apart
        (boards set by hand) leave the judged anchor as it is, and so does the option off.

        The view is taken only while the boards' own turn, as every keyframe's faces show it, is
        within ``wall_max_face_spread_rad``: the same bound that tells the start's faces of walls set
        square from boards set by hand, here read from hundreds of stretches instead of two to four.
        A hand-built maze whose start's few boards happen to lie square among themselves (its boards'
        turn 0.6-0.9°) then keeps the judged anchor, as with the option off; before any stretch is
        seen again the estimate is the prior's (a board set by hand), so the first jobs keep it too.
        """
        if not self.params.anchor_start_view or self.start_faces is None:
            return anchor
        board_std = BOARD_TURN_STD_RAD if judged is None or judged.board_std_rad is None else judged.board_std_rad
        if board_std > self.params.wall_max_face_spread_rad:
            return anchor  # boards turned as by hand: the start's few are no better a reading than the fit's
        view = start_view_rad(self.start_faces, self.params.wall_max_face_spread_rad, board_std)
        if view is None:
            return anchor
        floor = self.params.wall_anchor_std_rad  # two faces in line by chance say nothing tighter than this
        view = (view[0], max(view[1], floor))
        if anchor is None or judged is None or judged.view_board_share is None:
            return view
        return joined_with_view(anchor, view, board_std**2 * judged.view_board_share, floor)

    def _fit_to_reuse(self) -> tuple[PitchFit, int] | None:
        """The known lattice fit (and its keyframes) if the walls fitted it and the keyframes grew little since.

        A lattice that did not fit is looked for again every job (a maze that fits shows it as
        soon as it can); the final job (``rebuild_anyway``) fits afresh for the map it rebuilds.
        """
        if self.known_fit is None or self.rebuild_anyway:
            return None
        fit, keyframes = self.known_fit
        if not fit.fits or len(self.keyframes) >= LATTICE_REFIT_GROWTH * keyframes:
            return None
        return self.known_fit


@dataclass(frozen=True)
class SlamUpdate:
    """What one :meth:`Slam.update` did.

    ``pose`` (3,) and ``covariance`` (3×3) are the filter's map-frame estimate at the end
    of the revolution (``time_s``); ``map_from_odom`` (3,) the correction from the
    odometry frame; ``match`` the ICP result (None for the first scan), ``matched``
    whether the filter used it; ``keyframe`` the index of the keyframe the scan became,
    or None; ``loop_job`` work for an executor (background mode); ``verdicts`` the loop
    closure checks applied during this update (inline mode).
    """

    time_s: float
    pose: np.ndarray
    covariance: np.ndarray
    map_from_odom: np.ndarray
    match: IcpResult | None
    matched: bool
    keyframe: int | None
    points: int
    loop_job: LoopClosureJob | None = None
    verdicts: tuple[Verdict, ...] = ()
    map_rebuilt: bool = False


@dataclass(frozen=True)
class Relocalization:
    """Where a revolution was found in a map the Slam already had: its map pose, and how well it matched."""

    pose: np.ndarray  # (3,) map pose at the end of the revolution
    accepted: bool
    fitness: float
    rmse_m: float
    tried: int  # ICP starts tried


#: Finds the first revolution in the map a Slam was given (a resumed run): ``locate(slam, scan, odometry)``.
#: It places the Slam with :meth:`Slam.start_in_map` and says where it found the revolution.
FirstRevolutionLocator = Callable[["Slam", Scan, OdometrySource], Relocalization]


@dataclass(frozen=True)
class SlamUpdated:
    """What a listener of :attr:`SlamTaps.on_update` is told: the Slam, what it consumed, what it made of it."""

    slam: Slam
    scan: Scan
    odometry: OdometrySource
    update: SlamUpdate


@dataclass(frozen=True)
class SlamApplied:
    """What :attr:`SlamTaps.on_apply` listeners are told: a loop-closure result merged, and if it replaced the grid."""

    slam: Slam
    result: LoopClosureResult
    rebuilt: bool


@dataclass
class SlamTaps:
    """Where a :class:`Slam` lets others watch what it consumed, and when (:mod:`mazebot.taps`).

    A recording must let replay take exactly the steps the live SLAM took: which revolutions
    it processed (some are dropped when SLAM is behind), with odometry up to which reading,
    and after how many scans each loop-closure result (computed in a thread) was merged.
    Each tap is a tuple of listeners, called when the step has ended (``on_update`` after
    :meth:`Slam.update_steps`, ``on_final_job`` when :meth:`Slam.final_job` hands out a job,
    ``on_apply`` after :meth:`Slam.apply_steps`); the method itself does not change. A listener
    watches, it never steers: what it raises is logged and dropped (:func:`mazebot.taps.notify`).

    Example::

        slam.taps.on_update += (lambda seen: print(seen.update.pose),)
    """

    on_update: tuple[Callable[[SlamUpdated], None], ...] = ()
    on_final_job: tuple[Callable[[Slam], None], ...] = ()
    on_apply: tuple[Callable[[SlamApplied], None], ...] = ()


@dataclass(frozen=True)
class ClosureRecord:
    """An accepted loop closure: keyframe ``new`` seen from ``old``, and when they were taken."""

    old: int
    new: int
    old_time_s: float
    new_time_s: float
    measurement: np.ndarray
    by_set: bool = False  # a tentative closure the set accepted (mazebot.slam.closure_set)
    # the edge's information (3×3, ``new``'s frame) when it leaves a direction free (a degenerate match), else None
    free_information: np.ndarray | None = None


class Slam:
    """ICP pose-graph SLAM with an EKF front end, loop closure and an occupancy grid.

    Example::

        slam = Slam(SlamParams.from_config(cfg.slam, cfg.lidar, cfg.planner))
        for scan in scans:
            update = slam.update(scan, odometry_history)
        slam.pose, slam.grid.three_state(), slam.keyframe_poses()
    """

    def __init__(
        self,
        params: SlamParams | None = None,
        initial_pose: np.ndarray | None = None,
        *,
        background: bool = False,
        record_trajectory: bool = True,
        before_update: Callable[[Scan], None] | None = None,
        locate_first: FirstRevolutionLocator | None = None,
    ) -> None:
        self.params = params or SlamParams()
        #: the fault-injection seam (the simulator's ``slam-raise``, tests): called with each
        #: revolution before :meth:`update_steps` touches any state; what it raises, the update
        #: raises, as a bug in a stage would. None (the robot) costs one test per revolution.
        self.before_update = before_update
        #: a Slam given a map before its first revolution (:meth:`continue_map`, a resumed run)
        #: finds that revolution in it with this function first (:func:`mazebot.persist.resume.relocalize`)
        self.locate_first = locate_first
        self.relocalization: Relocalization | None = None  # what ``locate_first`` found
        self.taps = SlamTaps()
        self.background = background
        self.record_trajectory = record_trajectory  # keep every scan's pose for trajectory() (offline tools)
        self.initial_pose = np.zeros(3) if initial_pose is None else np.array(initial_pose, dtype=np.float64)
        p = self.params
        self.ekf = PoseEkf(self.initial_pose, p.initial_std, p.motion, p.filter_gate_chi2)
        self.calibration = HeadingCalibration(
            p.calibration_memory_scans, limit=p.calibration_limit, false_alarm=p.calibration_false_alarm
        )
        self.distance_calibration = DistanceCalibration(
            p.calibration_memory_scans, limit=p.calibration_limit, step_noise_m=p.distance_step_noise_m
        )
        self.lever_arm = LeverArmCalibration(
            p.calibration_memory_scans, false_alarm=p.calibration_false_alarm, held=p.lever_arm_held
        )
        self.time_offset = TimeOffsetCalibration(p.lidar_time_offset_s)
        self.grid = p.grid.new_grid()
        self.graph = PoseGraph()
        self.keyframes: list[Keyframe] = []
        self.selector = KeyframeSelector(p.keyframe_distance_m, p.keyframe_angle_rad)
        self.target: Target | None = None
        self.closures: list[ClosureRecord] = []
        self.rejections: Counter[str] = Counter()
        self.job_running = False
        self.scans = 0
        self.matched_scans = 0
        self.searches = 0  # correlative searches run (sequential matches)
        self.searches_won = 0  # ... whose match replaced ICP's from the prediction
        self.searches_any_heading = 0  # ... searched again over every heading, the window's having found nothing
        self.matches_doubted = 0  # ... run because ICP's residual stood out of the recent matches' (match_residuals)
        self.doubts_won = 0  # ... and whose match replaced that one
        # the recent matches' residuals: the doubt, match_residual_ratio and the every-heading search judge by them
        self._residuals = MatchResiduals(p.match_doubt_ratio, p.match_doubt_scans)
        self.closures_downweighted = 0  # loop closures the last optimization all but switched off
        self.closures_from_set = 0  # loop closures a set accepted after the thresholds refused them
        # closures verified as a set: recent ones in the graph, and tentative ones waiting (closure_set)
        self._set_members: list[Verdict] = []
        self._set_waiting: list[Verdict] = []
        self._search_due = False  # the next match searches (the robot was just re-localized)
        self._motion_unknown = False  # the next scan's odometry step is unknown (expect_unknown_motion)
        self._search_any_heading = False  # ... so its search spans every heading
        # per-edge variances of the sequential chain (loop closure search radius)
        self._edge_var_xy: list[float] = []
        self._edge_var_theta: list[float] = []
        self._last_odom: np.ndarray | None = None
        self._last_matched_pose: np.ndarray | None = None  # filter pose after the previous scan, if matched
        self._last_travel_fixed_pose: np.ndarray | None = None  # ... if its match fixed the direction of travel
        # the odometry noise learnt from the matches ([slam.motion] estimate), and the previous scan's
        # own match pose (not the filter's, which the odometry pulls towards itself)
        self.odometry_noise = OdometryNoiseEstimate(p.motion) if p.motion.estimate else None
        self._last_match_pose: np.ndarray | None = None
        self._last_rate: float | None = None  # odometry turn rate at the previous scan's end
        self._odom_at_keyframe: np.ndarray | None = None
        self._last_match: IcpResult | None = None
        self._keyframes_since_attempt = 0
        self._keyframes_since_optimization = 0
        self._pending_candidates: list[Candidate] = []
        self._verifying: list[Candidate] = []  # the candidates of the loop-closure job running
        self.wall_reference_rad: float | None = None  # the maze's wall grid in the map frame (mod 90°)
        self.lattice_fit: PitchFit | None = None  # the last lattice the walls were fitted to
        self._lattice_fit_keyframes = 0  # ... and how many keyframes it was fitted with
        self._lattice_on: bool | None = None  # whether the lattice priors are on, once looked for
        # keyframe 0's revolutions at rest, and the wall directions (robot frame) of those that show a grid
        self._anchor_revolutions = 0
        self._anchor_walls: list[float] = []
        # keyframe 0's surface (points, normals) of each revolution at rest, until its faces are judged
        self._anchor_surfaces: list[tuple[np.ndarray, np.ndarray]] = []
        self._anchor_spread: tuple[float | None] | None = None  # the faces' spread, once judged
        self._start_faces: Faces | None = None  # ... and the faces themselves (keyframe 0's frame)
        self._rest_surface: tuple[np.ndarray, np.ndarray] | None = None  # ... and the surfaces pooled (voxel filter)
        self._start_turns: tuple[tuple[float, float], ...] = ()  # the anchor the closures to them measured
        self._anchor_closed = False  # the robot moved: keyframe 0 keeps what it has measured
        self._target_position: np.ndarray | None = None
        self._target_keyframes: list[int] = []  # the keyframes the local submap was built from
        self.matches_seen_rescued = 0  # sequential matches counted by their inliers where the submap saw
        self.matches_widened = 0  # sequential matches whose basin did not hold along their weakest direction
        self.degenerate_retries = 0  # degenerate sequential matches tried again along their free direction
        self.degenerate_retries_won = 0  # ... and replaced by a restart that fixed every direction
        self._keyframes_since_target = 0
        # every scan's pose relative to the keyframe before it: the trajectory follows optimizations
        self._scan_log: list[tuple[float, int, np.ndarray]] = []

    # -- reading -----------------------------------------------------------------------

    @property
    def pose(self) -> np.ndarray:
        """Current map-frame pose estimate (3,) at the last scan's time."""
        return self.ekf.mean.copy()

    @property
    def covariance(self) -> np.ndarray:
        return self.ekf.covariance.copy()

    @property
    def map_from_odom(self) -> np.ndarray:
        """The correction (3,) from the odometry frame to the map frame after the last scan."""
        if self._last_odom is None:
            return self.initial_pose.copy()
        return compose(self.ekf.mean, inverse(self._last_odom))

    @property
    def anchored(self) -> bool:
        """Keyframe 0, the map's anchor, is final: measured over ``anchor_revolutions`` at rest, or the robot moved.

        The planner waits for it before it drives (a resumed map is anchored already).
        """
        if not self.keyframes:
            return False
        revolutions = self._anchor_revolutions
        return (
            len(self.keyframes) > 1
            or self._anchor_closed
            or revolutions == 0
            or revolutions >= self.params.anchor_revolutions
        )

    @property
    def anchor_revolutions(self) -> int:
        """How many revolutions at rest keyframe 0 measured its walls over (0 for a resumed map)."""
        return self._anchor_revolutions

    @property
    def anchor_wall_rad(self) -> float | None:
        """Keyframe 0's wall direction in its own frame (mod 90°), averaged at rest (None: < 2 usable revolutions)."""
        if len(self._anchor_walls) < 2:
            return None
        four = 4.0 * np.asarray(self._anchor_walls)
        return 0.25 * math.atan2(float(np.mean(np.sin(four))), float(np.mean(np.cos(four))))

    @property
    def anchor_face_spread_rad(self) -> float | None:
        """How far the wall faces keyframe 0 saw at rest turn apart (RMS, radians; None: fewer than two faces).

        :func:`mazebot.slam.wall_faces.face_spread` of its revolutions' surfaces pooled (the
        robot stood still), measured against the anchor's wall direction. Judged once, when
        keyframe 0 is final (:attr:`anchored`); None before.
        """
        if self._anchor_spread is None:
            direction = self.anchor_wall_rad
            if not self.anchored or direction is None:
                return None
            points = np.concatenate([pts for pts, _ in self._anchor_surfaces])
            normals = np.concatenate([nrm for _, nrm in self._anchor_surfaces])
            faces = wall_faces(points, normals, direction, steps=self.params.rest_face_steps)
            self._start_faces = faces
            first = voxel_downsample(points, self.params.submap_voxel_m)
            self._rest_surface = (points[first], normals[first])
            self._anchor_spread = (face_spread(quarter_turns(faces.normal_rad - direction), faces.count),)
            self._anchor_surfaces = []
            spread = self._anchor_spread[0]
            if spread is not None and spread > self.params.wall_max_face_spread_rad:
                log.info("the wall faces seen from the start turn %.2f deg apart (RMS): boards set by hand; "
                         "the start anchors the wall grid through every board the map sees", math.degrees(spread))
        return self._anchor_spread[0]

    @property
    def anchor_on_grid(self) -> bool:
        """Keyframe 0's faces at rest lie on one grid (or are too few to tell): a maze of exact walls.

        Either way the loop-closure jobs judge the anchor from every keyframe's faces once keyframe 0
        has two of them (:meth:`_make_job`); this only tells the two kinds of maze apart.
        """
        spread = self.anchor_face_spread_rad
        return spread is None or spread <= self.params.wall_max_face_spread_rad

    def keyframe_poses(self) -> np.ndarray:
        """Poses (N, 3) of all keyframes, optimized."""
        return np.array([kf.pose for kf in self.keyframes]).reshape(-1, 3)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Times (S,) and map-frame poses (S, 3) of every scan, following the optimized keyframes.

        Empty unless the Slam was made with ``record_trajectory=True`` (the default).
        """
        times = np.array([t for t, _, _ in self._scan_log])
        poses = np.array(
            [compose(self.keyframes[k].pose, rel) for _, k, rel in self._scan_log]
        ).reshape(-1, 3)
        return times, poses

    # -- the method ----------------------------------------------------------------------

    def update_steps(
        self, scan: Scan, odometry: OdometrySource, *, paint: bool | PaintDecision = True
    ) -> Generator[None, None, SlamUpdate]:
        """:meth:`update` in stages: a generator that yields between them and returns the update.

        The daemon's SLAM task lets the event loop run between two stages (the 20 Hz
        control tick must not wait for a whole keyframe scan: up to ~20 ms with the submap
        rebuild); offline tools call :meth:`update`, which runs every stage at once. The
        stages are the same computation in the same order either way, so the result is
        the same; between two of them SLAM's state is consistent (a keyframe is in the
        list, the graph and the selector together), only the new submap may still be
        under construction. Who wants to see each update listens on ``taps.on_update``.
        """
        if self.before_update is not None:
            self.before_update(scan)
        if self.locate_first is not None and self.relocalization is None and self.keyframes:
            # 0. a map given beforehand (a resumed run): find the first revolution in it
            self.relocalization = self.locate_first(self, scan, odometry)
            yield
        update = yield from self._update_stages(scan, odometry, paint)
        if self.taps.on_update:
            notify(self.taps.on_update, SlamUpdated(self, scan, odometry, update), "slam.on_update")
        return update

    def _update_stages(
        self, scan: Scan, odometry: OdometrySource, paint: bool | PaintDecision
    ) -> Generator[None, None, SlamUpdate]:
        """Steps 1-7 of the method (the module's docstring), yielding between them."""
        p = self.params
        # 1. de-skew: every sample into the robot frame at the end of the revolution, at the
        # lidar's stamps shifted by the learned offset; the odometry pose at that end
        prepared, odom = self.prepare(scan, odometry)
        time_s = prepared.time_s
        rate = _turn_rate(odometry, time_s)
        self.scans += 1

        # 2. predict: the odometry increment since the last scan moves the filter
        raw_increment = calibrated_increment = predicted_increment = None
        if self._last_odom is None:
            self.ekf.reset(compose(self.initial_pose, odom), self.ekf.covariance)
        else:
            raw_increment = relative_pose(self._last_odom, odom)
            calibrated_increment = self.distance_calibration.correct(self.calibration.correct(raw_increment))
            predicted_increment = self.lever_arm.correct(calibrated_increment)
            self.ekf.predict(predicted_increment)
        if self._motion_unknown:
            self._forget_motion()
        self._last_odom = odom
        yield

        # 3. match against the local submap, from the prediction (and from turned guesses if that fails)
        match = None
        if self.target is not None and len(self.target) and prepared.points_match.shape[0]:
            match = yield from self._match_steps(prepared)
        self._search_any_heading = False  # (a scan without points or submap searched nothing)

        # 4. correct the filter (unobserved directions keep the odometry)
        matched = False
        predicted_theta = float(self.ekf.mean[2])
        good_match = match is not None and self.acceptable(match)
        if match is not None and good_match and p.basin_probe_m > 0.0:
            assert self.target is not None
            match, widened_m2 = yield from probed_steps(
                self.target, prepared.points_match, match, p.basin_probe_m, p.icp, self.ekf.covariance,
                prepared.sensor_xy,
            )
            self.matches_widened += int(widened_m2 > 0.0)
        if match is not None and good_match and p.match_deskew_variance and predicted_increment is not None:
            match = self._deskewed(match, predicted_increment, predicted_theta)
        if match is not None and good_match:
            matched = self.ekf.correct(match.pose, match.information * p.match_information_scale)
        if callable(paint):
            paint = bool(paint(match, matched))
        if paint and match is not None and good_match and p.estimate_time_offset and self._last_rate is not None:
            # a turn starting or stopping shows a stamp offset (even when the filter's gate refused the match)
            self.time_offset.observe(float(match.pose[2]) - predicted_theta, rate - self._last_rate)
        self._last_rate = rate
        self.matched_scans += matched
        if matched and match is not None:
            self._residuals.add(match.rmse_m)
        self._last_match = match if matched else None
        pose = self.ekf.mean.copy()
        if (paint and matched and raw_increment is not None and calibrated_increment is not None
                and self._last_matched_pose is not None):
            matched_step = relative_pose(self._last_matched_pose, pose)
            if p.calibrate_heading:
                self.calibration.observe(raw_increment, matched_step)
            if p.calibrate_lever_arm:
                self.lever_arm.observe(calibrated_increment, matched_step)
        self._last_matched_pose = pose if matched else None
        if p.calibrate_distance:
            self._observe_distance(match if matched and paint else None, raw_increment)
        if self.odometry_noise is not None:
            self._learn_odometry_noise(match if matched and paint else None, predicted_increment)

        yield

        # 5. keyframe: into the pose graph, and a new local submap
        rays = map_rays(prepared, p.map_max_range_m, p.map_smoothing, p.range_noise_rel, p.map_hit_depth_m)
        keyframe = None
        if not paint:
            pass  # localizing only: the map and the graph stay as they are
        elif self._standing_at_anchor(odom):
            self._measure_anchor(prepared, rays)  # one more revolution of keyframe 0's walls, still at its pose
        elif self.selector.is_keyframe(pose):
            keyframe = self._add_keyframe(pose, odom, prepared, rays)
        if self.record_trajectory and self.keyframes:
            self._scan_log.append((time_s, len(self.keyframes) - 1, relative_pose(self.keyframes[-1].pose, pose)))
        if keyframe is not None and self._target_due(pose):
            yield
            yield from self._rebuild_target_steps()
        yield

        # 6. update the grid with the scan's rays at the corrected pose
        if paint:
            ends, hit, origins = rays
            self.grid.integrate(pose, transform_points(pose, ends), hit, transform_points(pose, origins))
        if keyframe is not None:
            yield

        # 7. close loops: candidates by distance and drift, strict verification, optimization, rebuilt map
        job = self._loop_closure_job() if keyframe is not None else None
        verdicts: tuple[Verdict, ...] = ()
        rebuilt = False
        if job is not None and not self.background:
            result = job.run()
            verdicts = tuple(result.verdicts)
            rebuilt = self.apply(result)
            job = None
        elif job is not None:
            self.job_running = True
        pose = self.ekf.mean.copy()
        return SlamUpdate(
            time_s=time_s,
            pose=pose,
            covariance=self.ekf.covariance.copy(),
            map_from_odom=compose(pose, inverse(odom)),
            match=match,
            matched=matched,
            keyframe=keyframe,
            points=int(prepared.points_full.shape[0]),
            loop_job=job,
            verdicts=verdicts,
            map_rebuilt=rebuilt,
        )

    update = all_at_once_method(
        update_steps,
        """Process one revolution; ``odometry`` gives odometry poses at any recent time.

        ``paint=False`` (the odometry is known bad: a wheel slips, an encoder was dead, the robot
        was just found again): the revolution only localizes the robot against the map as it is.
        No keyframe, no grid update, and no calibration learnt from the bad odometry: a revolution
        de-skewed and predicted with wrong wheel motion would put its walls in the wrong place.
        A callable decides once the revolution is matched: ``paint(match, matched)`` (the SLAM task
        asks whether ICP had to move the odometry's prediction far, i.e. a wheel slips right now).
        """,
    )

    def _note_lattice(self, fit: PitchFit | None, keyframes: int) -> None:
        """Keep the lattice fit (fitted with ``keyframes``), and log when the lattice priors switch on or off."""
        if fit is None:
            return
        self.lattice_fit = fit
        self._lattice_fit_keyframes = keyframes
        if fit.fits == self._lattice_on:
            return
        if fit.fits:
            log.info("walls fit a lattice of pitch %.4f m (%d x %d lines, %.0f %% of the faces): lattice priors on",
                     fit.pitch_m, fit.lines[0], fit.lines[1], 100 * fit.fit)
        elif self._lattice_on is None or fit.measured:
            log.info("walls do not fit a lattice (%d x %d lines, %.0f %% of the faces on one): lattice priors off",
                     fit.lines[0], fit.lines[1], 100 * fit.fit)
        self._lattice_on = fit.fits

    def apply_steps(self, result: LoopClosureResult) -> Generator[None, None, bool]:
        """:meth:`apply` in stages (as :meth:`update_steps`): the new submap and the late keyframes' rays.

        The keyframes and the filter move in the first stage, together; the old grid stays
        the published one until the new one has every keyframe. Listeners of ``taps.on_apply``
        are told once it is merged.
        """
        rebuilt = yield from self._apply_stages(result)
        if self.taps.on_apply:
            notify(self.taps.on_apply, SlamApplied(self, result, rebuilt), "slam.on_apply")
        return rebuilt

    def _apply_stages(self, result: LoopClosureResult) -> Generator[None, None, bool]:
        """The merge of :meth:`apply_steps`, yielding between its stages."""
        self.job_running = False
        self._verifying = []
        by_set = {(v.candidate.old, v.candidate.new) for v in result.set_accepted}
        for v in result.verdicts:
            if not v.accepted:
                if (v.candidate.old, v.candidate.new) in by_set:
                    continue  # this job's tentative closure, accepted by the set: below
                self.rejections[v.reason] += 1
                if v.tentative:
                    self._set_waiting.append(v)
                continue
            self._add_closure(v)
        for v in result.set_accepted:
            earlier = [w for w in self._set_waiting if (w.candidate.old, w.candidate.new) == (v.candidate.old,
                                                                                           v.candidate.new)]
            for w in earlier:  # counted as a rejection when it came: it is a closure now
                self.rejections[w.reason] -= 1
                if self.rejections[w.reason] <= 0:
                    del self.rejections[w.reason]
                self._set_waiting.remove(w)
            self.closures_from_set += 1
            self._add_closure(v)
        if self.params.loop.set_verify:
            oldest = len(self.keyframes) - 1 - self.params.loop.set_window_keyframes
            self._set_members = [v for v in self._set_members if v.candidate.new >= oldest]
            self._set_waiting = [v for v in self._set_waiting if v.candidate.new >= oldest]
        self._note_lattice(result.lattice_fit, result.lattice_fit_keyframes)
        self._start_turns = result.start_turns or self._start_turns
        if result.poses is None:
            return False
        self.closures_downweighted = result.downweighted
        if result.wall_reference_rad is not None:
            self.wall_reference_rad = result.wall_reference_rad
        count = result.poses.shape[0]
        last_old = self.keyframes[count - 1].pose
        correction = compose(result.poses[count - 1], inverse(last_old))  # map_new ← map_old, for later keyframes
        for k, kf in enumerate(self.keyframes):
            kf.pose = result.poses[k].copy() if k < count else compose(correction, kf.pose)
        self.graph.vertices = self.keyframe_poses()
        self.ekf.reset(compose(correction, self.ekf.mean))
        self._last_matched_pose = None  # the map moved under the filter: no calibration sample
        self._last_travel_fixed_pose = None  # ... nor a distance one
        self._last_match_pose = None  # ... nor an odometry noise sample
        if self.selector.last is not None:
            self.selector.accept(compose(correction, self.selector.last))
        yield
        yield from self._rebuild_target_steps()
        if result.grid is None:
            return False
        grid = result.grid
        for kf in self.keyframes[count:]:  # added while the job ran
            yield
            pose, ends, hit, origins = kf.rays()
            grid.integrate(pose, transform_points(pose, ends), hit, transform_points(pose, origins))
        for kf in self.keyframes:
            kf.integrated_pose = kf.pose.copy()
        grid.generation = self.grid.generation + 1
        grid.take_dirty()  # clients reload the whole map on a new generation
        self.grid = grid
        return True

    def _add_closure(self, v: Verdict) -> None:
        """An accepted loop closure into the pose graph and the list of closures (and the set's members)."""
        c = v.candidate
        self.graph.add_edge(c.old, c.new, v.measurement, v.information)
        self.closures.append(
            ClosureRecord(c.old, c.new, self.keyframes[c.old].time_s, self.keyframes[c.new].time_s, v.measurement,
                          by_set=v.reason == ACCEPTED_BY_SET,
                          free_information=v.information if ObservedDirections.of(v.information).dof < 3 else None)
        )
        if self.params.loop.set_verify:
            self._set_members.append(v)

    apply = all_at_once_method(
        apply_steps,
        """Merge a finished loop-closure job; returns True if the grid was replaced.

        Keyframes added while the job ran keep their pose relative to the newest
        keyframe of the snapshot, so the whole recent trajectory follows the correction.
        """,
    )

    def continue_map(
        self,
        keyframes: Sequence[Keyframe],
        graph: PoseGraph,
        grid: OccupancyGrid,
        *,
        wall_reference_rad: float | None,
        chain_variances: Sequence[tuple[float, float]],
    ) -> None:
        """Start from a map made before (a resumed run): its keyframes, pose graph, grid and wall direction.

        Call it before the first revolution. ``chain_variances`` are the (xy in m², heading in
        rad²) variances of the sequential edges 0→1, 1→2, … (the loop-closure search radius
        grows with them along the chain). The next keyframe continues the graph, linked to the
        last given one; the keyframes' surfaces are computed with this Slam's normal parameters.
        """
        if len(chain_variances) != max(0, len(keyframes) - 1):
            raise ValueError(
                f"a chain of {len(keyframes)} keyframes has {max(0, len(keyframes) - 1)} sequential edges; "
                f"got {len(chain_variances)} variances"
            )
        if self.scans:
            raise RuntimeError(f"continue_map is for a Slam that has seen no revolution; this one saw {self.scans}")
        for kf in keyframes:
            kf.normal_params = self.params.normals
        self.keyframes = list(keyframes)
        self.graph = graph
        self.grid = grid
        self.wall_reference_rad = wall_reference_rad
        self._edge_var_xy = [float(xy) for xy, _ in chain_variances]
        self._edge_var_theta = [float(theta) for _, theta in chain_variances]

    def start_in_map(
        self,
        map_from_odom: np.ndarray,
        submap: Target | None = None,
        *,
        submap_xy: np.ndarray | None = None,
    ) -> None:
        """Before the first revolution: where the odometry frame lies in the map (a resumed run's start).

        The first revolution's map pose is then ``map_from_odom ⊕ odometry``. ``submap`` (built
        from the keyframes around the map position ``submap_xy``) is what it is matched
        against; None keeps the Slam's own choice (made at the next keyframe).
        """
        self.initial_pose = np.array(map_from_odom, dtype=np.float64)
        if submap is None:
            return
        if submap_xy is None:
            raise ValueError("a submap needs the map position it was built around (submap_xy)")
        self.target = submap
        self._target_keyframes = []  # built elsewhere: what its keyframes saw is not known here
        self._target_position = np.array(submap_xy[:2], dtype=np.float64)

    def relocalized(self, pose: np.ndarray, odom: np.ndarray) -> None:
        """The robot was found at map ``pose`` when the odometry read ``odom`` (:mod:`mazebot.slam.relocalize`).

        The filter restarts there and the submap is taken around it; the map and the
        graph stay as they are (the next keyframe links to the last one by its true pose).
        """
        pose = np.asarray(pose, dtype=np.float64)
        self.ekf.reset(pose, self.ekf.covariance)
        self._last_odom = np.asarray(odom, dtype=np.float64).copy()
        self._last_matched_pose = None
        self._last_travel_fixed_pose = None
        self._last_match_pose = None
        self._last_match = None
        self._target_position = None
        self._search_due = True
        self._rebuild_target()

    def expect_unknown_motion(self) -> None:
        """The odometry says nothing of the step to the next scan: it was silent while the laser went on.

        A log whose odometry has a hole (the Seattle log's scan 27: three seconds, an 80° turn,
        no odometry reading between the two scans) hands the SLAM a step of zero where the robot
        moved. Its prediction is then no prediction: the filter's covariance is widened to the
        whole correlative window in position and to every heading, the match is searched over
        that window and every heading (Olson's correlative search without a motion prior, ICRA
        2009), and the step teaches neither the odometry's calibration nor its noise (the raw
        increment is not what the wheels did).
        """
        self._motion_unknown = True

    def _forget_motion(self) -> None:
        """The prediction widened to everything the search can cover; no calibration or noise sample from this step."""
        self._motion_unknown = False
        search = self.params.correlative
        window_m = search.window_xy_m if search is not None else self.params.icp.max_correspondence_m
        widened = self.ekf.covariance + np.diag([window_m**2, window_m**2, math.pi**2])
        self.ekf.reset(self.ekf.mean, widened)
        self._search_due = True
        self._search_any_heading = search is not None
        self._last_matched_pose = None
        self._last_travel_fixed_pose = None
        self._last_match_pose = None

    def rebuild_map(self) -> OccupancyGrid:
        """Rebuild the grid from every keyframe at its current pose (offline tools, at the end)."""
        grid = self.params.grid.new_grid()
        grid.rebuild((kf.rays() for kf in self.keyframes), cell_offset_m=self.grid.cell_offset_m)
        for kf in self.keyframes:
            kf.integrated_pose = kf.pose.copy()
        grid.generation = self.grid.generation + 1
        self.grid = grid
        return grid

    # -- steps ---------------------------------------------------------------------------

    def _add_keyframe(
        self,
        pose: np.ndarray,
        odom: np.ndarray,
        prepared: PreparedScan,
        rays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> int:
        p = self.params
        index = len(self.keyframes)
        kf = Keyframe.from_scan(index, pose, prepared, p.normals, p.map_max_range_m, rays=rays)
        if index == 0:
            self._anchor_revolutions = 1
            self._anchor_walls = self._usable_walls(kf)
            self._anchor_surfaces = [kf.surface()]
        self.keyframes.append(kf)
        self.graph.add_vertex(pose)
        self.selector.accept(pose)
        if index > 0:
            prev = self.keyframes[index - 1]
            z = relative_pose(prev.pose, pose)
            info = self._sequential_information(z, odom)
            self.graph.add_edge(index - 1, index, z, info)
            cov = np.linalg.inv(info)
            self._edge_var_xy.append(0.5 * float(cov[0, 0] + cov[1, 1]))
            self._edge_var_theta.append(float(cov[2, 2]))
        self._odom_at_keyframe = odom
        self._keyframes_since_target += 1
        self._keyframes_since_optimization += 1
        if p.wall_prior and self.wall_reference_rad is None:
            direction, strength, count = kf.wall_direction()
            if strength >= p.wall_min_strength and count >= p.wall_min_normals:
                self.wall_reference_rad = wrap_quarter(direction + float(pose[2]))
        self._keyframes_since_attempt += 1
        return index

    def _target_due(self, pose: np.ndarray) -> bool:
        """The new keyframe at ``pose`` calls for a new local submap (moved far enough, or enough keyframes)."""
        p = self.params
        moved = (
            math.inf
            if self._target_position is None
            else math.hypot(pose[0] - self._target_position[0], pose[1] - self._target_position[1])
        )
        due = self._keyframes_since_target >= p.submap_update_keyframes
        return self.target is None or moved >= p.submap_update_m or due

    def _standing_at_anchor(self, odom: np.ndarray) -> bool:
        """Keyframe 0 is the only one, wants more revolutions, and the odometry has not moved since it."""
        p = self.params
        if len(self.keyframes) != 1 or self._anchor_closed or self._anchor_revolutions == 0:
            return False
        if self._anchor_revolutions >= p.anchor_revolutions or self._odom_at_keyframe is None:
            return False
        moved = relative_pose(self._odom_at_keyframe, odom)
        if math.hypot(float(moved[0]), float(moved[1])) > p.anchor_still_m or abs(float(moved[2])) > p.anchor_still_rad:
            self._anchor_closed = True  # the robot drives: keyframe 0 keeps what it has
            return False
        return True

    def _measure_anchor(self, prepared: PreparedScan, rays: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        """One more revolution at rest: its wall direction joins keyframe 0's average.

        One scan's wall direction is noisy (0.27° RMS at the start of the bench's mazes
        with the A1's 1 % range noise), and independent from one revolution to the next:
        20 revolutions average it down to 0.07° (``wall_prior`` tests). The robot has not
        moved, so the scan's own normals, in keyframe 0's frame, are all it takes (about a
        millisecond a revolution); keyframe 0 itself, its points and rays, stays the first
        scan (the grid has every revolution anyway).
        """
        p = self.params
        self._anchor_revolutions += 1
        kf = Keyframe.from_scan(0, self.keyframes[0].pose, prepared, p.normals, p.map_max_range_m, rays=rays)
        self._anchor_walls += self._usable_walls(kf)
        self._anchor_surfaces.append(kf.surface())
        direction = self.anchor_wall_rad
        if p.wall_prior and direction is not None:
            self.wall_reference_rad = wrap_quarter(direction + float(self.keyframes[0].pose[2]))

    def _usable_walls(self, kf: Keyframe) -> list[float]:
        """``[direction]`` if the keyframe's normals show the wall grid (as the wall priors require), else ``[]``."""
        p = self.params
        direction, strength, count = kf.wall_direction()
        return [direction] if strength >= p.wall_min_strength and count >= p.wall_min_normals else []

    def _closed_already(self, candidate: Candidate) -> bool:
        """A recent accepted closure, or one being verified, joins keyframes within ``closed_reach_keyframes``
        of both the candidate's.

        Driving back along a corridor it has mapped, the robot finds a candidate at every
        attempt (every ``attempt_every`` keyframes, 0.3 m), and verifying each is five ICP runs
        and a whole-graph optimization (25-30 ms of the worker's CPU a job, replaying a 6x6
        exploration on a quiet machine). The graph ties such a pair already: that closure and
        two chains of a few keyframes of scan matches. A candidate past the reach (the next
        attempt but one) is verified, so a revisited corridor still gets a closure every two
        attempts. The candidates of the job running count as closed (most are accepted):
        whether its result came back before the next attempt depends on the CPU, the skip
        does not. On that replay (explore seed 1): 27 closures -> 15, the jobs' CPU roughly
        halved, the live estimate's ATE RMS 2.18 -> 2.22 mm (max 5.24 both).
        """
        reach = self.params.loop.closed_reach_keyframes
        closing = [(c.old, c.new) for c in self.closures[-PENDING_CANDIDATES:]]
        closing += [(c.old, c.new) for c in self._verifying]
        return reach > 0 and any(
            abs(candidate.new - new) <= reach and abs(candidate.old - old) <= reach for old, new in closing
        )

    def _in_sight(self, a: np.ndarray, b: np.ndarray) -> bool:
        """No wall of the map between two positions (the line between them crosses no occupied cell)."""
        rows, cols = _segment_cells(self.grid, a, b)
        shape = self.grid.shape
        inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
        return not bool((self.grid.log_odds[rows[inside], cols[inside]] > self.grid.occupied_logodds).any())

    def acceptable(self, match: IcpResult) -> bool:
        """A match good enough by SLAM's own limits (converged, inlier ratio, residual).

        With ``match_residual_ratio`` the residual must also stay within that many times the recent matched
        scans' median (:mod:`mazebot.slam.match_residuals`): one limit adapted to how well the run's right
        matches fit, rather than ``max_match_rmse_m`` alone (1 m on the laser logs).
        """
        p = self.params
        return (match.converged and match.fitness >= p.min_match_fitness and match.rmse_m <= p.max_match_rmse_m
                and not self._residuals.in_doubt(match.rmse_m, p.match_residual_ratio))

    def usable(self, match: IcpResult) -> bool:
        """A sequential match that needs no second look: :meth:`acceptable`, and turned from the prediction no
        further than the prediction's own heading uncertainty allows (:meth:`heading_plausible`)."""
        return self.acceptable(match) and self.heading_plausible(match)

    def heading_plausible(self, match: IcpResult) -> bool:
        """Is ``match``'s heading within ``match_heading_sigmas`` standard deviations of the prediction's?

        Called between the filter's prediction (step 2) and its correction (step 4), while
        the filter holds the prediction. ICP's own checks judge how well the scan fits
        where ICP stopped, not whether it stopped in the right basin: a scan that sees much
        the submap does not (a doorway, a corridor's end) can fit a wrong alignment tens of
        degrees off with a smaller residual than the right one. The prediction's heading
        variance is the odometry's noise as learnt from the matches
        (:mod:`mazebot.slam.odometry_noise`) on top of the last corrected pose's; the
        match's own claim is left out (ICP's Hessian is several times too sure of itself).
        A turn of ``k`` standard deviations is the innovation gate of a Kalman filter on the
        heading alone (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to
        Tracking and Navigation*, 2001, 5.7): at ``k`` = 4 a Gaussian prediction falls
        outside once in 16 000 scans.

        The gate picks between alignments, it does not veto the scan: a match beyond it
        sends the scan to the correlative search and the heading retries (:meth:`_match_steps`),
        and one of theirs within it replaces it; where none is, the match stands. The
        odometry's tails are heavier than a Gaussian's (on the Intel log with white noise of
        0.1 the prediction's heading error against the corrected poses' increments passed 4
        standard deviations on 1 of 903 scans, where every ICP run agreed on the right
        match), and an edge of odometry alone 16° off is a hinge the closures must bend back.
        """
        k = self.params.match_heading_sigmas
        if k <= 0.0:
            return True
        turn_rad = float(wrap_angle(float(match.pose[2]) - float(self.ekf.mean[2])))
        return turn_rad * turn_rad <= k * k * float(self.ekf.covariance[2, 2])

    def _match_steps(self, prepared: PreparedScan) -> Generator[None, None, IcpResult]:
        """:meth:`_match`, yielding before each retry (a scan that needs them costs up to five ICP runs).

        With ``params.correlative``, a prediction that is uncertain is checked by a
        correlative search over a window about it (:meth:`_search_steps`) before the
        heading retries; with ``params.degenerate_retry_sigmas``, a match ICP left
        degenerate is tried again along its free direction (:meth:`_degenerate_retry_steps`).
        """
        match = yield from self._predicted_match_steps(prepared)
        if self.params.degenerate_retry_sigmas > 0.0 and match.degenerate and self.acceptable(match):
            yield
            match = yield from self._degenerate_retry_steps(prepared, match)
        return match

    def _predicted_match_steps(self, prepared: PreparedScan) -> Generator[None, None, IcpResult]:
        """ICP from the prediction, the correlative search and the heading retries where it is in doubt."""
        p = self.params
        assert self.target is not None
        guess = self.ekf.mean
        match = yield from match_scan_steps(
            self.target, prepared.points_match, guess, p.icp, sensor_xy=prepared.sensor_xy
        )
        if p.correlative is not None and self._search_wanted(match, guess):
            yield
            match = yield from self._search_steps(prepared, guess, match)
        if p.correlative is not None and self.usable(match) and self._residuals.in_doubt(match.rmse_m):
            yield
            match = yield from self._doubt_steps(prepared, guess, match)
        if self.usable(match) or not p.retry_headings_rad:
            return match
        best = None
        for turn in p.retry_headings_rad:
            yield
            start = guess + np.array([0.0, 0.0, turn])
            retry = yield from match_scan_steps(
                self.target, prepared.points_match, start, p.icp, sensor_xy=prepared.sensor_xy, prior_pose=guess
            )
            if self._better_retry(retry, best):
                best = retry
        if best is not None and (self.usable(best) or not self.acceptable(match)):
            return best
        if not self.acceptable(match) and p.match_overlap_fitness:
            return self._judged_where_seen(prepared, match)
        return match  # acceptable but turned beyond the gate, and no match within it: the scan's evidence stands

    def _degenerate_retry_steps(self, prepared: PreparedScan, match: IcpResult) -> Generator[None, None, IcpResult]:
        """``match`` matched again from the prediction moved along the direction ICP left free, where that fixes it.

        ICP's degeneracy test (the Hessian's eigenvalue ratio; Zhang, Kaess and Singh, "On
        degeneracy of optimization-based state estimation problems", ICRA 2016) is taken where
        ICP stopped, and what it sees from there depends on where it started. Along a corridor
        a few door frames and alcoves fix the position only within a few centimetres of the
        right one: started a prediction's error away (the odometry's noise over a metre's
        step), their points pair with the side walls' lines or fall outside the robust kernel,
        the direction looks unobservable, it is kept at the prediction, and the map takes the
        odometry's length there, a random error per corridor that white noise does not average
        out. Restarted from the right place the same scan and submap fix every direction to a
        few millimetres, with a smaller residual. So ICP is started again from the prediction
        moved along the free direction by whole multiples of the prediction's standard
        deviation along it (the filter's covariance: the learnt odometry noise), each way, up
        to ``degenerate_retry_sigmas``. A restart that ends acceptable, not degenerate, within
        the heading gate, no farther along than one more standard deviation, and with a
        residual markedly under the degenerate match's (:data:`DEGENERATE_RETRY_RMSE_SHARE`)
        replaces it (the smallest residual wins). Where nothing along the corridor fixes it,
        every restart is degenerate too, or ends as poorly, and the match stands.
        """
        p = self.params
        assert self.target is not None
        if match.weak_direction is None:
            return match
        along = np.asarray(match.weak_direction[:2], dtype=np.float64)
        share = math.hypot(float(along[0]), float(along[1]))
        if share < DEGENERATE_POSITION_SHARE:  # a heading ICP could not fix, not a slide along a corridor
            return match
        along = along / share
        guess = self.ekf.mean.copy()
        sigma_m = math.sqrt(max(float(along @ self.ekf.covariance[:2, :2] @ along), 0.0))
        reach_m = (p.degenerate_retry_sigmas + 1.0) * sigma_m
        self.degenerate_retries += 1
        best = match
        for multiple in range(1, int(p.degenerate_retry_sigmas) + 1):
            for side in (1.0, -1.0):
                yield
                start = guess + np.append(side * multiple * sigma_m * along, 0.0)
                retry = yield from match_scan_steps(
                    self.target, prepared.points_match, start, p.icp, sensor_xy=prepared.sensor_xy
                )
                offset_m = float(along @ (retry.pose[:2] - guess[:2]))
                if (self.acceptable(retry) and not retry.degenerate and retry.rmse_m < best.rmse_m
                        and retry.rmse_m < DEGENERATE_RETRY_RMSE_SHARE * match.rmse_m
                        and abs(offset_m) <= reach_m and self.heading_plausible(retry)):
                    best = retry
        self.degenerate_retries_won += int(best is not match)
        return best

    def _better_retry(self, retry: IcpResult, best: IcpResult | None) -> bool:
        """Is ``retry`` a better pick than ``best``? Acceptable; within the heading gate before beyond it; then
        the smaller residual."""
        if not self.acceptable(retry):
            return False
        if best is None:
            return True
        if self.usable(retry) != self.usable(best):
            return self.usable(retry)
        return retry.rmse_m < best.rmse_m

    def _judged_where_seen(self, prepared: PreparedScan, match: IcpResult) -> IcpResult:
        """``match`` with its inlier ratio taken among the points the local submap could have seen, if that passes.

        A laser log's scans are a metre apart: one that passes a doorway or a corridor's
        end sees a room or a corridor the submap's keyframes never saw, and its plain
        inlier ratio falls under ``min_match_fitness`` however right the alignment is. The
        filter then takes the odometry's increment (several degrees off on the Intel log),
        and the pose graph gets an edge of odometry alone there, the weakest of the chain:
        every loop's residual ends up in it, a hinge of 2-5° in the final map (the Intel
        log's scans 21, 22, 63 and 707, each just under 0.5, on every seed), and ACES'
        second scan turns the whole map about the start. So a converged match whose
        residual passes is judged as loop closures may be (:mod:`mazebot.slam.overlap`):
        its inliers over the scan's points inside the area the submap's keyframes' beams
        covered must reach ``min_match_fitness``, and at least ``match_min_overlap`` of its
        points must lie there. A match that passes comes back with that ratio as its
        ``fitness`` and ``match_overlap_information_scale`` of its information; otherwise
        ``match`` as it was. ICP's Hessian treats each point's residual as independent: on
        the Intel log the sequential edges' chi² against the corrected poses was 64 times a
        calibrated one, and a match that sees half of what the submap saw, at a doorway, is
        the least sure of them. At full information the rescued matches, 1-2° off there,
        were kept against the closures and turned the map about its start (Intel seed 3:
        0.154 → 0.573 m); as weak edges they are bent back (0.095 m), where an edge of
        odometry alone was a hinge of 2-5°.
        """
        p = self.params
        if (not match.converged or match.rmse_m > p.max_match_rmse_m or not self._target_keyframes
                or prepared.points_match.shape[0] == 0):
            return match
        chosen = [self.keyframes[k] for k in self._target_keyframes if k < len(self.keyframes)]
        observed = ObservedArea.from_keyframes(
            [kf.pose for kf in chosen], [kf.sensor_xy for kf in chosen], [kf.ray_ends for kf in chosen]
        )
        seen = observed.contains(transform_points(match.pose, prepared.points_match), p.match_overlap_margin_m)
        ratio = min(1.0, match.correspondences / max(int(seen.sum()), 1))
        if float(seen.mean()) < p.match_min_overlap or ratio < p.min_match_fitness:
            return match
        self.matches_seen_rescued += 1
        scale = p.match_overlap_information_scale
        graph = None if match.graph_information is None else match.graph_information * scale
        return replace(match, fitness=ratio, information=match.information * scale, graph_information=graph)

    _match = all_at_once_method(
        _match_steps,
        """ICP from the prediction; if that match is not acceptable, from the prediction turned by each retry angle.

        A poor odometry heading (a wheel slipping in a turn, a metre between the scans of a
        laser log) can put ICP in the wrong basin; the best acceptable retry (lowest
        residual) wins, else the first result stands.
        """,
    )

    def _search_wanted(self, match: IcpResult, guess: np.ndarray) -> bool:
        """Is the prediction in doubt? ICP from it failed, the robot was just re-localized, or it is uncertain.

        Uncertain: the filter's standard deviation after the odometry step exceeds
        ``corr_uncertain_std_m`` / ``corr_uncertain_std_rad`` (a metre between two scans of a
        laser log, a long in-place turn): ICP's basin is then narrower than the prediction's
        error, and ICP settles in whichever local optimum is nearest, often a wall one
        door over or a few degrees off.
        """
        return self._search_due or not self.usable(match) or self._prediction_uncertain()

    def _prediction_uncertain(self) -> bool:
        p = self.params
        cov = self.ekf.covariance
        return bool(
            math.sqrt(max(cov[0, 0], cov[1, 1])) > p.corr_uncertain_std_m
            or math.sqrt(cov[2, 2]) > p.corr_uncertain_std_rad
        )

    def _search_window(self, failed: bool) -> tuple[float, float]:
        """Half-widths (m, rad) of the search: the whole window after a failure or re-localization,
        else ``corr_window_sigmas`` standard deviations of the prediction (no larger than the whole).

        A window fitted to the prediction's uncertainty holds the true pose (at 3σ, nearly
        always) and few of the look-alikes a building offers farther away: Olson (ICRA 2009)
        searches the motion model's support, not a fixed box.
        """
        p = self.params
        search = p.correlative
        assert search is not None
        if failed:
            return search.window_xy_m, search.window_theta_rad
        cov = self.ekf.covariance
        k = p.corr_window_sigmas
        xy = min(search.window_xy_m, k * math.sqrt(max(cov[0, 0], cov[1, 1])))
        theta = min(search.window_theta_rad, k * math.sqrt(cov[2, 2]))
        return xy, theta

    def _search_steps(
        self, prepared: PreparedScan, guess: np.ndarray, match: IcpResult
    ) -> Generator[None, None, IcpResult]:
        """The correlative search about ``guess``, ICP refining its best pose; which of the two matches stands.

        - ICP from the prediction failed: the refined match, if acceptable. A match turned
          beyond the heading gate (:meth:`heading_plausible`) is searched as a failed one; the
          refined match replaces an acceptable one only from within the gate.
        - ICP from the prediction failed and nothing acceptable within the window either
          (``failed_search_any_heading``): the window's position searched again over every
          heading, and the refined match taken if it pins every direction and fits as well as
          the run's recent matches (:meth:`_fits_as_well`): a turn the odometry did not see.
        - Re-localized and the prediction's match is acceptable: it stays.
        - The prediction was only uncertain and both matches are acceptable: the refined one
          replaces ICP's if it scores ``corr_override_score`` more on the likelihood table (at
          least as well when ICP's left the window: it wandered beyond the prediction's
          uncertainty), ICP rates it better on at least one of inlier ratio and residual, and
          the refined match is not degenerate (a corridor does not fix the position along it).
          The window is the prediction's own uncertainty, so the search cannot pick a
          look-alike far from where the odometry says the robot is. On the Intel log a fixed
          ±0.5 m window with the table's score alone replaced good matches by a corridor one
          door over; the score alone over the fitted window let a match 5° off win in the long
          corridor at the end (0.05 noise, seed 3: 1.23 m max error); asking ICP to rate it
          better on both measures kept wrong alignments at 0.1 noise (seed 1, 300 scans:
          3.7 m RMS against 0.18 m with one).
        """
        p = self.params
        search = p.correlative
        assert search is not None and self.target is not None
        self.searches += 1
        relocalized = self._search_due
        self._search_due = False
        failed = not self.usable(match)
        window_xy, window_theta = self._search_window(failed or relocalized)
        if self._search_any_heading:  # the odometry said nothing of this step's turn
            window_theta = math.pi
            self._search_any_heading = False
        table, src, refined = yield from self._refined_search_steps(prepared, guess, window_xy, window_theta)
        if failed and window_theta < math.pi and p.failed_search_any_heading and not self._found(refined):
            yield
            self.searches_any_heading += 1
            table, src, refined = yield from self._refined_search_steps(
                prepared, guess, window_xy, math.pi, p.failed_search_ambiguity_ratio
            )
            if not self._found(refined) or refined is None or refined.degenerate or not self._fits_as_well(refined):
                return match
        if refined is None or not self.acceptable(refined):
            return match
        if failed and (self.usable(refined) or not self.acceptable(match)):
            self.searches_won += 1
            return refined
        if failed or relocalized or not self.usable(refined):  # re-localized and the prediction fits: it stays
            return match
        delta = refined.pose - match.pose
        if math.hypot(delta[0], delta[1]) < 2.0 * search.resolution_m and abs(wrap_angle(delta[2])) < 0.01:
            return match  # the same alignment
        scores = table.score(np.array([match.pose, refined.pose]), src)
        off = match.pose - guess
        outside = math.hypot(off[0], off[1]) > window_xy * math.sqrt(2.0) or abs(wrap_angle(off[2])) > window_theta
        margin = 0.0 if outside else p.corr_override_score
        # and ICP does not disagree: more inliers or a smaller residual (a wall one door over or a
        # corridor's length fits the table about as well, but rarely ICP too); and the refined match
        # pins every direction: in a corridor the table cannot say where along it the robot is
        icp_better = (refined.fitness >= match.fitness or refined.rmse_m <= match.rmse_m) and not refined.degenerate
        if scores[1] >= scores[0] + margin and icp_better:
            self.searches_won += 1
            return refined
        return match

    def _found(self, refined: IcpResult | None) -> bool:
        """Did a search find an acceptable match?"""
        return refined is not None and self.acceptable(refined)

    def _fits_as_well(self, match: IcpResult) -> bool:
        """Is ``match``'s residual within ``failed_search_residual_ratio`` times the recent matched scans' median?

        A search over every heading finds, at a scan that sees a room the submap never saw, some
        turned alignment whose inlier ratio passes; its residual gives it away, several times
        those of the right matches around it (KISS-ICP's threshold from the residuals its
        registration has recently seen: Vizzo et al., IEEE RA-L 2023, III.C). Before the run has
        ten matched scans there is nothing to compare with, and no such match is taken.
        """
        limit_m = self._residuals.limit_m(self.params.failed_search_residual_ratio)
        return math.isfinite(limit_m) and match.rmse_m <= limit_m

    def _refined_search_steps(
        self, prepared: PreparedScan, guess: np.ndarray, window_xy_m: float, window_theta_rad: float,
        heading_ambiguity_ratio: float = 0.0,
    ) -> Generator[None, None, tuple[LikelihoodTable, np.ndarray, IcpResult | None]]:
        """The correlative search over ``±window_xy_m`` / ``±window_theta_rad`` about ``guess``, ICP from its best pose.

        Returns the likelihood table and the scan's points it scored (to score other poses
        alike), and ICP's match (None when the search's best scored under ``min_score``, or when
        ``heading_ambiguity_ratio`` > 0 and another heading scores that share of it:
        :meth:`_heading_ambiguous`).
        """
        p = self.params
        search = p.correlative
        assert search is not None and self.target is not None
        src = select_points(prepared.points_match, prepared.sensor_xy, search)
        crop = (guess[:2], search.max_range_m + window_xy_m + 3.0 * search.sigma_m + 0.5)
        table = LikelihoodTable(self.target.points, search.resolution_m, search.sigma_m, search.levels, crop=crop)
        found = correlative_match(table, src, guess, window_xy_m, window_theta_rad, prepared.sensor_xy)
        if found.score < search.min_score:
            return table, src, None
        if heading_ambiguity_ratio > 0.0 and self._heading_ambiguous(
            table, src, guess, window_xy_m, found.pose, found.score * heading_ambiguity_ratio, prepared.sensor_xy
        ):
            return table, src, None
        yield
        refined = yield from match_scan_steps(
            self.target, prepared.points_match, found.pose, p.icp, sensor_xy=prepared.sensor_xy
        )
        return table, src, refined

    def _heading_ambiguous(
        self, table: LikelihoodTable, src: np.ndarray, guess: np.ndarray, window_xy_m: float, best_pose: np.ndarray,
        floor: float, sensor_xy: np.ndarray | None,
    ) -> bool:
        """Does any heading ``failed_search_heading_separation_rad`` or more from ``best_pose``'s score ``floor``?

        A search over every heading has no motion prior to part a corridor seen one way from
        the same corridor seen turned half round, or a room's two square corners: the ratio
        test of the best against the second-best distinct alignment (Lowe, IJCV 2004, 7.1),
        here over headings. The other headings are searched about ``guess``'s position, centred
        half a turn from the best and reaching to the separation on either side of it.
        """
        separation_rad = self.params.failed_search_heading_separation_rad
        opposite = np.array([guess[0], guess[1], float(best_pose[2]) + math.pi])
        other = correlative_match(
            table, src, opposite, window_xy_m, math.pi - separation_rad, sensor_xy, floor=floor
        )
        return bool(other.score >= floor > 0.0)

    def _doubt_steps(
        self, prepared: PreparedScan, guess: np.ndarray, match: IcpResult
    ) -> Generator[None, None, IcpResult]:
        """A second opinion on an acceptable match whose residual stands out of the recent matches'.

        ``match_doubt_ratio`` (:mod:`mazebot.slam.match_residuals`): the correlative search
        looks over its whole window about the prediction, as after a failure (the prediction
        that led ICP astray may be farther off than its uncertainty says), ICP refines its
        best pose, and that match replaces ``match`` only if it is better on every measure: a
        smaller residual, at least the inlier ratio, and at least the score on the likelihood
        table. A smaller residual alone is no judge (a match that keeps fewer inliers has
        one): on the Intel log at ``0.05,0.05`` seed 2 two doubted right matches were replaced
        by ones of 35 mm instead of 83-96 mm with fewer inliers, 2° off, and the first 200
        scans went from 0.14 to 0.18 m RMS. Run after the usual search, so that where the
        second opinion does not win, the scan is matched exactly as without the doubt.
        """
        p = self.params
        search = p.correlative
        assert search is not None and self.target is not None
        self.matches_doubted += 1
        table, src, refined = yield from self._refined_search_steps(
            prepared, guess, search.window_xy_m, search.window_theta_rad
        )
        if refined is None or not self.usable(refined):
            return match
        scores = table.score(np.array([match.pose, refined.pose]), src)
        if refined.rmse_m < match.rmse_m and refined.fitness >= match.fitness and scores[1] >= scores[0]:
            self.doubts_won += 1
            return refined
        return match

    def _observe_distance(self, match: IcpResult | None, raw_increment: np.ndarray | None) -> None:
        """One sample of the odometry's distance scale if this scan's match and the previous scan's fixed the
        pose along the direction of travel (:mod:`mazebot.slam.distance_calibration`): the step between the two
        matches' poses, which the prediction (scaled by what is already applied) does not lean on."""
        if match is None or not fixes_travel(match.degenerate, match.weak_direction, float(match.pose[2])):
            self._last_travel_fixed_pose = None
            return
        if raw_increment is not None and self._last_travel_fixed_pose is not None:
            self.distance_calibration.observe(raw_increment, relative_pose(self._last_travel_fixed_pose, match.pose))
        self._last_travel_fixed_pose = match.pose.copy()

    def _learn_odometry_noise(self, match: IcpResult | None, increment: np.ndarray | None) -> None:
        """One more sample of the odometry's noise if this scan and the previous one were matched.

        ``increment`` is the odometry increment the filter predicted with: the raw one with
        its heading corrected by the online calibration. The noise learnt is what is left
        of the odometry's error after that correction, so a steady bias the calibration
        removes (unequal wheels, a wrong track width) does not also widen the prediction,
        and with it the correlative window, by the whole bias. The learnt model
        (:mod:`mazebot.slam.odometry_noise`) moves the filter's prediction from the next
        scan on, and with it the sequential edges' information, the chain's uncertainty
        and so the loop closures' search radius and correction bounds.
        """
        assert self.odometry_noise is not None
        if match is not None and increment is not None and self._last_match_pose is not None:
            self.odometry_noise.observe(increment, relative_pose(self._last_match_pose, match.pose))
            self.ekf.noise = self.odometry_noise.noise
        self._last_match_pose = None if match is None else match.pose.copy()

    def _deskewed(self, match: IcpResult, increment: np.ndarray, heading_rad: float) -> IcpResult:
        """``match`` with the de-skew's variance along the direction of travel (:mod:`mazebot.slam.deskew_variance`).

        The variance is the motion model's for the revolution's ``increment``, as the filter's
        prediction takes it. The filter and the sequential edge take ``match_information_scale``
        of the information; the variance is added before that scale at its share, so that after
        it the match's covariance has the motion model's variance more along the travel.
        """
        p = self.params
        variance_per_m = self.ekf.noise.xy_m2_per_m * p.match_information_scale
        info = deskew_information(match.information, increment, heading_rad, variance_per_m)
        graph = (None if match.graph_information is None
                 else deskew_information(match.graph_information, increment, heading_rad, variance_per_m))
        return replace(match, information=info, graph_information=graph)

    def _sequential_information(self, z: np.ndarray, odom: np.ndarray) -> np.ndarray:
        """Information of the edge previous keyframe → this one: odometry plus, if matched, ICP.

        Both are re-expressed in the frame of the edge's residual (the new keyframe's); ICP's
        covariance there takes the submap's own error (``edge_floor_std_m``, ``edge_floor_std_rad``:
        :mod:`mazebot.slam.submap_error`; 0: ICP's alone).
        """
        p = self.params
        increment = relative_pose(self._odom_at_keyframe, odom) if self._odom_at_keyframe is not None else z
        odom_cov = self.ekf.noise.covariance(increment) + np.diag([1e-8, 1e-8, 1e-8])
        info = rotate_information(np.linalg.inv(odom_cov), float(z[2]))
        if self._last_match is not None:
            icp_info = rotate_information(self._last_match.edge_information * p.match_information_scale,
                                          float(self.ekf.mean[2]))
            info = info + with_covariance_floor(icp_info, p.edge_floor_std_m, p.edge_floor_std_rad)
        return 0.5 * (info + info.T)

    def prepare(self, scan: Scan, odometry: OdometrySource) -> tuple[PreparedScan, np.ndarray]:
        """The revolution filtered and de-skewed into the robot frame at its end, and the
        odometry pose at that end: every step that reads a revolution (the update,
        re-localization, resuming a saved run) prepares it here, the same way.

        The lidar's stamps are late by the learned time offset (the samples were taken
        earlier), so they are shifted before the odometry is read at them: at the unshifted
        stamps a turn that starts or stops within the revolution is spread over the wrong samples.
        """
        offset_s = self.time_offset.offset_s
        if offset_s:
            scan = replace(scan, time_s=scan.time_s - offset_s)
        odom = odometry_pose_at(odometry, scan.end_time_s)
        prepared = prepare_scan(scan, self._deskew_motion(odometry, odom), self.params.prepare)
        normals = self.params.normals
        if normals.smooth and normals.smooth_scan:
            # matched like the submap is made (keyframes.smoothed_match_points); the map keeps the hits as measured
            voxel_m = self.params.prepare.voxel_size_m
            match = smoothed_match_points(prepared.points_full, prepared.sensor_xy, normals, voxel_m)
            prepared = replace(prepared, points_match=match)
        return prepared, odom

    def _deskew_motion(self, odometry: OdometrySource, end_odom: np.ndarray) -> PoseAtTime:
        """``pose_at_time`` for de-skew: odometry poses in the frame of the scan's end, heading calibrated."""
        calibration = self.calibration if self.params.calibrate_heading else None

        def pose_at(times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            x, y, th = odometry.at(times_s)
            rel = relative_pose(end_odom, np.column_stack((np.ravel(x), np.ravel(y), np.ravel(th))))
            theta = rel[:, 2] if calibration is None else calibration.correct_many(rel[:, 0], rel[:, 2])
            x, y = self.distance_calibration.correct_many(rel[:, 0], rel[:, 1])
            return x, y, theta

        return pose_at

    def _rebuild_target_steps(self) -> Generator[None, None, None]:
        """:meth:`_rebuild_target` in stages: the new keyframes' surfaces one by one, then the submap.

        A keyframe's surface (normals, points smoothed onto their lines) is computed the
        first time a submap needs it, one to four of them per rebuild, about a
        millisecond each; the submap (transform, voxel filter, kd-tree) comes after them.
        With ``pool_far_normals_one_pass`` (and the far hits pooled) the older keyframes near the
        robot are only those of the pass it is on (a keyframe at least ``loop.min_keyframe_gap``
        older than the newest is an earlier pass) until a loop closure from one of the recent
        keyframes has joined an earlier pass.
        """
        p = self.params
        count = len(self.keyframes)
        first_recent = max(0, count - p.submap_keyframes)
        chosen = list(range(first_recent, count))
        if p.submap_radius_m > 0 and first_recent > 0 and p.submap_near_keyframes > 0:
            xy = self.graph.vertices[:first_recent, :2]
            here = self.keyframes[-1].pose
            dist = np.hypot(xy[:, 0] - here[0], xy[:, 1] - here[1])
            near = np.flatnonzero(dist <= p.submap_radius_m)
            near = near[np.argsort(dist[near], kind="stable")[: p.submap_near_keyframes]]
            earlier = count - 1 - p.loop.min_keyframe_gap
            if (p.normals.pool_far_normals_one_pass and p.normals.pool_far_normals_beyond_m > 0.0
                    and not self._joined_to_earlier_pass(first_recent, earlier)):
                # an earlier pass no loop closure has joined yet: the match would snap onto it
                near = near[near > earlier]
            chosen = sorted(near.tolist()) + chosen
        for k in chosen:
            if not self.keyframes[k].has_surface:
                self.keyframes[k].packed_surface()
                yield
        self.target = yield from build_target_steps([self.keyframes[k] for k in chosen], p.submap_voxel_m)
        self._target_keyframes = chosen
        self._target_position = self.keyframes[-1].pose[:2].copy()
        self._keyframes_since_target = 0

    def _joined_to_earlier_pass(self, first_recent: int, earlier: int) -> bool:
        """A loop closure accepted from keyframe ``first_recent`` or newer onto keyframe ``earlier`` or older.

        Every closure is looked at: their order of acceptance is not their new ends' (a set's members
        are accepted together, after closures of newer keyframes).
        """
        return any(c.new >= first_recent and c.old <= earlier for c in self.closures)

    _rebuild_target = all_at_once_method(
        _rebuild_target_steps,
        "The local submap: the recent keyframes, and older ones close to the newest (KISS-ICP's local map).",
    )

    def final_job(self) -> LoopClosureJob | None:
        """The whole graph optimized once more and the grid rebuilt from it: for the end of an exploration.

        The live grid holds every scan at the pose it had when it came in; a rebuild after
        a loop closure only happens when a keyframe moved more than the rebuild
        thresholds, so the small corrections of the later optimizations (wall priors,
        closures) never reach it. Once the maze is explored the map is final: one
        rebuild from the optimized keyframes gives it their accuracy (on the bench's 6×6
        seed 20: coverage 0.9877 live, 0.9908 rebuilt). None while another job runs (ask
        again when it is merged) or with fewer than two keyframes. Run and merge it like
        the jobs :meth:`update` hands out.
        """
        if self.job_running or len(self.keyframes) < 2:
            return None
        job = self._make_job(self._pending_candidates, None, optimize_anyway=True)
        self._pending_candidates = []
        self.job_running = True
        if self.taps.on_final_job:
            notify(self.taps.on_final_job, self, "slam.on_final_job")
        return replace(job, rebuild_anyway=True)

    def _make_job(
        self, candidates: list[Candidate], poses: np.ndarray | None, *, optimize_anyway: bool
    ) -> LoopClosureJob:
        poses = self.keyframe_poses() if poses is None else poses
        self._keyframes_since_optimization = 0
        self._verifying = list(candidates)
        ei, ej, z, omega = self.graph.edge_arrays
        # Keyframe 0's wall grid judged from every keyframe's faces (mazebot.slam.start_anchor) as soon
        # as it has faces at rest, in any maze: its normals' mean at rest is one place's view, and one
        # place can read it off (0.32° in the bench's 16x16 seed 8, whose start is a dead end 0.15 m
        # from three walls; tied at wall_anchor_std_rad it turned the whole map by 0.28°). Without
        # faces at rest, that mean is all there is.
        faces = self._start_faces if self.anchor_face_spread_rad is not None else None
        anchor = self.anchor_wall_rad if faces is None else None
        return LoopClosureJob(
            candidates=candidates,
            keyframes=list(self.keyframes),
            poses=poses,
            integrated_poses=np.array([kf.integrated_pose for kf in self.keyframes]).reshape(-1, 3),
            edges=(ei.copy(), ej.copy(), z.copy(), omega.copy()),
            params=self.params,
            wall_reference_rad=self.wall_reference_rad,
            optimize_anyway=optimize_anyway,
            anchor_wall=None if anchor is None else (anchor, self.params.wall_anchor_std_rad),
            start_faces=faces,
            rest_surface=self._rest_surface,
            start_turns=self._start_turns,
            known_fit=None if self.lattice_fit is None else (self.lattice_fit, self._lattice_fit_keyframes),
            set_members=tuple(self._set_members),
            set_waiting=tuple(self._set_waiting),
        )

    def _loop_closure_job(self) -> LoopClosureJob | None:
        """Look for candidates every ``attempt_every`` keyframes; a job for them (and for periodic optimization).

        Candidates found while a job runs wait (the newest ``PENDING_CANDIDATES``) for the next one.
        """
        p = self.params.loop
        poses = None
        if self._keyframes_since_attempt >= p.attempt_every:
            self._keyframes_since_attempt = 0
            poses = self.keyframe_poses()
            found = find_candidates(
                poses,
                len(self.keyframes) - 1,
                np.asarray(self._edge_var_xy),
                np.asarray(self._edge_var_theta),
                replace(p, max_candidates=4 * p.max_candidates),
            )
            # a keyframe one cell away behind a wall is near, but sees another corridor
            found = [c for c in found if self._in_sight(poses[c.old], poses[c.new])]
            found = [c for c in found if not self._closed_already(c)]
            # the nearest ones, and keyframe 0 beyond them if asked for (loop_closure.find_candidates)
            anchor = [c for c in found[p.max_candidates :] if p.anchor_candidate and c.old == 0]
            found = found[: p.max_candidates] + anchor
            self._pending_candidates = (self._pending_candidates + found)[-PENDING_CANDIDATES:]
        if self.job_running:
            return None
        periodic = (
            self.params.wall_prior
            and self.wall_reference_rad is not None
            and self._keyframes_since_optimization >= self.params.optimize_every_keyframes
        )
        candidates, self._pending_candidates = self._pending_candidates, []
        if not candidates and not periodic:
            return None
        return self._make_job(candidates, poses, optimize_anyway=periodic)


def _mean_turn(turns: Sequence[tuple[float, float]], floor_std_rad: float) -> tuple[float, float]:
    """The inverse-variance mean (modulo 90°) of ``(direction_rad, std_rad)`` pairs, and its std (floored)."""
    direction = np.array([d for d, _ in turns])
    weight = 1.0 / np.array([std for _, std in turns]) ** 2
    mean = 0.25 * math.atan2(float(weight @ np.sin(4.0 * direction)), float(weight @ np.cos(4.0 * direction)))
    return mean, max(1.0 / math.sqrt(float(weight.sum())), floor_std_rad)


def _segment_cells(grid: OccupancyGrid, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the grid cells along the segment a -> b (sampled at half a cell)."""
    length = float(np.hypot(*(b[:2] - a[:2])))
    steps = max(2, math.ceil(2.0 * length / grid.resolution_m) + 1)
    u = np.linspace(0.0, 1.0, steps)[:, None]
    return grid.to_cell(a[:2] + u * (b[:2] - a[:2]))


def _turn_rate(odometry: OdometrySource, time_s: float, window_s: float = 0.02) -> float:
    """The odometry's turn rate (rad/s) over the ``window_s`` before ``time_s``."""
    _, _, th = odometry.at(np.array([time_s - window_s, time_s]))
    th = np.ravel(th)
    return math.remainder(float(th[1] - th[0]), math.tau) / window_s


def odometry_pose_at(odometry: OdometrySource, time_s: float) -> np.ndarray:
    """The odometry pose at ``time_s``, heading wrapped to [-π, π)."""
    x, y, th = odometry.at(np.array([time_s]))
    return np.array([float(np.ravel(x)[0]), float(np.ravel(y)[0]), math.remainder(float(np.ravel(th)[0]), math.tau)])
