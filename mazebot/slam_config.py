"""The ``[slam]`` section of ``config.toml``: its nested sections are the SLAM's parameter objects.

Each nested section (``[slam.icp]``, ``[slam.loop]``, ``[slam.grid]`` ...) is the frozen
dataclass the algorithm that reads it takes, defined once here with its defaults, units,
ranges and descriptions, as in KISS-ICP's ``config/config.py``: ``IcpParams()`` is the
daemon's ICP, and the config holds an ``IcpParams``. The constraints are pydantic
``Field`` metadata, checked when a config file is parsed (``mazebot.config``); an
algorithm builds its parameters in code without validation, as plain dataclasses.

A section whose algorithm needs behaviour of its own (``GridParams.new_grid``) or values
from another section (the lidar's range and mounting, the maze's pitch) is subclassed
beside the algorithm, adding only those; :func:`as_params` turns the config's section
into that subclass, field by field, without a mapping written by hand.

Until this layout, every ``[slam]`` key was flat (``icp_max_iterations``); :data:`FLAT_KEYS`
says where each one went, and ``mazebot.config`` moves an old file's keys there with a
warning.

This module imports only pydantic: ``mazebot.config`` (and ``mazebot motors stop``) loads it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

#: The maze's wall pitch, 1 ft (docs/design.md, "The reference robot"): the default of
#: ``[planner] cell_size_m``, the one key for it; ``mazebot.config`` derives the others from that key.
MAZE_CELL_M = 0.3048

#: Unknown keys in a nested section are an error, as in every other section.
_FORBID = ConfigDict(extra="forbid")


@dataclass(frozen=True)
class PrepareSection:
    """Scan preparation: impulse rejection, range limit and thinning (``mazebot.slam.preprocess``).

    The lidar's own range and mounting come from ``[lidar]``
    (:class:`mazebot.slam.preprocess.PrepareParams` adds them).
    """

    __pydantic_config__ = _FORBID

    max_range_m: Annotated[float, Field(gt=0.2, le=40, description=(
        "farther returns only clear space (never matched, never a wall); at most [lidar] max_range_m"))] = 8.0
    median_window: Annotated[int, Field(ge=1, le=15, description=(
        "samples in the running median of impulse rejection (odd)"))] = 3
    impulse_abs_m: Annotated[float, Field(ge=0, description=(
        "a sample this far plus impulse_rel of its median from its median is a spike"))] = 0.05
    impulse_rel: Annotated[float, Field(ge=0, description="relative part of the spike threshold")] = 0.05
    circular: Annotated[bool, Field(description=(
        "a scan is a full turn: its first and last samples are neighbours"))] = True
    voxel_size_m: Annotated[float, Field(gt=0.001, le=0.5, description="point spacing of a scan for matching")] = 0.025

    def __post_init__(self) -> None:
        if self.median_window < 1 or self.median_window % 2 == 0:
            raise ValueError(f"median_window must be odd and positive, got {self.median_window}")
        if self.voxel_size_m <= 0:
            raise ValueError(f"voxel_size_m must be positive, got {self.voxel_size_m}")


@dataclass(frozen=True)
class MotionSection:
    """Odometry noise of the EKF's motion model, as variance growth per metre and per radian."""

    __pydantic_config__ = _FORBID

    xy_m2_per_m: Annotated[float, Field(gt=0, description=(
        "odometry position variance growth per metre travelled, each axis ((2 cm)² per m)"))] = 4e-4
    theta_rad2_per_m: Annotated[float, Field(gt=0, description=(
        "odometry heading variance per metre travelled ((0.01 rad)² per m)"))] = 1e-4
    theta_rad2_per_rad: Annotated[float, Field(gt=0, description=(
        "odometry heading variance per radian turned ((0.05 rad)² per rad)"))] = 2.5e-3
    estimate: Annotated[bool, Field(description=(
        "learn the three variances above from the data: the disagreement between the odometry's and the "
        "scan matches' increments (the values above are the prior, used until enough matches; off on the "
        "robot, whose noise is measured; on for laser logs, whose odometry nobody described)"))] = False
    estimate_min_matches: Annotated[int, Field(ge=1, le=100000, description=(
        "matched increments before the estimate replaces the prior"))] = 20
    estimate_window: Annotated[int, Field(ge=1, le=100000, description=(
        "the estimate is over this many newest matched increments (the odometry may change: a floor, a load)"))] = 200
    estimate_floor_xy_m2_per_m: Annotated[float, Field(gt=0, description=(
        "the learned position variance never goes below this ((1 cm)² per m: the matches' own error)"))] = 1e-4
    estimate_floor_theta_rad2: Annotated[float, Field(gt=0, description=(
        "the learned heading variance per metre and per radian never goes below this ((0.005 rad)²)"))] = 2.5e-5


@dataclass(frozen=True)
class IcpParams:
    """Point-to-line ICP (``mazebot.slam.icp``); distances in metres, angles in radians."""

    __pydantic_config__ = _FORBID

    max_iterations: Annotated[int, Field(ge=1, le=1000, description="ICP iterations at most")] = 150
    converged_translation_m: Annotated[float, Field(gt=0, description=(
        "ICP converged: last step below this ..."))] = 0.01
    converged_rotation_rad: Annotated[float, Field(gt=0, description="... and below this rotation")] = 0.01
    stop_translation_m: Annotated[float, Field(gt=0, description=(
        "ICP refines until its step is below this ..."))] = 5e-4
    stop_rotation_rad: Annotated[float, Field(gt=0, description="... and this rotation")] = 5e-4
    max_correspondence_m: Annotated[float, Field(gt=0, description=(
        "first distance gate of ICP correspondences (about the initial pose error)"))] = 0.3
    min_correspondence_m: Annotated[float, Field(gt=0, description=(
        "the adaptive gate never shrinks below this"))] = 0.05
    candidates: Annotated[int, Field(ge=1, le=128, description=(
        "nearest neighbours searched when the nearest faces away from the lidar"))] = 16
    robust_scale_min_m: Annotated[float, Field(gt=0, description=(
        "floor of the Cauchy kernel's scale (unweighted residuals)"))] = 0.01
    degeneracy_ratio: Annotated[float, Field(ge=0, lt=1, description=(
        "eigenvalue ratio below which a direction counts as unobservable"))] = 0.02
    sigma_min_m: Annotated[float, Field(gt=0, description=(
        "floor of the residual std used for the information matrix (unweighted)"))] = 0.005
    min_correspondences: Annotated[int, Field(ge=3, description=(
        "fewer matches than this: give up, keep the prior"))] = 10
    range_noise_ratio: Annotated[float, Field(ge=0, lt=0.3, description=(
        "weight ICP residuals by the lidar's range noise, std / range (A1: 0.01; 0: all points alike)"))] = 0.0
    noise_floor_m: Annotated[float, Field(gt=0, description=(
        "... plus this std that does not grow with range (submap pose errors)"))] = 0.002
    robust_scale_min_sigma: Annotated[float, Field(gt=0, description=(
        "floor of the Cauchy scale on normalized residuals, in std"))] = 2.0
    min_variance_factor: Annotated[float, Field(gt=0, description=(
        "the information never trusts the points more than the noise model"))] = 1.0
    information_cluster_rad: Annotated[float, Field(ge=0, le=3.2, description=(
        "residuals on one wall err together: ICP's information from its covariance clustered by wall (normals "
        "within this angle ...), added to its Hessian's, never surer than either (0: the Hessian's alone)"
    ))] = 0.0
    information_cluster_m: Annotated[float, Field(gt=0, description=(
        "... and lines within this distance of each other are one wall"))] = 0.25
    information_cluster_filter: Annotated[bool, Field(description=(
        "the filter takes that clustered information too (false: only the pose graph's sequential edges and loop "
        "closures do; the filter, and the correlative window its uncertainty sets, keep the Hessian's)"))] = True

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be at least 1, got {self.max_iterations}")
        if not 0.0 < self.min_correspondence_m <= self.max_correspondence_m:
            raise ValueError(
                f"need 0 < min_correspondence_m <= max_correspondence_m, got "
                f"{self.min_correspondence_m}, {self.max_correspondence_m}"
            )
        if not 0.0 <= self.degeneracy_ratio < 1.0:
            raise ValueError(f"degeneracy_ratio must be in [0, 1), got {self.degeneracy_ratio}")
        if self.range_noise_ratio < 0.0:
            raise ValueError(f"range_noise_ratio must be at least 0, got {self.range_noise_ratio}")
        if self.range_noise_ratio > 0.0 and self.noise_floor_m <= 0.0:
            raise ValueError(f"noise_floor_m must be positive with range noise weighting, got {self.noise_floor_m}")


@dataclass(frozen=True)
class NormalParams:
    """Surface normals of keyframe points (``mazebot.slam.icp.estimate_normals``)."""

    __pydantic_config__ = _FORBID

    neighbours: Annotated[int, Field(ge=3, le=50, description="neighbours for surface normals")] = 10
    radius_m: Annotated[float, Field(gt=0, description=(
        "neighbours farther than this do not count for a normal"))] = 0.1
    max_line_spread: Annotated[float, Field(gt=0, le=1, description=(
        "smallest / largest eigenvalue of a neighbourhood that is a line"))] = 0.2
    smooth: Annotated[bool, Field(description=(
        "move each point onto the line fitted through its neighbours"))] = True
    smooth_whole_face_only: Annotated[bool, Field(description=(
        "with smooth, move only points whose neighbours all lie within radius_m on their own face"))] = False
    smooth_scan: Annotated[bool, Field(description=(
        "with smooth, match each scan's own points smoothed onto their lines the same way (off: as measured)"))] = False
    smooth_max_span_m: Annotated[float, Field(ge=0, description=(
        "with smooth, move only points whose neighbours on their face span at most this length of their line "
        "(0: no limit)"))] = 0.0
    pool_far_normals_beyond_m: Annotated[float, Field(ge=0, description=(
        "give a submap the hits farther than this from their lidar that their own scan gives no normal (far hits "
        "on walls seen at a grazing angle, their neighbours farther apart than radius_m) a normal estimated from "
        "all its keyframes' points pooled, so its walls reach as far as the scans saw (0: off, each keyframe keeps "
        "only the hits with a normal of their own, on a laser log's corridor none beyond about 6 m; the near hits "
        "without one are mostly clutter and corners, and given one they turned the Intel map by 1.5 degrees)"))] = 0.0


@dataclass(frozen=True)
class CorrelativeParams:
    """A correlative search (Olson, ICRA 2009); distances in metres, angles in radians.

    ``window_xy_m`` / ``window_theta_rad`` are half-widths about the initial pose;
    ``levels`` the branch-and-bound table levels above the fine one (block ``2^levels``
    cells at the top). Points farther than ``max_range_m`` from the lidar are left out
    (they would set a heading step too fine for the near ones), and at most
    ``max_points`` of the rest are used, evenly spread. ``min_score`` is the score below
    which the search found nothing worth trusting.
    """

    __pydantic_config__ = _FORBID

    resolution_m: Annotated[float, Field(gt=0.001, le=1, description="cell of the correlative likelihood table")] = 0.03
    sigma_m: Annotated[float, Field(gt=0, le=1, description=(
        "smoothing of that table (std of a point's position)"))] = 0.04
    window_xy_m: Annotated[float, Field(ge=0, le=5, description=(
        "sequential search: half-width in x and y (under half a maze cell) ..."))] = 0.12
    window_theta_rad: Annotated[float, Field(ge=0, le=3.2, description="... and in heading")] = 0.35
    levels: Annotated[int, Field(ge=0, le=8, description="branch-and-bound levels of the sequential search")] = 2
    max_range_m: Annotated[float, Field(gt=0, description=(
        "the search uses scan points this close to the lidar ..."))] = 4.0
    max_points: Annotated[int, Field(ge=10, description="... at most this many of them")] = 200
    min_score: Annotated[float, Field(ge=0, le=1, description="a search scoring less found nothing (0..1)")] = 0.35

    def __post_init__(self) -> None:
        if not (self.resolution_m > 0 and self.sigma_m > 0 and self.max_range_m > 0):
            raise ValueError("resolution_m, sigma_m and max_range_m must be positive")
        if self.window_xy_m < 0 or self.window_theta_rad < 0 or self.levels < 0 or self.max_points < 1:
            raise ValueError("windows and levels must not be negative, max_points at least 1")


@dataclass(frozen=True)
class LoopSection:
    """Loop closure: candidate search and acceptance tests (``mazebot.slam.loop_closure``).

    The correlative search about the prior is the ``[slam.search]`` one with the loop
    window of ``[slam] loop_corr_*`` (:class:`mazebot.slam.loop_closure.LoopClosureParams`
    adds it).
    """

    __pydantic_config__ = _FORBID

    search_radius_m: Annotated[float, Field(gt=0, description="look for loop closures at least this close ...")] = 0.25
    max_search_radius_m: Annotated[float, Field(gt=0, description="... and never farther than this")] = 1.0
    sigma_scale: Annotated[float, Field(ge=0, description=(
        "search radius grows by this many std of the drift"))] = 3.0
    min_keyframe_gap: Annotated[int, Field(ge=2, description="a candidate is at least this many keyframes old")] = 40
    min_gap_m: Annotated[float, Field(ge=0, description=(
        "... or, where the keyframes lie farther apart, this much travel: the gap in keyframes is this over "
        "the median spacing of the keyframes so far, never more than min_keyframe_gap (0: the count alone; "
        "a laser log's scans may lie 1 m or 2 m apart)"))] = 0.0
    submap_half_width: Annotated[int, Field(ge=0, le=100, description=(
        "candidate submap: keyframes i-k .. i+k"))] = 6
    attempt_every: Annotated[int, Field(ge=1, description="look for loop closures every this many keyframes")] = 3
    closed_reach_keyframes: Annotated[int, Field(ge=0, description=(
        "skip a candidate whose two keyframes lie within this many of an accepted closure's two: the graph "
        "ties those places already, through that closure (0: verify every candidate; 5 halves the "
        "worker's CPU on a 6x6 maze but let a 16x16 tour's largest error grow from 8.4-11.4 to 12.2 mm, "
        "3 kept it at 10.6 mm)"))] = 3
    max_candidates: Annotated[int, Field(ge=1, description="candidates verified per attempt (nearest first)")] = 1
    distinct_places: Annotated[bool, Field(description=(
        "candidates beyond the nearest are other places, and only where sigma_scale std of the drift exceed "
        "search_radius_m: a keyframe whose submap (submap_half_width each side) overlaps a chosen candidate's is "
        "passed over (off: the nearest keyframes, mostly one place's)"))] = False
    anchor_candidate: Annotated[bool, Field(description=(
        "verify keyframe 0 too whenever it is in sight within max_search_radius_m, against its revolutions at "
        "rest alone (closures to it turn the map about the start onto the start's own view: they anchor the "
        "wall grid)"))] = True
    min_fitness: Annotated[float, Field(ge=0, le=1, description="accept: at least this share of points matched")] = 0.8
    overlap_fitness: Annotated[bool, Field(description=(
        "a match below min_fitness still passes if its inlier ratio among the points the submap could have "
        "seen (inside its keyframes' beams) reaches min_fitness: a building's doorways and far corridor sides "
        "have nothing to match (off: the ratio among all points)"))] = False
    min_overlap: Annotated[float, Field(ge=0, le=1, description=(
        "... and at least this share of the points lies where the submap could have seen it"))] = 0.5
    overlap_margin_m: Annotated[float, Field(ge=0, description=(
        "a point is seen by a beam that reached at least this close to it"))] = 0.2
    max_rmse_m: Annotated[float, Field(gt=0, description="accept: point-to-line RMS at most this")] = 0.012
    min_correspondences: Annotated[int, Field(ge=3, description="accept: at least this many matched points")] = 40
    accept_degenerate: Annotated[bool, Field(description=(
        "accept matches that leave a direction unconstrained (a straight corridor), with information, "
        "correction and chi2 test in the directions they constrain only"))] = False
    gate_chi2: Annotated[float, Field(gt=0, description=(
        "accept: correction consistent with odometry (chi2, 3 dof; 11.34: 99 %)"))] = 11.34
    max_correction_m: Annotated[float, Field(gt=0, description=(
        "accept: the correction moves at most this far ..."))] = 0.10
    max_correction_rad: Annotated[float, Field(gt=0, description="... and turns at most this much")] = 0.15
    correction_sigmas: Annotated[float, Field(ge=0, description=(
        "... or, if larger, this many std of the chain's drift, and the search about the prior as wide "
        "(0: the fixed limits alone)"))] = 0.0
    ambiguity_shift_m: Annotated[float, Field(ge=0, description=(
        "retry ICP this far off (one cell: [planner] cell_size_m unless set); another good fit there rejects "
        "(0: off)"))] = MAZE_CELL_M
    ambiguity_tolerance_m: Annotated[float, Field(gt=0, description=(
        "a retry ending farther than this from the match is another fit"))] = 0.05
    ambiguity_fitness_ratio: Annotated[float, Field(gt=0, le=1, description=(
        "that other fit counts if its inlier ratio is this share of the match's ..."))] = 0.85
    ambiguity_rmse_ratio: Annotated[float, Field(ge=1, description=(
        "... and its residual at most this many times"))] = 4.0
    search_ambiguity_ratio: Annotated[float, Field(ge=0, le=1, description=(
        "refuse a closure the correlative search found when another pose of its window scores at least this "
        "share of the best (0: off) ..."))] = 0.0
    search_peak_separation_m: Annotated[float, Field(gt=0, description=(
        "... counting poses this far from the best and farther and parted from it by a dip in the score below "
        "that share of theirs (nearer ones, and a ridge along a corridor, are the best's own peak)"))] = 1.0
    weak_direction_ratio: Annotated[float, Field(ge=0, le=1, description=(
        "refuse a closure whose match lies farther than ICP's correspondence gate from the prior along the "
        "match's weakest direction when the scan scores at least this share of the match's score at a pose on "
        "the way back toward the prior: a corridor's walls fit all along it, and the match pulled the chain "
        "along it where the scan fits no better (0: off)"))] = 0.0
    information_scale: Annotated[float, Field(gt=0, le=1, description=(
        "scale of a loop closure's ICP information"))] = 0.1
    dcs_phi: Annotated[float, Field(ge=0, description=(
        "dynamic covariance scaling (Agarwal et al., ICRA 2013): a closure whose chi2 exceeds this loses "
        "weight in the optimization (0: plain least squares)"))] = 11.34
    min_std_m: Annotated[float, Field(gt=0, description=(
        "floor of the chain's position std in the consistency test"))] = 0.005
    min_std_rad: Annotated[float, Field(gt=0, description="floor of the chain's heading std")] = 0.005
    max_range_m: Annotated[float | None, Field(ge=0, description=(
        "verify a loop closure with the points this close to the lidar (0: all)"))] = 2.0
    set_verify: Annotated[bool, Field(description=(
        "closures verified as a set too (mazebot.slam.closure_set, after Olson's single-cluster graph "
        "partitioning): a match that passed every test but fell a little short of min_fitness or max_rmse_m "
        "waits, and is accepted when enough closures nearby agree with it; a closure that disagrees with such a "
        "set is refused (off: each candidate judged alone)"))] = False
    set_fitness_ratio: Annotated[float, Field(gt=0, le=1, description=(
        "... waits with an inlier ratio of at least this share of min_fitness ..."))] = 0.75
    set_rmse_ratio: Annotated[float, Field(ge=1, description=(
        "... and a residual of at most this many times max_rmse_m"))] = 1.6
    set_window_keyframes: Annotated[int, Field(ge=1, le=1000, description=(
        "two closures are compared when their old ends and their new ends each lie within this many keyframes "
        "(a short chain between them is sure enough to tell)"))] = 10
    set_min_size: Annotated[int, Field(ge=2, le=100, description=(
        "a set is at least this many closures, each agreeing (chi2 under gate_chi2) with this many less one"))] = 3
    set_confidence: Annotated[float, Field(ge=1, description=(
        "... and stands out from any other set: the ratio of its affinity's two largest eigenvalues"))] = 2.0

    def __post_init__(self) -> None:
        if self.search_radius_m > self.max_search_radius_m:
            raise ValueError("search_radius_m must not exceed max_search_radius_m")


@dataclass(frozen=True)
class GridSection:
    """The occupancy grid's cells and log-odds (``mazebot.slam.grid``)."""

    __pydantic_config__ = _FORBID

    resolution_m: Annotated[float, Field(gt=0.001, le=1, description="occupancy grid cell size")] = 0.02
    l_hit: Annotated[float, Field(gt=0, description="log-odds added to a cell a beam ends in")] = 0.85
    l_miss: Annotated[float, Field(lt=0, description="log-odds added to a cell a beam crosses")] = -0.4
    l_min: Annotated[float, Field(lt=0, description="lowest log-odds of a cell")] = -5.0
    l_max: Annotated[float, Field(gt=0, description="highest log-odds of a cell")] = 5.0
    occupied_prob: Annotated[float, Field(ge=0.5, lt=1, description=(
        "a cell above this probability is a wall (0.75: two hits, not one stray)"))] = 0.75
    free_prob: Annotated[float, Field(gt=0, le=0.5, description="a cell below this probability is free")] = 0.25
    max_free_range_m: Annotated[float, Field(gt=0, description="no-return beams clear space this far")] = 4.0


@dataclass(frozen=True)
class LatticeSection:
    """Wall-lattice position priors (``mazebot.slam.wall_lattice``); the pitch is ``[planner] cell_size_m``."""

    __pydantic_config__ = _FORBID

    fit_tolerance_m: Annotated[float, Field(gt=0, description=(
        "a face this close to a lattice line fits it (boards offset, posts set out by hand)"))] = 0.02
    std_m: Annotated[float, Field(gt=0, description="trust in one keyframe's wall faces on the lattice")] = 0.005
    gate_m: Annotated[float, Field(gt=0, description=(
        "a face farther than this from its lattice line is not used for the prior"))] = 0.04
    normal_tolerance_rad: Annotated[float, Field(gt=0, description=(
        "a point's normal within this of a lattice axis belongs to its class"))] = 0.26
    inlier_m: Annotated[float, Field(gt=0, description="a point within this of its class's offset counts")] = 0.01
    min_points: Annotated[int, Field(ge=1, description="a class needs this many inlier points ...")] = 10
    min_extent_m: Annotated[float, Field(ge=0, description="... spread this far along the face")] = 0.05
    max_range_m: Annotated[float, Field(gt=0, description=(
        "points farther from the lidar are too noisy to say where a face is"))] = 1.2


@dataclass(frozen=True)
class EndpointSmoothing:
    """Hits moved along their beams onto their local wall line (``mazebot.slam.endpoint_smoothing``)."""

    __pydantic_config__ = _FORBID

    half_window: Annotated[int, Field(ge=1, description="neighbouring samples on each side, in scan order")] = 4
    radius_m: Annotated[float, Field(gt=0, description="neighbours farther than this from the hit do not count")] = 0.1
    min_neighbours: Annotated[int, Field(ge=3, description="points (the hit included) needed for a line")] = 5
    max_line_spread: Annotated[float, Field(gt=0, description=(
        "smallest / largest eigenvalue of a usable neighbourhood"))] = 0.1
    min_cos_incidence: Annotated[float, Field(ge=0, le=1, description=(
        "beams more grazing than this (0.3: ~73°) keep their range"))] = 0.3
    max_shift_m: Annotated[float, Field(ge=0, description="never move an endpoint farther than this")] = 0.03

    def __post_init__(self) -> None:
        if self.half_window < 1 or self.radius_m <= 0 or self.min_neighbours < 3:
            raise ValueError(
                f"need half_window >= 1, radius_m > 0 and min_neighbours >= 3, got {self.half_window}, "
                f"{self.radius_m}, {self.min_neighbours}"
            )


# The façade's own parameters: SlamParams (mazebot.slam.slam) is these sections' fields side by side.


@dataclass(frozen=True)
class FilterSection:
    """The pose filter (EKF) and its online calibrations (``mazebot.slam.ekf``)."""

    __pydantic_config__ = _FORBID

    filter_gate_chi2: Annotated[float, Field(gt=0, description=(
        "refuse a scan match this unlikely under the prediction (chi2, 3 dof)"))] = 16.27
    calibrate_heading: Annotated[bool, Field(description=(
        "learn the odometry's heading bias (unequal wheels, track width) from scan matches"))] = True
    calibration_memory_scans: Annotated[float, Field(ge=10, description=(
        "scans the heading calibration remembers (exponential forgetting)"))] = 1000.0
    calibration_limit: Annotated[float, Field(gt=0, le=1, description=(
        "the heading calibration's turn scale and its bias in rad per metre stay within plus or minus this"))] = 0.1
    calibration_false_alarm: Annotated[float, Field(ge=0, lt=1, description=(
        "apply each of the calibration's two estimates only as far as its Wald statistic against zero passes a "
        "test repeated after every matched scan, whose chance of passing anywhere in a run of white odometry "
        "noise is at most this (0.001 on laser logs; 0: apply what was learnt)"))] = 0.0
    calibrate_distance: Annotated[bool, Field(description=(
        "learn the odometry's distance scale (the wheels' mean diameter) from the scan matches that fix the "
        "direction of travel, with the heading calibration's memory and limit, applied as its posterior mean "
        "under a prior of a couple of percent on the wheels"))] = False
    calibrate_lever_arm: Annotated[bool, Field(description=(
        "learn where the tracked sensor sits relative to the point the odometry measures from the matched "
        "turns, with the heading calibration's memory and test (on for laser logs, whose laser may sit ahead "
        "of the wheels; the robot's lidar mount is configured in [lidar])"))] = False
    lever_arm_held: Annotated[bool, Field(description=(
        "a lever arm coordinate whose test has once passed stays applied as the fit's estimate, still refined by "
        "every matched turn, instead of being re-tested and withdrawn whenever its Wald statistic falls under "
        "the threshold (a laser's mount does not move; false: applied only while the test passes, shrunk by it)"
        ))] = False
    distance_step_noise_m: Annotated[float, Field(ge=0, le=0.1, description=(
        "the distance calibration's fit takes the wheels' prior in as this much noise on each matched step (0: "
        "the prior applied once, to the fit's result; a robot's steps between revolutions are a few centimetres, "
        "matched to about a millimetre, where 0.01 halves the scale a small maze's tour learns; laser logs: 0.01)"
        ))] = 0.0
    lidar_time_offset_s: Annotated[float, Field(ge=-0.05, le=0.1, description=(
        "how late the lidar's time stamps are against the odometry's (start value)"))] = 0.0
    estimate_time_offset: Annotated[bool, Field(description=(
        "learn that offset online from how scan matches disagree with odometry when turns start"))] = True
    initial_std: Annotated[tuple[float, float, float], Field(description=(
        "std of the start pose: m, m, rad"))] = (1e-3, 1e-3, 1e-3)


@dataclass(frozen=True)
class MatchingSection:
    """Which scan matches the filter uses, and how much it trusts them."""

    __pydantic_config__ = _FORBID

    min_match_fitness: Annotated[float, Field(ge=0, le=1, description=(
        "share of points matched for the filter to use a match ..."))] = 0.5
    max_match_rmse_m: Annotated[float, Field(gt=0, description="... and at most this point-to-line residual")] = 0.03
    retry_headings_rad: Annotated[tuple[float, ...], Field(description=(
        "when a match fails, retry ICP from the prediction turned by these"))] = (0.05, -0.05, 0.1, -0.1)
    match_information_scale: Annotated[float, Field(gt=0, le=1, description=(
        "scale of ICP's information matrix (ICP is optimistic about itself)"))] = 0.5
    match_doubt_ratio: Annotated[float, Field(ge=0, description=(
        "a converged match whose residual exceeds this many times the median of the recent matched scans' is in "
        "doubt: the correlative search looks over its whole window, and its match replaces ICP's if it has the "
        "smaller residual, at least the inlier ratio and at least the likelihood table's score (0: off; 4 with slam "
        "run --match-doubt)"))] = 0.0
    match_residual_ratio: Annotated[float, Field(ge=0, description=(
        "a match whose residual exceeds this many times the median of the recent matched scans' (the last "
        "match_doubt_scans) is not acceptable, as one beyond max_match_rmse_m (0: off)"))] = 0.0
    match_doubt_scans: Annotated[int, Field(ge=1, description=(
        "... the recent matched scans whose residuals that median is taken over"))] = 50
    match_heading_sigmas: Annotated[float, Field(ge=0, description=(
        "a sequential match whose heading differs from the prediction's by more than this many of the prediction's "
        "heading standard deviations is looked at again: the correlative search and the heading retries look for "
        "an acceptable match within it, which replaces it; where none is, it stands (0: off)"))] = 0.0
    basin_probe_m: Annotated[float, Field(ge=0, description=(
        "ICP restarted this far to either side of an accepted match along its weakest position direction, where "
        "the prediction is surer along it than this over the square root of 3; where ICP does not come back, the "
        "match's information along that direction is widened to the span it cannot tell apart, and the odometry "
        "decides there (mazebot.slam.basin_probe; 0: off)"))] = 0.0
    degenerate_retry_sigmas: Annotated[float, Field(ge=0, le=5, description=(
        "an acceptable sequential match that ICP left degenerate (a direction kept at the prediction) is matched "
        "again from the prediction moved along that direction by 1, 2, ... up to this many of the prediction's "
        "standard deviations along it, each way; a restart that fixes every direction with a residual markedly "
        "smaller (under 0.8 of it) within one more of them replaces it (0: off)"))] = 0.0
    edge_floor_std_m: Annotated[float, Field(ge=0, description=(
        "a sequential edge's match also carries the submap's own error (its keyframes' placement, which ICP's "
        "Hessian holds fixed): this std is added to the match's covariance on each position axis of the edge, "
        "before the odometry's information is added (mazebot.slam.submap_error; 0: ICP's alone)"))] = 0.0
    edge_floor_std_rad: Annotated[float, Field(ge=0, description=(
        "... and this one to its heading (0: ICP's alone)"))] = 0.0
    match_deskew_variance: Annotated[bool, Field(description=(
        "a moving revolution's match also carries the de-skew's error: the motion model's variance of the "
        "revolution's odometry increment is added to the match's covariance along the direction of travel, where "
        "only the few points facing it hold the match (mazebot.slam.deskew_variance; false: ICP's Hessian alone)"
    ))] = False
    # the correlative search (``[slam.search]``) also where the prediction itself is uncertain
    corr_uncertain_std_m: Annotated[float, Field(gt=0, description=(
        "search also when the prediction's position std exceeds this ..."))] = 0.05
    corr_uncertain_std_rad: Annotated[float, Field(gt=0, description="... or its heading std this")] = 0.035
    corr_window_sigmas: Annotated[float, Field(gt=0, description=(
        "that search's half-widths: this many prediction stds (at most the search's own window)"))] = 3.0
    failed_search_any_heading: Annotated[bool, Field(description=(
        "where ICP from the prediction failed and the correlative search over its window found no acceptable "
        "match either, search again over every heading (the window's position, no heading prior), and take a "
        "match that pins every direction: the odometry missed a turn (false: the odometry's step is taken)"))] = False
    failed_search_residual_ratio: Annotated[float, Field(gt=0, description=(
        "... and whose residual is at most this many times the median of the recent matched scans' (the last "
        "match_doubt_scans; a turned look-alike fits with several times the right matches' residual)"))] = 4.0
    failed_search_ambiguity_ratio: Annotated[float, Field(ge=0, le=1, description=(
        "... and where no heading failed_search_heading_separation_rad or more from the best scores this share of "
        "it on the likelihood table (a corridor seen half a turn round fits about as well; 0: no such test)"))] = 0.9
    failed_search_heading_separation_rad: Annotated[float, Field(gt=0, le=3.1416, description=(
        "... the headings that far from the best being another alignment (nearer, the best's own peak)"))] = 0.52
    corr_override_score: Annotated[float, Field(ge=0, le=1, description=(
        "its match replaces an acceptable ICP match scoring this much less on the likelihood table"))] = 0.05
    match_overlap_fitness: Annotated[bool, Field(description=(
        "a match under min_match_fitness that nothing else rescued still counts if its inlier ratio among the "
        "points the local submap could have seen (inside its keyframes' beams) reaches min_match_fitness: a scan "
        "through a doorway sees much the submap never saw (off: the ratio among all points)"))] = False
    match_min_overlap: Annotated[float, Field(ge=0, le=1, description=(
        "... and at least this share of the scan's points lies where the submap could have seen it"))] = 0.5
    match_overlap_margin_m: Annotated[float, Field(ge=0, description=(
        "... a point counts as seen by a submap beam that reached at least this close to it"))] = 0.2
    match_overlap_information_scale: Annotated[float, Field(gt=0, le=1, description=(
        "... and such a match's information is this share of ICP's: few inliers at a doorway, less sure than "
        "its Hessian says (against the Intel log's corrected poses ICP's information looked 64 times too sure; "
        "about 3 times on triangles of its scans, which need no reference)"))] = 1 / 64


@dataclass(frozen=True)
class KeyframeSection:
    """Keyframes and the local submap ICP matches against (``mazebot.slam.keyframes``)."""

    __pydantic_config__ = _FORBID

    keyframe_distance_m: Annotated[float, Field(gt=0, description=(
        "a scan becomes a keyframe after this much travel ..."))] = 0.10
    keyframe_angle_rad: Annotated[float, Field(gt=0, description=(
        "... or this much turn (11°: eight in a 90° turn)"))] = 0.2
    submap_keyframes: Annotated[int, Field(ge=1, le=500, description=(
        "recent keyframes in the local submap ICP matches"))] = 20
    submap_radius_m: Annotated[float, Field(ge=0, description=(
        "older keyframes this close to the robot join the local submap (0: only recent ones)"))] = 0.5
    submap_near_keyframes: Annotated[int, Field(ge=0, le=500, description=(
        "at most this many older keyframes, nearest first"))] = 20
    submap_voxel_m: Annotated[float, Field(gt=0.001, le=0.5, description="point spacing of the local submap")] = 0.01
    submap_update_m: Annotated[float, Field(ge=0, description=(
        "rebuild the local submap at a keyframe this far from the last rebuild ..."))] = 0.05
    submap_update_keyframes: Annotated[int, Field(ge=1, description=(
        "... or after this many keyframes (in-place turns see the same walls)"))] = 4


@dataclass(frozen=True)
class GraphSection:
    """The pose graph's optimization and the map rebuilds after it (``mazebot.slam.posegraph``)."""

    __pydantic_config__ = _FORBID

    optimize_iterations: Annotated[int, Field(ge=1, le=500, description=(
        "Levenberg-Marquardt iterations per optimization"))] = 30
    optimize_every_keyframes: Annotated[int, Field(ge=1, description=(
        "optimize the pose graph this often even without a loop closure (wall priors)"))] = 20
    rebuild_threshold_m: Annotated[float, Field(ge=0, description=(
        "rebuild the map when optimization moved a keyframe farther than this ..."))] = 0.01
    rebuild_threshold_rad: Annotated[float, Field(ge=0, description="... or turned one more than this")] = 0.005
    rebuild_after_exploration: Annotated[bool, Field(description=(
        "once the exploration is over (the robot returning home, or home), every optimization that moves a "
        "keyframe rebuilds the map, however little: the map the robot keeps follows the graph's last "
        "corrections instead of lagging them by up to the thresholds above (off: alljapan-015's coverage 0.9943 -> "
        "0.9989 with it, shi2's 0.9952 -> 0.9913)"))] = False


@dataclass(frozen=True)
class WallSection:
    """Right-angle wall priors and the map's anchor (``mazebot.slam.slam``)."""

    __pydantic_config__ = _FORBID

    wall_prior: Annotated[bool, Field(description=(
        "walls meet at right angles (a maze): each keyframe's walls give a weak heading prior"))] = True
    wall_prior_std_rad: Annotated[float, Field(gt=0, description="trust in one keyframe's wall direction")] = 0.01
    wall_min_strength: Annotated[float, Field(ge=0, le=1, description=(
        "use a keyframe only if its wall normals are this aligned to a right-angle grid ..."))] = 0.6
    wall_min_normals: Annotated[int, Field(ge=1, description="... with at least this many normals ...")] = 40
    wall_max_deviation_rad: Annotated[float, Field(gt=0, description=(
        "... and within this of the reference grid"))] = 0.087
    anchor_revolutions: Annotated[int, Field(ge=1, le=100, description=(
        "revolutions at rest keyframe 0, the map's anchor, measures its walls over"))] = 20
    anchor_still_m: Annotated[float, Field(ge=0, description=(
        "the robot stands still while the odometry moved less than this ..."))] = 0.002
    anchor_still_rad: Annotated[float, Field(ge=0, description=(
        "... and turned less than this since keyframe 0"))] = 0.002
    wall_anchor_std_rad: Annotated[float, Field(gt=0, description=(
        "trust in the anchor's wall direction (it fixes the wall grid of the whole map)"))] = 0.001
    wall_max_face_spread_rad: Annotated[float, Field(gt=0, description=(
        "faces keyframe 0 sees at rest that turn apart by more than this (RMS about their mean) are boards set "
        "by hand, each at its own angle (logged once; the anchor is judged from every keyframe's faces in "
        "any maze)"))] = 0.005
    anchor_links: Annotated[bool, Field(description=(
        "the anchor judged from every keyframe's faces links the keyframes by the pose graph's edges (the chain "
        "of matches and the closures, at their heading std), so the boards far from the start count too; off: "
        "by the faces they share alone (main's fit)"))] = False
    anchor_start_view: Annotated[bool, Field(description=(
        "where the faces keyframe 0 sees at rest lie on one grid (walls set square), the anchor judged from every "
        "keyframe's faces is joined by their own mean, at a std of their spread and of the boards' own turn (estimated "
        "from every keyframe's faces), counting the boards both read once, while that turn is within "
        "wall_max_face_spread_rad (boards turned by hand keep the judged anchor); "
        "off: the judged anchor alone"))] = True
    rest_face_steps: Annotated[bool, Field(description=(
        "each face keyframe 0 sees at rest is read across the steps between boards in line (one direction, "
        "an offset per board, cut where the step is large and significant: mazebot.slam.wall_faces) instead "
        "of one line through them: the start's faces read their boards' turns, not the steps between them; "
        "off: one line per face"))] = True
    line_tie_std_m: Annotated[float, Field(ge=0, le=0.1, description=(
        "two keyframes of different passes (min_keyframe_gap apart) that see faces of one straight wall in line "
        "(facing the same way, within 4 cm across, meeting along) are tied across the wall at this std: places "
        "that meet only across a wall are never in sight of each other for a loop closure, and the wall they both "
        "see is all they share (mazebot.slam.line_ties; needs no lattice; 0: off)"))] = 0.0


@dataclass(frozen=True)
class MapSection:
    """What a revolution paints into the occupancy grid."""

    __pydantic_config__ = _FORBID

    map_max_range_m: Annotated[float | None, Field(ge=0, description=(
        "farther hits clear space but mark no wall (range noise grows with range; 0: no limit)"))] = 1.2
    range_noise_rel: Annotated[float, Field(ge=0, lt=0.3, description=(
        "the lidar's range noise, std as a fraction of the range (A1: about 1 %)"))] = 0.01
    map_hit_depth_m: Annotated[float, Field(ge=0, le=0.05, description=(
        "a hit marks the cell this far behind the wall's face (under the wall thickness)"))] = 0.006


#: The sections whose fields :class:`mazebot.slam.slam.SlamParams` holds side by side.
FACADE_SECTIONS = ("filter", "matching", "keyframes", "graph", "walls", "map")


class SlamConfig(BaseModel):
    """SLAM: scan preparation, odometry filter, ICP, keyframes, loop closure, occupancy grid."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, defer_build=True)

    scan_queue_size: int = Field(
        8,
        ge=1,
        le=32,
        description="revolutions waiting for SLAM (8: 1.5 s of an A1's, inside the odometry history); beyond, "
        "the oldest is dropped",
    )
    odometry_history_s: float = Field(
        3.0, ge=0.5, le=60, description="odometry kept for de-skew and the filter (time-stamped poses)"
    )
    loop_closure_executor: Literal["process", "thread"] = Field(
        "process",
        description="run loop-closure jobs in a worker process (a core of its own) or a thread of the daemon",
    )
    loop_closure_nice: int = Field(
        19,
        ge=0,
        le=19,
        description="the loop-closure worker process's nice value: on a CPU shared with the daemon (one Pi core, "
        "a quota) its jobs take what the daemon leaves instead of half of it; 0: as the daemon",
    )
    loop_closure_pause_behind: int = Field(
        3,
        ge=0,
        le=32,
        description="revolutions waiting for SLAM at which the loop-closure worker process is paused until at "
        "most one waits: on a shared CPU budget (a quota, one Pi core) a long job on another core took what SLAM "
        "needed; 0: never paused",
    )
    correlative: bool = Field(
        True, description="search a window of poses ([slam.search]) before ICP where its match failed, "
        "or after re-localization"
    )
    loop_corr_window_m: float = Field(
        0.1, ge=0, le=10,
        description="loop closure: branch-and-bound window about the prior, x and y (0 and 0: ICP only) ...",
    )
    loop_corr_window_rad: float = Field(0.15, ge=0, le=3.2, description="... and heading")
    loop_corr_levels: int = Field(3, ge=0, le=8, description="branch-and-bound levels of the loop-closure search")
    map_smooth_endpoints: bool = Field(
        True, description="move each hit along its beam onto the line through its neighbours ([slam.smoothing])"
    )
    wall_lattice: bool = Field(
        True,
        description="walls lie on a square lattice of the planner's cell size: each keyframe's wall faces "
        "give a weak position prior ([slam.lattice]; needs walls.wall_prior)",
    )
    prepare: PrepareSection = Field(default_factory=PrepareSection)
    filter: FilterSection = Field(default_factory=FilterSection)
    motion: MotionSection = Field(default_factory=MotionSection)
    icp: IcpParams = Field(default_factory=IcpParams)
    normals: NormalParams = Field(default_factory=NormalParams)
    matching: MatchingSection = Field(default_factory=MatchingSection)
    search: CorrelativeParams = Field(default_factory=CorrelativeParams)
    keyframes: KeyframeSection = Field(default_factory=KeyframeSection)
    graph: GraphSection = Field(default_factory=GraphSection)
    walls: WallSection = Field(default_factory=WallSection)
    lattice: LatticeSection = Field(default_factory=LatticeSection)
    loop: LoopSection = Field(default_factory=LoopSection)
    grid: GridSection = Field(default_factory=GridSection)
    map: MapSection = Field(default_factory=MapSection)
    smoothing: EndpointSmoothing = Field(default_factory=EndpointSmoothing)


_T = TypeVar("_T")


def section_values(section: object) -> dict[str, Any]:
    """A section's fields by name (shallow: nested dataclasses stay objects)."""
    return {f.name: getattr(section, f.name) for f in fields(section)}  # type: ignore[arg-type]


def as_params(cls: type[_T], section: object, **derived: Any) -> _T:
    """The algorithm's parameter object ``cls`` from its config ``section``, plus the ``derived`` values.

    ``cls`` is the section's class or a subclass of it that adds behaviour or values taken
    from elsewhere (``derived``); the section's fields carry over by name.
    """
    return cls(**section_values(section), **derived)


def _moved(prefix: str, section: str, names: str) -> dict[str, str]:
    return {f"{prefix}{name}": f"{section}.{name}" for name in names.split()}


#: Every flat ``[slam]`` key of the old layout and where it lives now (``slam.`` left out).
FLAT_KEYS: dict[str, str] = {
    "max_range_m": "prepare.max_range_m",
    **_moved("", "prepare", "median_window impulse_abs_m impulse_rel"),
    "voxel_m": "prepare.voxel_size_m",
    "odom_var_xy_m2_per_m": "motion.xy_m2_per_m",
    "odom_var_theta_rad2_per_m": "motion.theta_rad2_per_m",
    "odom_var_theta_rad2_per_rad": "motion.theta_rad2_per_rad",
    "odom_calibration": "filter.calibrate_heading",
    "odom_calibration_memory_scans": "filter.calibration_memory_scans",
    **_moved("", "filter", "lidar_time_offset_s estimate_time_offset filter_gate_chi2"),
    "icp_max_iterations": "icp.max_iterations",
    "icp_converged_m": "icp.converged_translation_m",
    "icp_converged_rad": "icp.converged_rotation_rad",
    "icp_stop_m": "icp.stop_translation_m",
    "icp_stop_rad": "icp.stop_rotation_rad",
    **_moved("icp_", "icp", "max_correspondence_m min_correspondence_m degeneracy_ratio range_noise_ratio "
             "noise_floor_m"),
    "icp_min_fitness": "matching.min_match_fitness",
    "icp_max_rmse_m": "matching.max_match_rmse_m",
    "icp_retry_headings_rad": "matching.retry_headings_rad",
    "icp_information_scale": "matching.match_information_scale",
    "normal_neighbours": "normals.neighbours",
    "normal_radius_m": "normals.radius_m",
    **_moved("", "keyframes", "keyframe_distance_m keyframe_angle_rad submap_keyframes submap_radius_m "
             "submap_near_keyframes submap_voxel_m submap_update_m submap_update_keyframes"),
    **_moved("", "graph", "optimize_iterations optimize_every_keyframes rebuild_threshold_m rebuild_threshold_rad"),
    **_moved("", "walls", "wall_prior wall_prior_std_rad wall_min_strength anchor_revolutions wall_anchor_std_rad"),
    "wall_lattice_std_m": "lattice.std_m",
    "wall_lattice_gate_m": "lattice.gate_m",
    **_moved("loop_", "loop", "search_radius_m max_search_radius_m sigma_scale min_keyframe_gap submap_half_width "
             "attempt_every min_fitness max_rmse_m min_correspondences accept_degenerate gate_chi2 max_correction_m "
             "max_correction_rad ambiguity_shift_m ambiguity_fitness_ratio ambiguity_rmse_ratio max_range_m "
             "information_scale"),
    "corr_resolution_m": "search.resolution_m",
    "corr_sigma_m": "search.sigma_m",
    "corr_window_m": "search.window_xy_m",
    "corr_window_rad": "search.window_theta_rad",
    **_moved("corr_", "search", "levels max_range_m max_points min_score"),
    **_moved("grid_", "grid", "resolution_m l_hit l_miss l_min l_max occupied_prob free_prob max_free_range_m"),
    **_moved("", "map", "map_max_range_m range_noise_rel map_hit_depth_m"),
}
