"""``mazebot slam run``: run the SLAM offline on a CARMEN laser log and measure it.

Example::

    mazebot slam run --carmen ../shared/data/carmen/intel.gfs.log --odom-noise 0.05,0.05 --seed 1 --out /tmp/intel

reads the log's laser messages (``FLASER``, ``RLASER``, ``ROBOTLASER1``), feeds them with
odometry to :class:`mazebot.slam.slam.Slam` (loop closures inline), and writes into
``--out``:

- ``trajectory.txt``: one line ``timestamp x y theta`` per scan (the log's timestamps;
  poses after the last optimization, in the log's frame: the map frame is anchored at
  the first laser pose of the log, where the first scan registers against the finished
  map: :func:`reanchor`, off with ``--no-reanchor``; with ``--start-placement``, along a
  direction that registration leaves open, where the start's odometry puts it:
  :func:`place_along_unobserved`);
- ``map.png``, ``map.pgm`` + ``map.yaml`` (ROS ``map_server``);

and prints one JSON line of statistics, with the error of the trajectory against the
poses the log carries (in a ``*.gfs.log`` those are GMapping's corrected poses, the
reference here). ``error`` (the headline) compares pose by pose from the shared first
pose, no alignment; ``error_aligned`` is the literature's ATE after a rigid SE(2) fit of
the whole trajectory, and ``relative_error`` Kümmerle et al.'s relative displacement
error between consecutive scans (:mod:`mazebot.slam.trajectory_metrics`): the reference
is itself another SLAM's output in its own frame.

Odometry: without ``--odom-noise`` the log's own odometry (``ODOM`` messages, else the
odometry pose of each laser message; in the corrected logs here the ``ODOM`` lines are the
robot's wheel odometry re-based onto each scan's corrected pose, read back by
:func:`rebased_odometry`). ``--odom-noise SX,STH`` instead derives it from the
log's (corrected) poses: every increment between two scans gets Gaussian noise with
standard deviation ``SX`` per metre travelled on each axis and ``STH`` radians per metre
travelled plus per radian turned on the heading, drawn from ``--seed``. ``--odom-model
systematic`` adds what white noise lacks, the errors of real wheels: a scale error per
wheel, a track-width error and a heading bias that drifts
(:mod:`mazebot.slam.odometry_errors`). Logs may be gzip-compressed (``*.log.gz``), and
their stamps may repeat (rounded): scans are taken in file order.

The maze defaults of ``[slam]`` suit a 1 ft maze and an A1; a building scanned by a SICK
LMS (1° beams, ~0.7 m between scans, 80 m range) needs coarser ones: see
:func:`laser_log_params`.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mazebot.argtypes import non_negative_int, positive_int
from mazebot.config import load_config
from mazebot.errors import EXIT_OK, UsageError
from mazebot.geometry import compose, inverse, relative_pose, wrap_angle
from mazebot.slam.carmen import MOUNTED_KINDS, CarmenLog, LaserRecord, odometry_at, one_laser, read_carmen
from mazebot.slam.correlative import CorrelativeParams
from mazebot.slam.ekf import MotionNoise, OdometryHistory
from mazebot.slam.heading_bias import sequential_heading_bias
from mazebot.slam.loop_closure import ObservedDirections
from mazebot.slam.map_consistency import (
    Neighbourhood,
    consistency,
    first_scan_heading_deg,
    judged_scans,
    register_scan,
    scan_corrections,
    thin_scans,
)
from mazebot.slam.map_export import write_map_png, write_ros_map
from mazebot.slam.odometry_errors import SystematicOdometryModel, parse_systematic, systematic_odometry
from mazebot.slam.posegraph import PoseGraph
from mazebot.slam.robust_closures import optimize_dcs
from mazebot.slam.slam import GridParams, Slam, SlamParams, SlamUpdate
from mazebot.slam.trajectory_metrics import aligned_error, anchored_error, relative_error

#: the odometry noise a laser log's SLAM starts from, before the scan matches have measured it
#: (:mod:`mazebot.slam.odometry_noise`): 0.1 m per metre on each axis and 0.1 rad per metre and
#: per radian, wider than any building robot's wheels, so that the first matches, the
#: correlative window and the first loop closures are not held to an odometry nobody measured
LASER_LOG_PRIOR_NOISE = MotionNoise(
    xy_m2_per_m=0.1**2, theta_rad2_per_m=0.1**2, theta_rad2_per_rad=0.1**2, estimate=True
)

#: a closure the correlative search found is refused when another alignment of its window scores this share
#: of the best (:func:`mazebot.slam.correlative.runner_up`): after metres of drift the window spans metres of
#: corridor, and of two look-alikes scoring within 10 % the best is no surer the right one
LASER_LOG_AMBIGUITY_RATIO = 0.9
#: ... counting alignments farther than this from the best: twice ICP's 0.5 m correspondence gate, beyond
#: which ICP started at one would not converge to the other (nearer, they are one basin)
LASER_LOG_PEAK_SEPARATION_M = 1.0
#: with ``slam run --match-doubt``, a sequential match whose residual exceeds this many times the median of the
#: recent matches' is in doubt and searched again over the whole correlative window
#: (:mod:`mazebot.slam.match_residuals`): on the Intel log at
#: ``0.1,0.1`` the right matches' 99th percentile is 6-7 times their median and a match 30° off 12 times; a doubt
#: only asks the search for a second opinion, so the limit sits below the right matches' tail, not above it
LASER_LOG_DOUBT_RATIO = 4.0
#: the heading calibration applies an estimate only where its Wald statistic passes a test repeated after every
#: matched scan whose chance of passing anywhere in a run of white odometry noise is this
#: (:class:`mazebot.slam.ekf.HeadingCalibration`): white noise, whose estimates are zero but for their scatter,
#: is not learnt as a bias, not even for a while
LASER_LOG_CALIBRATION_FALSE_ALARM = 0.001


def laser_log_params(
    base: SlamParams, calibrate_heading: bool = True, closure_ambiguity: bool = False, match_doubt: bool = False,
    calibrate_distance: bool = False, calibrate_lever_arm: bool = True, wide_loop_search: bool = False,
) -> SlamParams:
    """SLAM settings for an indoor laser log (SICK LMS, metres between scans) from the maze ones.

    Every scan moves the robot more than the maze keyframe spacing, so every scan is a
    keyframe; points are thinned to 5 cm, normals use a 0.3 m neighbourhood (1° beams
    are ~9 cm apart at 5 m), the grid has 5 cm cells, ICP starts with a 0.5 m gate (the
    odometry is off by decimetres after a metre). The scans carry one time stamp each: no
    de-skew and no time-offset calibration. The map is rebuilt once at the end
    from the optimized keyframes, not after every loop closure. ICP weights every point
    alike (``range_noise_ratio`` 0): a SICK's range noise is about a centimetre whatever
    the range, not the A1's 1 % of it.

    Each choice below was measured on the Intel and Radish logs, with white and systematic
    odometry noise and the logs' own wheel odometry; the figures, per branch named here, are in
    ``docs/benchmarks-history.md`` (search for the branch's name).

    ``calibrate_heading`` (on; ``slam run --no-odom-calibration`` turns it off): real wheel odometry
    turns every corner by the track width's error and drifts on every straight by the wheels'
    (Borenstein & Feng 1996); the learnt noise would otherwise take that bias in whole, widening every
    prediction and so the correlative window, where a look-alike can win. Its estimates may reach ±0.5,
    not the maze robot's ±0.1: a log's odometry comes undescribed. Each estimate is applied only once a
    test repeated after every matched scan shows it beyond white noise, at a level spent over the whole
    run (:data:`LASER_LOG_CALIBRATION_FALSE_ALARM`): on white noise it applies nothing, so those runs
    compute what they computed without it, while it holds the runs with systematic odometry that are
    lost without it (branches ``reallogs7``–``reallogs9``).

    ``calibrate_lever_arm`` (on; ``slam run --no-lever-arm`` turns it off): where the laser sits relative to
    the point the log's odometry measures, learnt from the matched turns with the same test
    (:class:`mazebot.slam.lever_arm.LeverArmCalibration`). Odometry made from the laser's poses
    (``--odom-noise``) has none, and nothing is applied there; the corrected logs' own wheel odometry
    puts ACES's laser about 7 cm and the Intel log's about 10 cm ahead of the odometry's centre, where
    their ``PARAM robot_frontlaser_offset`` says 0.

    ``closure_ambiguity`` (``slam run --closure-ambiguity``; off): a searched closure is refused when
    another alignment of its window, parted from the best by a dip in the score, scores
    :data:`LASER_LOG_AMBIGUITY_RATIO` of it. It refuses a 7.5 m look-alike on ACES with drifting odometry
    but also right closures in long Intel corridors (branches ``reallogs8``, ``reallogs9``): not the default.

    ``wide_loop_search`` (``slam run --wide-loop-search``; off): loop candidates searched within 1 m plus 3
    standard deviations of the chain's drift with no 5 m cap, and beyond the nearest, where that drift exceeds
    the 1 m itself, the nearest keyframe of up to two more distinct places (``distinct_places``). A drift of
    7–8 m outgrows the cap: back at its start on wheels whose heading drifts 3° a metre, the ACES log verified
    only the nearest keyframe of the drifted estimate, a corridor 7 m from the truth, for 20 keyframes and never
    closed that loop (0.42 m RMS; 0.11 m with it). But the closures the extra places add make ACES on its own
    wheels and on milder bad wheels worse (0.10 to 0.23 m RMS; branch ``loops23``): not the default.

    ``[slam.matching] failed_search_any_heading`` (from ``--config``; off): a scan that neither ICP from the
    prediction nor the correlative search over its window could match is searched again over every heading, and
    a match that pins every direction, with a residual within ``failed_search_residual_ratio`` of the run's
    recent ones and no other heading scoring ``failed_search_ambiguity_ratio`` of it, is taken: the odometry
    missed a turn inside the step. It holds Seattle at half the scan rate (30.5 m to 0.26 m RMS) and through a
    4 m and a 5.6 m laser (30.6 / 30.5 m to 0.68 / 0.44 m), the four logs as logged and the Radish seeds the
    same to the digit, but loses ACES at half the scan rate (0.39 to 34.4 m) and through a 4 m laser (0.54 to
    14.9 m; Intel there 0.49 to 4.3 m max): an option (branch ``robust23``).

    ``match_doubt`` (``slam run --match-doubt``; off): a sequential match whose residual exceeds
    :data:`LASER_LOG_DOUBT_RATIO` times the recent median is searched again and replaced only by a match
    better on residual, inlier ratio and score. It puts right a 40° wrong match on real Intel scans but
    left the measured maps no better (branch ``reallogs12``).

    Loop closures:

    - verified with the whole scan (``max_range_m`` None): the maze's 2 m crop leaves a few dozen
      points of a 2 m wide corridor;
    - searched up to 5 m away and allowed to move a pose by up to 1.5 m, or by more where the chain's
      own uncertainty says so (3 standard deviations of its drift, ``correction_sigmas``): a building's
      loops are longer than any fixed cap;
    - keyframe 0 not verified as an extra candidate (``anchor_candidate`` off): it lost ACES with
      systematic odometry, and measured again with the present verification it is worse on 16 of 19 runs (ACES
      as logged 0.10 → 0.27 m): the closures onto keyframe 0 are measured against a submap of the start's
      in-place turns, and carry its first step's odometry error (a median 0.7-1.6° on ACES);
    - the inlier ratio over all points (``overlap_fitness`` off): the overlap-aware ratio let wrong
      closures in along the Intel log's last long corridor;
    - a candidate at least 30 keyframes old: 30 m at the corrected logs' metre a scan, 60 m at half their
      scan rate;
    - every candidate verified (``closed_reach_keyframes`` 0): after a loop of tens of metres the
      closures back onto the start each carry weight the robust optimization needs;
    - no wall prior: a building's walls do not lie on one right-angle grid.

    Options that pass through from ``--config``, each better on some logs and worse on others, so off:
    ICP's information clustered by wall (``[slam.icp] information_cluster_rad``; branches ``reallogs5``,
    ``reallogs6``); no smoothing of the submap's points onto their local lines (``[slam.normals] smooth``
    false: the smoothing turns each Seattle match +0.035°, yet without it Intel at ``0.1,0.1`` loses a
    stretch; branch ``seattle15``); the scan's points smoothed as the submap's are (``[slam.normals]
    smooth_scan``) or only points whose whole neighbourhood is one face smoothed (``smooth_whole_face_only``),
    each removing that turn and each worse on other logs (branch ``wheels21``), or only points whose neighbours
    on their face span a short piece of wall smoothed (``smooth_max_span_m``: Seattle within 0.15 m on every
    run, Freiburg 101 and the own-wheel ACES and Intel turned further about their start; branch ``radish23``);
    a sequential match turned
    beyond ``[slam.matching] match_heading_sigmas`` of the prediction searched again (branches ``radish18``,
    ``guard19``); the loop candidates' gap as travel where the scans lie farther apart than a metre
    (``[slam.loop] min_gap_m`` 30: :func:`mazebot.slam.loop_closure.keyframe_gap`; every log at its own rate the
    same to the digit, at half the rate ACES and Intel better, Freiburg 101 worse; branch ``rate22``); closures
    accepted in the directions they constrain (``[slam.loop] accept_degenerate``;
    branch ``corridor17``); a match whose residual exceeds four times the recent matched scans' median refused as one
    beyond ``max_match_rmse_m`` (``[slam.matching] match_residual_ratio`` 4: Freiburg 101 through a 4 m laser held,
    the Intel log lost a stretch; branch ``robust23``); closures verified as a set rather than each alone
    (``[slam.loop] set_verify``; branch ``reallogs6``).

    The correlative search (:mod:`mazebot.slam.correlative`) on 5 cm cells smoothed by
    10 cm (a beam every 1° is ~9 cm apart at 5 m), with points up to 10 m: ±0.5 m and ±30°
    for a sequential match that failed from the prediction; loop closures that failed from
    the prior search ±1.5 m / ±0.2 rad about it (the correction allowed).

    The odometry's noise is never told (``--odom-noise`` only makes the odometry): a log's
    own odometry comes without a description, so the motion model starts wide
    (:data:`LASER_LOG_PRIOR_NOISE`) and is learnt from the disagreement between the
    odometry's and the scan matches' increments (:mod:`mazebot.slam.odometry_noise`). That
    model drives the filter's prediction (and so the correlative window), the sequential
    edges' information and, through the chain's uncertainty, the loop closures' search
    radius and correction bounds.
    """
    search = CorrelativeParams(
        resolution_m=0.05, sigma_m=0.1, window_xy_m=0.5, window_theta_rad=0.52, levels=3,
        max_range_m=10.0, max_points=250, min_score=0.3,
    )
    motion = replace(
        base.motion,
        xy_m2_per_m=LASER_LOG_PRIOR_NOISE.xy_m2_per_m,
        theta_rad2_per_m=LASER_LOG_PRIOR_NOISE.theta_rad2_per_m,
        theta_rad2_per_rad=LASER_LOG_PRIOR_NOISE.theta_rad2_per_rad,
        estimate=True,
    )
    return replace(
        base,
        prepare=replace(
            base.prepare, min_range_m=0.1, max_range_m=30.0, voxel_size_m=0.05, mount_x_m=0.0, mount_y_m=0.0
        ),
        icp=replace(base.icp, max_correspondence_m=0.5, min_correspondence_m=0.1, range_noise_ratio=0.0),
        normals=replace(base.normals, radius_m=0.3),
        motion=motion,
        loop=replace(
            base.loop,
            search_radius_m=1.0,
            max_search_radius_m=math.inf if wide_loop_search else 5.0,  # see wide_loop_search in the docstring
            max_candidates=3 if wide_loop_search else 1,
            distinct_places=wide_loop_search,
            min_keyframe_gap=30,
            submap_half_width=5,
            attempt_every=1,
            closed_reach_keyframes=0,  # every candidate verified: see the docstring
            anchor_candidate=False,  # keyframe 0 at rest is a maze robot's start; not measured on the logs
            min_fitness=0.6,
            overlap_fitness=False,  # measured: admitted wrong closures in the Intel log's last corridor
            max_rmse_m=0.05,
            max_correction_m=1.5,
            max_correction_rad=0.2,
            correction_sigmas=3.0,
            ambiguity_shift_m=0.0,
            search_ambiguity_ratio=LASER_LOG_AMBIGUITY_RATIO if closure_ambiguity else 0.0,
            search_peak_separation_m=LASER_LOG_PEAK_SEPARATION_M,
            min_std_m=0.05,
            min_std_rad=0.02,
            max_range_m=None,
            search=None
            if base.loop.search is None
            else replace(search, window_xy_m=1.5, window_theta_rad=0.2, levels=5),
        ),
        correlative=None if base.correlative is None else search,  # [slam] correlative = false turns both off
        lattice=None,  # no maze: no wall lattice
        grid=GridParams(resolution_m=0.05, max_free_range_m=20.0),
        map_max_range_m=20.0,
        filter_gate_chi2=1e6,  # the odometry noise model is rough here; never refuse a converged match
        max_match_rmse_m=1.0,
        match_doubt_ratio=LASER_LOG_DOUBT_RATIO if match_doubt else 0.0,  # a residual far out of the run's own
        match_deskew_variance=False,  # a laser log's scan carries one stamp: nothing is de-skewed
        # a sequential match under min_match_fitness stays refused (``match_overlap_fitness`` false): judged where
        # the submap saw, the maps are more consistent but turn about the start by more (branch reallogs4)
        retry_headings_rad=(0.05, -0.05, 0.1, -0.1, 0.15, -0.15),
        wall_prior=False,
        calibrate_heading=calibrate_heading,
        calibrate_distance=calibrate_distance,
        calibrate_lever_arm=calibrate_lever_arm,
        distance_step_noise_m=0.01,  # a log's steps are 0.1-1 m under white noise of centimetres: the prior steadies
        # the fit's first observations (the ACES log's first 100 scans at 0.05,0.05: 0.08 m RMS; 0.21 m without it)
        calibration_limit=0.5,  # a log's odometry comes undescribed: any wheel or track error a robot still drives with
        calibration_false_alarm=LASER_LOG_CALIBRATION_FALSE_ALARM,
        estimate_time_offset=False,
        lidar_time_offset_s=0.0,
        keyframe_distance_m=0.2,
        keyframe_angle_rad=0.2,
        submap_keyframes=10,
        submap_radius_m=2.0,
        submap_near_keyframes=10,
        submap_voxel_m=0.05,
        submap_update_m=0.0,
        submap_update_keyframes=1,
        rebuild_threshold_m=math.inf,  # no map rebuild after each loop closure: one at the end
        rebuild_threshold_rad=math.inf,
    )


def noisy_odometry(
    poses: np.ndarray, sigma_xy_per_m: float, sigma_theta: float, rng: np.random.Generator
) -> np.ndarray:
    """Odometry poses (N, 3) from reference poses: each increment perturbed (see the module docstring).

    The odometry frame starts at the origin.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    out = np.zeros_like(poses)
    for k in range(1, poses.shape[0]):
        inc = relative_pose(poses[k - 1], poses[k])
        d = math.hypot(inc[0], inc[1])
        noisy = inc + rng.standard_normal(3) * np.array(
            [sigma_xy_per_m * d, sigma_xy_per_m * d, sigma_theta * (d + abs(inc[2]))]
        )
        out[k] = compose(out[k - 1], noisy)
    return out


def log_odometry(log: CarmenLog) -> np.ndarray:
    """The log's own odometry of the laser at each laser message: ``ODOM`` interpolated, else the message's own.

    ``ODOM`` poses are interpolated in time between the messages around each laser
    message; where the stamps do not increase (logs whose stamps were rounded), time says
    nothing, and each laser message takes the last ``ODOM`` before it in the file. Without
    ``ODOM`` lines (or with all of them zero) each message's odometry pose: a ``FLASER``'s
    ``odom_x odom_y odom_theta``. A zero ``ODOM`` line among others is a reading like any: a
    robot's odometry starts at 0 0 0 and stays there until the wheels turn, and a laser message
    logged then is at the origin (taken as the first pose off it instead, a log whose first
    scans come before the first turn of the wheels loses that turn from its first step). Logs
    whose ``ODOM`` lines were moved onto the corrected pose at every scan (the corrected Radish
    logs) give their raw odometry back through :func:`rebased_odometry`.

    The SLAM tracks the laser, so the odometry is the laser's: a ``ROBOTLASER1`` gives the
    laser's pose and the robot's, and the laser's mounting on the robot (the one relative
    to the other, in the same message) is applied to the robot's odometry (``ODOM`` or,
    without it, its robot pose); so does a ``RAWLASERn``, placed by the reader on the same
    ``ODOM`` readings with the log's ``PARAM`` mounting (:func:`mazebot.slam.carmen.with_odometry_poses`).
    ``FLASER`` poses are the laser's already.
    """
    rebased = rebased_odometry(log)
    if rebased is not None:
        return rebased
    times = np.array([r.timestamp_s for r in log.lasers])
    odom = log.odometry if any(np.any(o.pose) for o in log.odometry) else []
    interpolated = odometry_at(odom, times, np.array([r.line_number for r in log.lasers]))
    robot = np.array([r.odom_pose for r in log.lasers]).reshape(-1, 3) if interpolated is None else interpolated
    mount = np.zeros((len(log.lasers), 3))
    for k, r in enumerate(log.lasers):
        if r.kind in MOUNTED_KINDS:
            mount[k] = relative_pose(r.odom_pose, r.pose)  # the laser in the robot frame
    return compose(robot, mount)


#: How close a re-basing ``ODOM`` line's pose is to its laser message's corrected pose (the logs
#: print 6 significant digits).
REBASE_TOLERANCE_M = 2e-3
REBASE_TOLERANCE_RAD = 2e-3


def rebased_odometry(log: CarmenLog) -> np.ndarray | None:
    """The raw odometry of a log whose ``ODOM`` lines were moved onto each scan's corrected pose, or None.

    The corrected Radish logs (and logs made the same way) carry the robot's wheel odometry
    in their ``ODOM`` lines, but re-based: right after each laser message an ``ODOM`` line
    stamped 0 holds that message's corrected pose, and the lines up to the next laser
    message are that pose composed with the odometry's motion since. Read in file order,
    such lines hand the SLAM the reference itself at every scan, with each step's error
    undone at the next (on ACES 0.6 m RMS over 323 m, where the wheels' own drift is
    metres). The raw motion between two scans is the last ``ODOM`` before the second
    relative to the re-basing line after the first (both in the same frame); chained, the
    steps give the odometry the robot measured. Where a scan has no re-basing line the
    step is taken between the last ``ODOM`` lines before each scan, which then share one
    frame. None when fewer than half of the laser messages are followed by a re-basing
    line: the log is not of this kind.
    """
    if not log.lasers or not log.odometry:
        return None
    odom_lines = np.array([o.line_number for o in log.odometry])
    laser_lines = np.array([r.line_number for r in log.lasers])
    before = np.searchsorted(odom_lines, laser_lines) - 1  # the last ODOM before each laser message
    following = np.append(laser_lines[1:], np.iinfo(np.int64).max)
    rebase = np.full(len(log.lasers), -1)
    for k, record in enumerate(log.lasers):
        i = before[k] + 1
        if i < len(log.odometry) and odom_lines[i] < following[k] and log.odometry[i].timestamp_s == 0.0:
            gap = relative_pose(record.pose, log.odometry[i].pose)
            if math.hypot(gap[0], gap[1]) <= REBASE_TOLERANCE_M and abs(gap[2]) <= REBASE_TOLERANCE_RAD:
                rebase[k] = i
    if np.count_nonzero(rebase >= 0) * 2 < len(log.lasers):
        return None
    poses = np.zeros((len(log.lasers), 3))
    for k in range(1, len(log.lasers)):
        base = rebase[k - 1] if rebase[k - 1] >= 0 else before[k - 1]
        end = before[k]
        if base < 0 or end < base:  # no odometry yet, or none since the re-basing line
            poses[k] = poses[k - 1]
            continue
        step = relative_pose(log.odometry[base].pose, log.odometry[end].pose)
        poses[k] = compose(poses[k - 1], step)
    return poses


def same_motion(odometry: np.ndarray, reference: np.ndarray, tol_m: float = 1e-3, tol_rad: float = 1e-3) -> bool:
    """Do two trajectories make the same increments (within ``tol_m`` / ``tol_rad``, the log's rounding)?

    A raw log's laser messages carry the odometry in their pose fields too (CARMEN's
    ``FLASER`` ``x y theta`` equal ``odom_x odom_y odom_theta`` when nothing corrected them),
    and so do the corrected logs here whose odometry fields repeat the corrected poses:
    either way the log holds one trajectory, and an error of the SLAM "against the
    reference" would be against the odometry it was given.
    """
    odometry = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    reference = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    if odometry.shape[0] < 2:
        return True
    a = relative_pose(odometry[:-1], odometry[1:])
    b = relative_pose(reference[:-1], reference[1:])
    gap = np.abs(a - b)
    gap[:, 2] = np.abs(wrap_angle(a[:, 2] - b[:, 2]))
    return bool(np.all(gap[:, :2] <= tol_m) and np.all(gap[:, 2] <= tol_rad))


def slam_clock(times_s: np.ndarray) -> np.ndarray:
    """Strictly increasing times for SLAM from a log's stamps, which may repeat or step back.

    A few of the Intel log's messages step back by ~0.1 s; the Radish logs' stamps are
    rounded to six significant digits, so consecutive scans often share one. Each scan
    gets at least a millisecond after the previous one (SLAM only needs the order: the
    laser-log settings neither de-skew nor estimate a time offset).
    """
    clock = np.asarray(times_s, dtype=np.float64).copy()
    for k in range(1, len(clock)):
        clock[k] = max(clock[k], clock[k - 1] + 1e-3)
    return clock


def from_first_pose(odometry: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``odometry`` (N, 3) moved rigidly to start at the log's first pose: the map frame is the log's,
    anchored there, so the SLAM's poses and the corrected ones share a frame from the first scan on."""
    return compose(reference[0], relative_pose(odometry[0], odometry))


#: a laser message's odometry is stale when the last ``ODOM`` reading before it in the file is older than this
#: many of the odometry's own periods (its median interval): a logger that drops a reading or two is not yet
#: a hole, three seconds without one at 20 Hz (the Seattle log's scan 27) is
ODOMETRY_GAP_PERIODS = 10.0


def odometry_gaps(log: CarmenLog) -> np.ndarray:
    """(N,) bool per laser message: the log's ``ODOM`` readings say nothing of the step to it from the previous one.

    True where no ``ODOM`` reading lies between the two messages in the file and the last one
    before the second is more than :data:`ODOMETRY_GAP_PERIODS` of the odometry's own periods
    older than it: the wheels were not read while the robot went on, and the step the odometry
    gives (zero, where the ODOM lines were re-based onto each scan's corrected pose:
    :func:`rebased_odometry`) is no measurement of the motion. Re-basing lines (stamped 0) are
    not readings; a log without ``ODOM`` lines, or whose stamps give no period, has no gaps.
    """
    gaps = np.zeros(len(log.lasers), dtype=bool)
    readings = [o for o in log.odometry if o.timestamp_s != 0.0]
    if len(readings) < 2 or len(log.lasers) < 2:
        return gaps
    intervals = np.diff([o.timestamp_s for o in readings])
    intervals = intervals[intervals > 0]
    if intervals.size == 0:
        return gaps
    period_s = float(np.median(intervals))
    lines = np.array([o.line_number for o in readings])
    laser_lines = np.array([r.line_number for r in log.lasers])
    times = np.array([r.timestamp_s for r in log.lasers])
    after = np.searchsorted(lines, laser_lines)  # the first reading after each laser message
    silent = after[1:] == after[:-1]  # none between the two messages
    last = np.array([readings[i - 1].timestamp_s if i > 0 else -np.inf for i in after])  # the last one before
    gaps[1:] = silent & (times[1:] - last[1:] > ODOMETRY_GAP_PERIODS * period_s)
    return gaps


def log_updates(
    slam: Slam, lasers: Sequence[LaserRecord], odometry: np.ndarray, gaps: np.ndarray | None = None
) -> Iterator[SlamUpdate]:
    """Each scan of ``lasers`` handed to ``slam`` with the odometry up to it, in the log's order: one update
    a scan, yielded before the next scan is read so that a caller can look at the SLAM between them.
    ``gaps`` (N,) marks the scans the odometry says nothing about (:func:`odometry_gaps`)."""
    history = OdometryHistory(horizon_s=1e12)
    clock = slam_clock(np.array([r.timestamp_s for r in lasers]))
    for k, record in enumerate(lasers):
        history.append(clock[k], *odometry[k])
        if gaps is not None and gaps[k]:
            slam.expect_unknown_motion()
        scan = record.to_scan()
        yield slam.update(replace(scan, time_s=np.full(len(scan), clock[k])), history)


def _parse_noise(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        sx, sth = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--odom-noise expects SIGMA_XY,SIGMA_THETA like 0.05,0.05, got {text!r}") from None
    if not (sx >= 0 and sth >= 0 and math.isfinite(sx) and math.isfinite(sth)):
        raise UsageError(f"--odom-noise values must be finite and >= 0, got {text!r}")
    return sx, sth


def run_carmen(
    log_path: str,
    out_dir: str,
    odom_noise: tuple[float, float] | None = None,
    seed: int = 1,
    max_scans: int | None = None,
    config_path: str | None = None,
    systematic: SystematicOdometryModel | None = None,
    consistency_scans: int = 60,
    anchor_first_scan: bool = True,
    calibrate_odometry: bool = True,
    closure_ambiguity: bool = False,
    match_doubt: bool = False,
    place_start: bool = False,
    calibrate_distance: bool = False,
    calibrate_lever_arm: bool = True,
    search_odometry_gaps: bool = False,
    wide_loop_search: bool = False,
) -> dict[str, Any]:
    """Run SLAM on a CARMEN log, write the outputs into ``out_dir``, return the statistics.

    ``systematic`` (the ``systematic`` odometry model): odometry from the log's poses
    with per-wheel scale errors, a track-width error and a drifting heading bias, plus
    ``odom_noise`` as white noise (:mod:`mazebot.slam.odometry_errors`).
    ``consistency_scans``: how many scans (spread over the log, the first always) are
    registered against the map of the others (:mod:`mazebot.slam.map_consistency`), at the
    SLAM's poses and at the reference's; 0 skips it. ``anchor_first_scan``: the finished map
    is re-anchored where the first scan registers against it (:func:`reanchor`); ``place_start``: then moved
    along the direction that registration leaves open onto the start's odometry (:func:`place_along_unobserved`).
    ``calibrate_odometry``: the odometry's heading calibrated online; ``closure_ambiguity``: a closure the
    search found refused where its window holds a look-alike; ``match_doubt``: a sequential match whose
    residual stands out of the recent ones searched again; ``calibrate_distance``: the odometry's distance scale
    calibrated online (all four :func:`laser_log_params`). ``search_odometry_gaps``: a scan the log's own
    odometry was silent before (:func:`odometry_gaps`) is matched as after unknown motion
    (:meth:`mazebot.slam.slam.Slam.expect_unknown_motion`); off, the gaps are only counted. Measured
    (branch ``wheels22``): it holds Seattle's 80° turn at scan 27 through a 4 m and a 5.6 m laser (30.6 and
    30.5 m RMS without it, 0.54 and 0.36 m with it) and takes that scan's heading error from 80° to 1°, but on
    Seattle as logged, which holds without it, the map comes out turned further about its start (0.165 to
    0.265 m RMS): an option. ``wide_loop_search``: loop candidates as far as the chain's drift reaches, at
    distinct places (:func:`laser_log_params`).
    """
    log = one_laser(read_carmen(log_path))
    if not log.lasers:
        raise UsageError(f"{log_path}: no laser messages (FLASER, RLASER, ROBOTLASER1/2 or RAWLASER1-4)")
    lasers = log.lasers[:max_scans] if max_scans else log.lasers
    reference = np.array([r.pose for r in lasers]).reshape(-1, 3)
    times = np.array([r.timestamp_s for r in lasers])
    drawn = None
    gaps = np.zeros(len(lasers), dtype=bool)  # odometry made from the poses has none
    if systematic is not None:
        white = odom_noise or (0.0, 0.0)
        odometry, drawn, _ = systematic_odometry(reference, systematic, white, np.random.default_rng(seed))
    elif odom_noise is not None:
        odometry = noisy_odometry(reference, odom_noise[0], odom_noise[1], np.random.default_rng(seed))
    else:
        odometry = log_odometry(log)[: len(lasers)]
        gaps = odometry_gaps(log)[: len(lasers)]
        if len(lasers) > 1 and not np.any(odometry):
            raise UsageError(
                f"{log_path}: no odometry (its ODOM lines and odometry fields are zero): give --odom-noise "
                "to make odometry from its poses"
            )
    searched_gaps = gaps if search_odometry_gaps else None
    config = load_config(config_path)
    params = laser_log_params(
        SlamParams.from_config(config.slam, config.lidar), calibrate_odometry, closure_ambiguity, match_doubt,
        calibrate_distance, calibrate_lever_arm, wide_loop_search,
    )
    odometry = from_first_pose(odometry, reference)
    slam = Slam(params, initial_pose=np.zeros(3))
    online = np.zeros_like(reference)
    scan_ms = []
    keyframe_scans: dict[int, tuple[int, bool]] = {}  # keyframe -> (the scan that made it, was it matched)
    wall0 = time.perf_counter()
    updates = log_updates(slam, lasers, odometry, searched_gaps)
    for k in range(len(lasers)):
        cpu0 = time.thread_time()
        update = next(updates)  # the scan's conversion (microseconds) is counted with its update
        scan_ms.append((time.thread_time() - cpu0) * 1e3)
        online[k] = update.pose
        if update.keyframe is not None:
            keyframe_scans[update.keyframe] = (k, update.matched)
    points = match_points(lasers, params)
    bias = remove_heading_bias(slam, params.sequential_heading_bias_sigmas)
    _, before_anchoring = slam.trajectory()
    edges = edge_chi2(slam, keyframe_scans, reference)
    # the map judged by itself, before it is re-anchored (a rigid move: only the first scan's row changes)
    judged_scans_ = judged_scans(len(points), consistency_scans or REANCHOR_NOISE_SCANS)
    own = scan_corrections(before_anchoring, points, judged_scans_, params.icp, neighbourhood(params))
    anchoring = reanchor(slam, own, heading_noise_rad(own)) if anchor_first_scan else None
    _, before_placing = slam.trajectory()
    placing = place_along_unobserved(slam, points, odometry, params) if place_start else None
    slam.rebuild_map()  # from the keyframes at their final, optimized (and re-anchored) poses
    seconds = time.perf_counter() - wall0
    _, final = slam.trajectory()

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"{t:.6f} {x:.6f} {y:.6f} {th:.6f}" for t, (x, y, th) in zip(times, final, strict=True)]
    traj_tmp = out / ".trajectory.txt.tmp"
    traj_tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    traj_tmp.replace(out / "trajectory.txt")
    three = slam.grid.three_state()
    write_map_png(three, out / "map.png")
    write_ros_map(slam.grid, out / "map")
    ms = np.asarray(scan_ms)
    # a log without corrected poses (its laser poses are its odometry) has no reference to judge by
    judged = odom_noise is not None or systematic is not None or not same_motion(odometry, reference)
    learnt = slam.odometry_noise
    judged_consistency = map_consistency(own, points, reference if judged else None, params, judged_scans_, final)
    if not consistency_scans:
        judged_consistency = {}
    return {
        "log": str(log_path),
        "scans": len(lasers),
        "keyframes": len(slam.keyframes),
        "loop_closures": len(slam.closures),
        "loop_closures_rejected": sum(slam.rejections.values()),
        "rejections": dict(slam.rejections.most_common()),
        "loop_closures_downweighted": slam.closures_downweighted,
        "loop_closures_set": slam.closures_from_set,
        "loop_closures_off_reference": closures_off_reference(slam, keyframe_scans, reference) if judged else None,
        "odometry_gaps": int(np.count_nonzero(gaps)),
        "odometry_gaps_searched": search_odometry_gaps,
        "wide_loop_search": wide_loop_search,
        "searches": slam.searches,
        "searches_won": slam.searches_won,
        "searches_any_heading": slam.searches_any_heading,
        "matches_doubted": slam.matches_doubted,
        "doubts_won": slam.doubts_won,
        "matches_seen_rescued": slam.matches_seen_rescued,
        "matches_widened": slam.matches_widened,
        "degenerate_retries": slam.degenerate_retries,
        "degenerate_retries_won": slam.degenerate_retries_won,
        "odom_noise": None if odom_noise is None else list(odom_noise),
        "odom_model": "log" if odom_noise is None and systematic is None else
        ("systematic" if systematic is not None else "white"),
        "odom_systematic": None if drawn is None else {k: round(v, 6) for k, v in vars(drawn).items()},
        "seed": seed,
        "odom_calibration": None if not calibrate_odometry else {
            "turn_scale": round(slam.calibration.scale, 5), "bias_rad_per_m": round(slam.calibration.bias_rad_per_m, 5),
            # what the recursion learnt, and each estimate's Wald statistic (the applied ones are shrunk by it)
            "learnt": [round(float(v), 5) for v in slam.calibration.learnt],
            "wald": [round(float(v), 2) for v in slam.calibration.wald()],
            "threshold": round(slam.calibration.threshold(), 2),  # the last test's
            "applied_scans": slam.calibration.applied_observations,  # matched scans after which it applied any
        },
        "odom_distance_calibration": None if not calibrate_distance else {
            "scale": round(slam.distance_calibration.estimate, 5),
            "learnt": round(slam.distance_calibration.learnt, 5),
            "wald": round(slam.distance_calibration.wald(), 2),
            "std": round(math.sqrt(slam.distance_calibration.variance()), 5)
            if slam.distance_calibration.observations > 1 else None,
            "observations": slam.distance_calibration.observations,
            "applied_scans": slam.distance_calibration.applied_observations,
        },
        "lever_arm": None if not calibrate_lever_arm else {
            "applied_m": [round(float(v), 4) for v in slam.lever_arm.estimate],
            "learnt_m": [round(float(v), 4) for v in slam.lever_arm.learnt],
            "wald": [round(float(v), 2) for v in slam.lever_arm.wald()],
            "threshold": round(slam.lever_arm.threshold(), 2),
            "observations": slam.lever_arm.observations,
            "applied_scans": slam.lever_arm.applied_observations,
        },
        "odom_noise_learnt": None if learnt is None else {
            "pairs": learnt.pairs,
            "xy_m_per_sqrt_m": round(math.sqrt(learnt.noise.xy_m2_per_m), 5),
            "theta_rad_per_sqrt_m_rad": round(math.sqrt(learnt.noise.theta_rad2_per_m), 5),
        },
        "reference": "the log's poses" if judged else None,
        "error": anchored_error(final, reference) if judged else None,
        "error_online": anchored_error(online, reference) if judged else None,
        "error_before_reanchor": anchored_error(before_anchoring, reference) if judged else None,
        "error_odometry": anchored_error(odometry, reference) if judged else None,
        "error_aligned": aligned_error(final, reference) if judged else None,
        "relative_error": relative_error(final, reference, lag=1) if judged else None,
        "relative_error_odometry": relative_error(odometry, reference, lag=1) if judged else None,
        "heading_bias": bias,
        "reanchor": anchoring,
        "start_placement": placing,
        "error_before_start_placement": anchored_error(before_placing, reference) if judged else None,
        "edge_chi2": edges if judged else {k: {**v, "reference_median": None, "reference_mean": None}
                                           if k != "graph" else v for k, v in edges.items()},
        **judged_consistency,
        "scan_ms_p50": round(float(np.percentile(ms, 50)), 3),
        "scan_ms_p99": round(float(np.percentile(ms, 99)), 3),
        "seconds": round(seconds, 3),
        "map": {"rows": int(three.shape[0]), "cols": int(three.shape[1]), "resolution_m": slam.grid.resolution_m},
        "out": str(out),
    }



#: the median of a chi² of 3 degrees of freedom: what a calibrated SE(2) edge's chi² has half the time
CHI2_MEDIAN_3DOF = 2.366


def edge_chi2(
    slam: Slam, keyframe_scans: dict[int, tuple[int, bool]], reference: np.ndarray
) -> dict[str, dict[str, Any]]:
    """Each kind of pose-graph edge's chi² (``eᵀΩe``), at the optimized poses and at the reference's.

    Kinds: ``matched`` (a sequential edge whose new keyframe's scan was matched: odometry
    and ICP), ``hinge`` (a sequential edge of odometry alone: the match was refused) and
    ``closure``. An edge whose information is honest has a chi² of 3 degrees of freedom
    against the truth, median :data:`CHI2_MEDIAN_3DOF`; against the optimized graph less
    (the optimization fits part of each residual). The reference (another SLAM's poses)
    has errors of its own, so its figure is an upper bound. Medians and means, nominal
    information (before the robust weights of :mod:`mazebot.slam.robust_closures`).
    ``graph``: the optimized graph's chi² over its redundancy (3 per edge beyond a
    spanning tree), the a-posteriori variance factor of a least-squares adjustment: 1
    when the edges' information is calibrated against each other (Förstner's variance
    components), more when they claim more than they agree.
    """
    ei, ej, z, omega = slam.graph.edge_arrays
    poses = slam.keyframe_poses()
    count = poses.shape[0]
    inside = (ei < count) & (ej < count)
    ei, ej, z, omega = ei[inside], ej[inside], z[inside], omega[inside]
    ref = np.array([reference[keyframe_scans[k][0]] if k in keyframe_scans else reference[0] for k in range(count)])
    matched = np.array([keyframe_scans.get(k, (0, True))[1] for k in range(count)])
    sequential = ej == ei + 1
    kinds = {"matched": sequential & matched[ej], "hinge": sequential & ~matched[ej], "closure": ~sequential}

    def chi2(vertices: np.ndarray) -> np.ndarray:
        e = relative_pose(z, relative_pose(vertices[ei], vertices[ej]))
        e[:, 2] = wrap_angle(e[:, 2])
        return np.einsum("mi,mij,mj->m", e, omega, e)

    own, against = chi2(poses), chi2(ref)
    # the whole graph's a-posteriori variance factor: its chi² over its redundancy (3 per edge beyond a tree)
    redundancy = 3 * (ei.size - (count - 1))
    out: dict[str, dict[str, Any]] = {"graph": {
        "edges": int(ei.size),
        "redundancy": redundancy,
        "optimized_chi2": round(float(own.sum()), 1),
        "variance_factor": round(float(own.sum()) / redundancy, 3) if redundancy > 0 else None,
    }}
    for kind, mask in kinds.items():
        n = int(mask.sum())
        out[kind] = {
            "edges": n,
            "optimized_median": round(float(np.median(own[mask])), 3) if n else None,
            "optimized_mean": round(float(np.mean(own[mask])), 3) if n else None,
            "reference_median": round(float(np.median(against[mask])), 3) if n else None,
            "reference_mean": round(float(np.mean(against[mask])), 3) if n else None,
        }
    return out


#: a loop closure farther than this from the reference's relative pose is counted as wrong (the reference's
#: own poses scatter by 1.5 cm and 0.45° per scan about its map: branch reallogs4)
CLOSURE_OFF_M = 0.3
CLOSURE_OFF_RAD = math.radians(2.0)


def closures_off_reference(
    slam: Slam, keyframe_scans: dict[int, tuple[int, bool]], reference: np.ndarray
) -> dict[str, int]:
    """How many accepted loop closures are off the reference's relative pose by more than
    :data:`CLOSURE_OFF_M` or :data:`CLOSURE_OFF_RAD`, all and those a set accepted; and how many
    left a direction free (``degenerate``: judged in the directions they constrain alone, their
    position along a corridor being the chain's) and of those how many are off."""
    out = {"off": 0, "set_off": 0, "degenerate": 0, "degenerate_off": 0}
    for c in slam.closures:
        if c.old not in keyframe_scans or c.new not in keyframe_scans:
            continue
        truth = relative_pose(reference[keyframe_scans[c.old][0]], reference[keyframe_scans[c.new][0]])
        e = relative_pose(truth, c.measurement)
        e[2] = float(wrap_angle(e[2]))
        if c.free_information is not None:  # the error's free component is no error of the closure's
            e = ObservedDirections.of(c.free_information).constrained_part(e, np.eye(3))
            out["degenerate"] += 1
        if math.hypot(float(e[0]), float(e[1])) > CLOSURE_OFF_M or abs(float(e[2])) > CLOSURE_OFF_RAD:
            out["off"] += 1
            out["set_off"] += int(c.by_set)
            out["degenerate_off"] += int(c.free_information is not None)
    return out


def match_points(lasers: list[LaserRecord], params: SlamParams) -> list[np.ndarray]:
    """Each laser message's points (sensor frame) between the preparation's minimum and maximum range."""
    prepare = params.prepare
    points = []
    for record in lasers:
        xy = record.points_xy(prepare.max_range_m)
        points.append(xy[np.hypot(xy[:, 0], xy[:, 1]) >= prepare.min_range_m])
    return points


#: the first scan's registration against the finished map re-anchors it only within these bounds:
#: the corrections measured on the Radish logs are 0-1° (white odometry noise) and 0.7-3.1°
#: (systematic odometry errors), 1-8 cm; more says the map near the start, or the registration,
#: is not to be trusted
REANCHOR_MAX_RAD = math.radians(5.0)
REANCHOR_MAX_M = 0.3
#: ... and only if its heading correction exceeds this many times the RMS heading correction of the
#: map's other scans: a correction within the map's own scatter is noise (ACES' maps scatter by
#: 0.3-0.8° per scan). Moving the frame by a correction c that is noise of that scatter σ turns a
#: right map by about σ; leaving a real offset costs all of it: break-even near c = σ, and 1.5 σ
#: leans towards leaving the frame alone
REANCHOR_SIGMAS = 1.5
#: scans judged for that scatter when ``--consistency-scans`` is 0
REANCHOR_NOISE_SCANS = 60


def heading_noise_rad(corrections: np.ndarray) -> float | None:
    """RMS heading correction (rad) of the judged scans other than the first (None: fewer than ten judged)."""
    others = corrections[corrections[:, 0] != 0]
    if others.shape[0] < 10:
        return None
    return float(np.sqrt(np.mean(others[:, 3] ** 2)))


def anchor_move(anchor: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """The rigid move (map frame) that takes the first scan from where it registers (``anchor`` corrected by
    ``correction``, in its own frame) onto ``anchor``: applied to every other pose, it re-anchors a map."""
    return compose(anchor, inverse(compose(anchor, correction)))


def reanchor(slam: Slam, corrections: np.ndarray, heading_noise_rad: float | None) -> dict[str, Any]:
    """Re-anchor the finished map where the first scan registers against it; returns what was done.

    The map frame is the first scan's: keyframe 0 is held at the log's first pose, and
    the map's orientation about it comes from the first few matches only (in-place turns
    of 30° with a 180° laser on the Radish logs, each a few tenths of a degree off), so
    the whole map is turned about the start by that much, and by decimetres at its far
    end, however consistent it is. Once the map is finished, the first scan registered
    against the map of the others (``corrections``, from
    :func:`mazebot.slam.map_consistency.scan_corrections`: the scans more than three away
    in the log, the 40 nearest within 10 m) says where the map puts it, measured against
    every later visit of the start. The whole map (every keyframe but the first, and the
    scans that follow them) is moved rigidly so that this pose is the anchor, and the
    first scan stays there: nothing else inside the map changes, only its frame.

    Left as it is when the first scan was not registered, when the correction exceeds
    :data:`REANCHOR_MAX_RAD` / :data:`REANCHOR_MAX_M`, or when its heading is within
    :data:`REANCHOR_SIGMAS` times ``heading_noise_rad``, the scatter of the map's other
    scans (None: no such test).
    """
    first = corrections[corrections[:, 0] == 0]
    if first.shape[0] == 0:
        return {"applied": False, "heading_deg": None, "shift_m": None, "noise_deg": None}
    c = first[0, 1:]
    shift_m, heading_rad = math.hypot(float(c[0]), float(c[1])), float(c[2])
    significant = heading_noise_rad is None or abs(heading_rad) > REANCHOR_SIGMAS * heading_noise_rad
    applied = significant and abs(heading_rad) <= REANCHOR_MAX_RAD and shift_m <= REANCHOR_MAX_M
    if applied:
        move = anchor_move(slam.keyframes[0].pose, c)
        for keyframe in slam.keyframes[1:]:  # keyframe 0, the first scan, is where it registered: the anchor
            keyframe.pose = compose(move, keyframe.pose)
    return {
        "applied": applied,
        "heading_deg": round(math.degrees(heading_rad), 3),
        "shift_m": round(shift_m, 4),
        "noise_deg": None if heading_noise_rad is None else round(math.degrees(heading_noise_rad), 3),
    }


def remove_heading_bias(slam: Slam, sigmas: float) -> dict[str, Any] | None:
    """Take the heading bias every sequential match shares out of the finished graph, where significant.

    :func:`mazebot.slam.heading_bias.sequential_heading_bias` estimates it with the graph's headings
    from its loops; beyond ``sigmas`` standard errors it is subtracted from every sequential edge's
    measured turn and the graph optimized again as a loop-closure job does (closures robust, the
    first keyframe held), the keyframes moved to the result. Within them nothing moves: the
    map is the one the run made. ``sigmas`` 0 (``[slam.graph] sequential_heading_bias_sigmas``,
    the default): nothing is estimated. Returns what was found and done (None: off, or no loop).
    """
    if sigmas <= 0 or len(slam.keyframes) < 3:
        return None
    cpu0 = time.thread_time()
    ei, ej, z, omega = slam.graph.edge_arrays
    vertices = slam.keyframe_poses()
    sequential = ej == ei + 1
    found = sequential_heading_bias(vertices, ei, ej, z, omega, sequential)
    if found is None:
        return None
    applied = found.significant(sigmas)
    if applied:
        corrected = z.copy()
        corrected[sequential, 2] -= found.bias_rad
        robust = optimize_dcs(
            vertices, (ei, ej, corrected, omega), ej - ei > 1, slam.params.loop.dcs_phi,
            max_iterations=slam.params.optimize_iterations,
        )
        graph = PoseGraph()
        graph.add_vertices(robust.vertices)
        graph.add_edges(ei, ej, corrected, omega)
        slam.graph = graph
        for keyframe, pose in zip(slam.keyframes, robust.vertices, strict=True):
            keyframe.pose = pose.copy()
    return {
        "applied": applied,
        "bias_deg": round(math.degrees(found.bias_rad), 5),
        "std_deg": round(math.degrees(found.std_rad), 5),
        "variance_factor": round(found.variance_factor, 3),
        "cpu_ms": round((time.thread_time() - cpu0) * 1e3, 1),  # the estimate and, if applied, the optimization
    }


def neighbourhood(params: SlamParams) -> Neighbourhood:
    """The map a scan is judged against (:mod:`mazebot.slam.map_consistency`), its points thinned as the SLAM's."""
    return Neighbourhood(voxel_m=params.prepare.voxel_size_m, normal_radius_m=params.normals.radius_m)


#: the scans of the start whose odometry places the map along a direction the first scan does not fix: those
#: before the odometry has travelled this far from the first pose. An in-place turn (the start of every log
#: here) moves the robot a few centimetres a scan, and white odometry noise of 0.1 m per metre then errs by a
#: centimetre or two over it, where the first match along a corridor can slide by a decimetre (below)
START_ODOMETRY_PATH_M = 0.5


def place_along_unobserved(
    slam: Slam, points: list[np.ndarray], odometry: np.ndarray, params: SlamParams
) -> dict[str, Any]:
    """Move the finished map along the direction its first scan's registration leaves open, onto the odometry.

    The map frame is the first scan's pose, and the rest of the map hangs on it through the
    first matches. Where the start is a corridor, the first scan registered against the
    finished map (the others' scans at their poses, :func:`mazebot.slam.map_consistency.register_scan`)
    fixes it across the corridor and in heading but not along it: ICP stays wherever it is
    started along the corridor (the Intel log's first scan: ±0.1 m, a weak-direction standard
    deviation of 16-275 mm against 0.8 mm across). Along that direction the scans say nothing
    about where the first pose sits in the map, and the first matches' choice is a local
    optimum (the Intel log's second scan against the first converges 0.115 m along the
    corridor from the corrected poses' increment, at a smaller residual, on every seed) that
    the whole map then carries. The odometry of the start (:data:`START_ODOMETRY_PATH_M`) is the
    only measurement of that direction: the map, every keyframe but the first (the first
    scan sits anywhere along the direction alike), is moved along it by the mean offset
    of the start scans' odometry positions from their map positions. Nothing inside the map
    changes, and nothing across the corridor or in heading. Left alone when the registration
    is not degenerate, when no scan of the start has odometry, when the move would exceed
    :data:`REANCHOR_MAX_M` (the odometry or the map is then not to be trusted there), or when it
    is within :data:`REANCHOR_SIGMAS` times the odometry's own error over the start's path (by
    the noise model learnt from the matches): as for the heading, a move within the noise of its
    measurement is noise (on the stand-in Intel run of seed 3 a move of 5 mm made it 1.6 mm worse).

    ``slam run --start-placement``; off by default. Measured (branch ``reallogs13``): it moved the
    Intel maps whose second scan slid (0.12-0.14 m) and no Radish map (their first scan's
    registration is not degenerate), better on five (``0.1,0.1`` seed 1 0.239 -> 0.164 m, ``0.05``
    seed 4 0.137 -> 0.094 m) and worse on six (``0.1,0.1`` seed 2 0.136 -> 0.199 m): along the corridor
    nothing in the scans ties one visit of the start to another, and where the later visits sit
    elsewhere along it than the start's own scans, moving the whole map moves the visits that were right.
    """
    _, poses = slam.trajectory()
    nothing = {"applied": False, "shift_m": None, "noise_m": None, "direction_deg": None, "scans": 0}
    if poses.shape[0] < 2 or odometry.shape[0] < poses.shape[0]:
        return nothing
    around = neighbourhood(params)
    found = register_scan(poses, thin_scans(points, around.voxel_m), 0, params.icp, around)
    if found is None or not found.converged or not found.degenerate:
        return nothing
    strength, directions = np.linalg.eigh(found.information[:2, :2])
    along = directions[:, int(np.argmin(strength))]  # the map-frame direction the registration leaves open
    path = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(odometry[: poses.shape[0], :2], axis=0).T))))
    start = np.flatnonzero((path <= START_ODOMETRY_PATH_M) & (np.arange(poses.shape[0]) > 0))
    if start.size == 0:
        return nothing
    offset = float(np.mean((odometry[start, :2] - poses[start, :2]) @ along))
    # the odometry's own error over the start's path, by the noise model the matches taught the filter
    noise_m = math.sqrt(slam.ekf.noise.xy_m2_per_m * float(path[start[-1]]))
    result = {"applied": False, "shift_m": round(offset, 4), "noise_m": round(noise_m, 4),
              "direction_deg": round(math.degrees(math.atan2(along[1], along[0])), 2), "scans": int(start.size)}
    if abs(offset) > REANCHOR_MAX_M or abs(offset) <= REANCHOR_SIGMAS * noise_m:
        return result
    for keyframe in slam.keyframes[1:]:
        keyframe.pose = keyframe.pose + np.array([*(offset * along), 0.0])
    return {**result, "applied": True}


def map_consistency(
    own: np.ndarray,
    points: list[np.ndarray],
    reference: np.ndarray | None,
    params: SlamParams,
    judged: list[int],
    trajectory: np.ndarray,
) -> dict[str, Any]:
    """The map's self-consistency (:mod:`mazebot.slam.map_consistency`) at the SLAM's poses and the reference's.

    ``own``: the SLAM's scans registered against the others at its poses (before
    :func:`reanchor`); the reference's are registered here, the same ``judged`` scans with
    the same points (:func:`match_points`). ``first_scan_heading_deg`` is what the map asks
    of the scan the map frame is anchored at: a reference whose own first pose sits off
    its map turns every anchored figure. ``error_reference_reanchored`` measures that:
    ``trajectory`` (the SLAM's final one) against the reference re-anchored where its own
    first scan registers against its own map (:func:`anchor_move`, the rule :func:`reanchor`
    follows for the SLAM's map, without its gate), None when that scan was not registered.
    On the Radish logs Freiburg 101's first corrected pose sits 0.49°
    off its own map, and the SLAM's maps, whose first scans sit on theirs, are 0.15-0.20 m
    RMS off the reference as given and 0.06-0.07 m off it re-anchored.
    """
    out: dict[str, Any] = {"consistency": {**consistency(own), "first_scan_heading_deg": first_scan_heading_deg(own)}}
    if reference is None:
        return {**out, "consistency_reference": None, "error_reference_reanchored": None}
    corrections = scan_corrections(reference, points, judged, params.icp, neighbourhood(params))
    out["consistency_reference"] = {
        **consistency(corrections), "first_scan_heading_deg": first_scan_heading_deg(corrections)
    }
    first = corrections[corrections[:, 0] == 0]
    out["error_reference_reanchored"] = None
    if first.shape[0]:
        reanchored = reference.copy()
        reanchored[1:] = compose(anchor_move(reference[0], first[0, 1:]), reference[1:])
        out["error_reference_reanchored"] = anchored_error(trajectory, reanchored)
    return out


def _cmd_run(args: argparse.Namespace) -> int:
    if args.odom_systematic is not None and args.odom_model != "systematic":
        raise UsageError("--odom-systematic needs --odom-model systematic")
    systematic = parse_systematic(args.odom_systematic) if args.odom_model == "systematic" else None
    stats = run_carmen(
        args.carmen, args.out, _parse_noise(args.odom_noise), args.seed, args.max_scans, args.config, systematic,
        args.consistency_scans, not args.no_reanchor, args.odom_calibration, args.closure_ambiguity, args.match_doubt,
        args.start_placement, args.odom_distance_calibration, args.lever_arm, args.odometry_gaps,
        args.wide_loop_search,
    )
    print(json.dumps(stats))
    return EXIT_OK


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    slam = sub.add_parser("slam", help="run the SLAM offline on recorded data")
    ssub = slam.add_subparsers(dest="slam_command", required=True)
    run = ssub.add_parser(
        "run",
        help="SLAM on a CARMEN laser log: trajectory.txt, map.png, map.pgm + map.yaml, JSON statistics",
        description="Run the SLAM on a CARMEN log (FLASER/RLASER/ROBOTLASER1 + ODOM) and compare its trajectory "
        "with the poses the log carries.",
    )
    run.add_argument("--carmen", required=True, metavar="LOG", help="CARMEN log file (plain, or gzip: *.gz)")
    run.add_argument(
        "--odom-noise",
        metavar="SX,STH",
        default=None,
        help="derive odometry from the log's poses with this noise: SX m per m travelled, STH rad per m and per rad "
        "(e.g. 0.05,0.05); default: the log's own odometry",
    )
    defaults = SystematicOdometryModel()
    run.add_argument(
        "--odom-model",
        choices=("white", "systematic"),
        default="white",
        help="white: --odom-noise alone (independent per scan); systematic: the odometry of a differential drive "
        "whose wheels and track width are off (a scale error per wheel: distance scale, and heading drift on "
        "straights and in turns) with a heading bias that drifts as a random walk, all drawn from --seed, "
        "plus --odom-noise as white noise (default: white)",
    )
    run.add_argument(
        "--odom-systematic",
        metavar="WHEEL,TRACK,BIAS,WALK",
        default=None,
        help="standard deviations of the systematic model: per-wheel scale, track-width scale, heading bias in "
        "rad/m, its random walk in rad/m per sqrt(m) travelled (default "
        f"{defaults.wheel_scale_std},{defaults.track_scale_std},{defaults.bias_rad_per_m_std},"
        f"{defaults.bias_walk_rad_per_m_per_sqrt_m}; nominal track {defaults.track_width_m} m)",
    )
    run.add_argument(
        "--odom-calibration",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="calibrate the odometry's heading online from the scan matches (a turn scale and a drift per metre, "
        "as the robot does, each applied only as far as the matches show it beyond white noise): for wheel "
        "odometry with systematic errors; on by default, --no-odom-calibration turns it off",
    )
    run.add_argument(
        "--odom-distance-calibration",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="calibrate the odometry's distance scale online from the scan matches that fix the direction of "
        "travel (the wheels' mean diameter; applied as its posterior mean under a prior of a couple of percent on "
        "the wheels); off by default",
    )
    run.add_argument(
        "--lever-arm",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="learn where the laser sits relative to the point the odometry measures from the matched turns "
        "(applied only as far as the matches show it); on by default, --no-lever-arm turns it off",
    )
    run.add_argument(
        "--odometry-gaps",
        action="store_true",
        help="match a scan the log's own odometry was silent before (no ODOM reading for over ten of its periods) "
        "as after unknown motion: the whole correlative window at every heading, the prediction widened to it; "
        "off by default (the gaps are counted either way)",
    )
    run.add_argument(
        "--wide-loop-search",
        action="store_true",
        help="look for loop closures as far as 3 std of the chain's drift reach (no 5 m cap) and, where that drift "
        "exceeds 1 m, verify the nearest keyframe of up to three distinct places; off by default",
    )
    run.add_argument(
        "--closure-ambiguity",
        action="store_true",
        help="refuse a loop closure the correlative search found when another alignment of its window, over 1 m "
        "from the best, scores 0.9 of it (a look-alike along a corridor); off by default",
    )
    run.add_argument(
        "--match-doubt",
        action="store_true",
        help="search a sequential match again over the whole correlative window when its residual exceeds 4 times "
        "the median of the last 50 matched scans', and take the search's match if it is better on residual, "
        "inlier ratio and table score; off by default",
    )
    run.add_argument("--seed", type=int, default=1, help="seed of the odometry noise (default 1)")
    run.add_argument("--max-scans", type=positive_int, default=None, metavar="N", help="only the first N scans")
    run.add_argument(
        "--consistency-scans",
        type=non_negative_int,
        default=60,
        metavar="N",
        help="register N scans (spread over the log) against the map of the others, at the SLAM's poses and at the "
        "reference's: how crisp each map is, without trusting the reference (default 60; 0: skip)",
    )
    run.add_argument(
        "--no-reanchor",
        action="store_true",
        help="keep the map where the first scans' matches put it (default: moved rigidly so that the first scan, "
        "registered against the finished map, sits at the log's first pose)",
    )
    run.add_argument(
        "--start-placement",
        action="store_true",
        help="move the finished map along a direction the first scan's registration against it leaves open (a "
        "corridor at the start) onto the start's odometry, where the two differ by more than the odometry's own "
        "error; off by default",
    )
    run.add_argument("--out", required=True, metavar="DIR", help="output directory")
    run.add_argument("--config", default=None, help="config file whose [slam] section is the starting point")
    run.set_defaults(func=_cmd_run)
