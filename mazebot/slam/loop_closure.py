"""Loop closure: find old keyframes the robot may be revisiting, and verify each strictly.

A maze is the worst place for loop closure: its corridors are identical, so a scan
taken in one cell can match another cell's walls perfectly. A false loop closure
bends the whole map, so every candidate must pass every test below or it is dropped
(strict acceptance: the approach of Olson, "Recognizing places using
spectrally clustered local matches", RAS 2009, and of Cartographer's constraint
builder: search only where the pose uncertainty allows, then demand a good and
unambiguous match).

**Candidates** (:func:`find_candidates`). For the newest keyframe ``n`` and every
keyframe ``i`` at least ``min_keyframe_gap`` keyframes older (younger ones are in the
local submap already; with ``min_gap_m``, fewer where the keyframes lie far apart:
:func:`keyframe_gap`), the uncertainty of the relative pose ``x_i⁻¹ x_n`` accumulated along the chain
of sequential edges ``i → n`` is propagated to first order:

    σ²_xy(i, n) = Σ_k σ²_xy,k + σ²_θ,k · |t_n − t_k|²,     σ²_θ(i, n) = Σ_k σ²_θ,k

(a heading error at keyframe ``k`` swings everything after it by its lever arm). ``i``
is a candidate when its distance to ``n`` is below ``search_radius_m + sigma_scale ·
σ_xy`` (capped at ``max_search_radius_m``). The nearest candidates are tried first;
with ``anchor_candidate``, keyframe 0 too whenever it is within the radius. The map's
frame is keyframe 0's: a heading error in the first sequential edges turns the whole map
about the start, and a closure to any later keyframe leaves those edges as they are
(the Seattle log: closures to keyframes 3–9 on the return, none to 0, the map turned by
0.7°); only a closure to keyframe 0 itself measures them.

**Verification** (:func:`verify`). ICP of the new keyframe's points against a submap of
the keyframes around ``i`` (``i ± submap_half_width``), in ``i``'s frame, started at the
prior relative pose; with ``search``, a match that fails there (no convergence, few
correspondences, a low inlier ratio, a high residual) is tried once more from the best
pose of a branch-and-bound correlative search over a window about the prior
(:func:`search_window`, :mod:`mazebot.slam.correlative`): a closure accepted without the
search is accepted with it too. Accepted only if

1. ICP converged with at least ``min_correspondences`` matches, an inlier ratio
   (``fitness``) of at least ``min_fitness`` and a point-to-line RMS of at most
   ``max_rmse_m`` (both scans see the same walls, closely);
2. the match constrains every direction (not ``degenerate``: a straight corridor
   cannot say where along it the robot is), unless ``accept_degenerate``: then the
   closure keeps only the directions it constrains (:class:`ObservedDirections`: its
   information's free eigenvalues zero, its measurement the prior's along them, the
   tests below judged in the constrained directions alone);
3. it is consistent with the odometry chain: the correction ``z ⊖ prior`` is within
   ``max_correction_m`` / ``max_correction_rad`` and its Mahalanobis distance under
   the chain covariance plus the ICP covariance is below ``gate_chi2``; with
   ``correction_sigmas`` k the limits grow to k standard deviations of the chain
   (:func:`correction_limits`), and the search window with them;
4. it is unambiguous: ICP restarted from the prior shifted by ``±ambiguity_shift_m``
   along both axes (one maze cell: where a repeated corridor would fit) never finds,
   farther than ``ambiguity_tolerance_m`` from the match, another alignment nearly as
   good: an inlier ratio of at least ``ambiguity_fitness_ratio`` of the match's and a
   residual at most ``ambiguity_rmse_ratio`` times its (relative, because at the edge
   of the lidar's range a shifted copy always loses a few points); and a closure the
   correlative search found is refused when its window holds another alignment that
   scores nearly as well (``search_ambiguity_ratio``, :meth:`WindowSearch.rival`);
5. with ``weak_direction_ratio``, it does not slide the chain along a ridge: a match that
   lies farther than ICP's correspondence gate from the prior along its own weakest
   direction is refused when the scan scores nearly as well on the way back toward the
   prior (:func:`weak_direction_rival`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import gammainc, gammaincinv

from mazebot.geometry import relative_pose, transform_points, wrap_angle
from mazebot.slam.correlative import (
    CorrelativeParams,
    CorrelativeResult,
    LikelihoodTable,
    correlative_match,
    runner_up,
    select_points,
)
from mazebot.slam.ekf import rotate_information
from mazebot.slam.icp import IcpParams, IcpResult, Target, match_scan
from mazebot.slam.overlap import ObservedArea
from mazebot.slam_config import LoopSection


@dataclass(frozen=True)
class LoopClosureParams(LoopSection):
    """Search and acceptance thresholds (the ``[slam.loop]`` section) and the correlative search about the prior.

    ``max_range_m`` None: verify with every point (``0`` in the config).
    """

    # branch and bound over this window about the prior before ICP (None: ICP from the prior alone)
    search: CorrelativeParams | None = None


@dataclass(frozen=True)
class Candidate:
    """Keyframe ``new`` may be seeing the place of keyframe ``old``.

    ``prior`` (3,) is the pose of ``new`` in the frame of ``old`` from the current
    estimates, ``prior_covariance`` (3×3) its chain uncertainty, ``distance_m`` their
    distance.
    """

    old: int
    new: int
    prior: np.ndarray
    prior_covariance: np.ndarray
    distance_m: float


@dataclass(frozen=True)
class Verdict:
    """The outcome of :func:`verify`: accepted or not, why (``reason``: a short category), and the edge.

    ``measurement`` (3,) is the pose of ``new`` in the frame of ``old``; ``information``
    (3×3) is in the frame of the pose graph's residual (``new``'s), ready for
    :meth:`mazebot.slam.posegraph.PoseGraph.add_edge`.
    """

    candidate: Candidate
    accepted: bool
    reason: str
    measurement: np.ndarray
    information: np.ndarray
    fitness: float = 0.0
    rmse_m: float = float("nan")
    chi2: float = float("nan")
    overlap_fitness: float = float("nan")  # the inlier ratio where the submap saw (when it was asked for)
    detail: str = ""  # the numbers behind ``reason``
    # refused by a quality threshold it missed by less than the set's margin, and every other test passed:
    # ``measurement`` and ``information`` are the match's, for :mod:`mazebot.slam.closure_set` to judge
    tentative: bool = False


def chain_uncertainty(
    positions_xy: np.ndarray, edge_var_xy: np.ndarray, edge_var_theta: np.ndarray, new: int
) -> tuple[np.ndarray, np.ndarray]:
    """``(σ²_xy, σ²_θ)`` (N,) of the pose of keyframe ``new`` relative to every keyframe ``i < new``.

    ``edge_var_xy[k]`` / ``edge_var_theta[k]`` are the position (per axis) and heading
    variances of the sequential edge ``k → k + 1``; ``positions_xy`` (N, 2) the
    keyframes' positions. Prefix sums make this O(N) for all ``i`` at once (the lever
    arm ``|t_n − t_k|²`` expands into sums of ``σ²_θ,k``, ``σ²_θ,k t_k`` and ``σ²_θ,k |t_k|²``).
    Entries ``i >= new`` are 0.
    """
    n = int(new)
    positions = np.asarray(positions_xy, dtype=np.float64)
    var_xy = np.asarray(edge_var_xy, dtype=np.float64)[:n]
    var_th = np.asarray(edge_var_theta, dtype=np.float64)[:n]
    tn = positions[n]
    # a heading error of edge k -> k+1 swings keyframes k+1 .. n about keyframe k+1
    pivot = positions[1 : n + 1]

    def suffix(values: np.ndarray) -> np.ndarray:  # sums over k = i .. n-1, for every i < n
        return np.cumsum(values[::-1], axis=0)[::-1]

    out_xy = np.zeros(len(positions))
    out_th = np.zeros(len(positions))
    if n == 0:
        return out_xy, out_th
    s_th = suffix(var_th)
    lever = s_th * float(tn @ tn) - 2.0 * (suffix(var_th[:, None] * pivot) @ tn)
    lever += suffix(var_th * np.einsum("ij,ij->i", pivot, pivot))
    out_xy[:n] = suffix(var_xy) + np.maximum(lever, 0.0)
    out_th[:n] = s_th
    return out_xy, out_th


def keyframe_gap(poses: np.ndarray, new: int, params: LoopSection) -> int:
    """How many keyframes older than ``new`` a candidate must be: ``min_keyframe_gap``, or fewer where it is
    ``min_gap_m`` of travel at the median spacing of keyframes ``0 .. new``.

    The gap keeps out the keyframes the robot has just passed, which the local submap holds already: a
    distance, which a count of keyframes stands for only at one spacing. A laser log at half its scan
    rate puts its scans twice as far apart, and a gap of 30 scans would ask for 60 m of travel where the
    whole log asked for 30. The median, not the mean: in-place turns make keyframes a few centimetres
    apart. Never more than the count: at a denser spacing the count is what spans the local submap.
    """
    gap = params.min_keyframe_gap
    if params.min_gap_m <= 0 or new < 1:
        return gap
    xy = np.asarray(poses, dtype=np.float64)[: new + 1, :2]
    spacing_m = float(np.median(np.hypot(*np.diff(xy, axis=0).T)))
    if spacing_m <= 0:
        return gap
    return max(2, min(gap, round(params.min_gap_m / spacing_m)))


def distinct_places(nearest: np.ndarray, others: np.ndarray, submap_half_width: int) -> np.ndarray:
    """``nearest`` then those of ``others`` (keyframe indices, nearest first) whose submap overlaps no earlier one's.

    A candidate is verified against the submap of keyframes ``i ± submap_half_width``; a second
    candidate whose submap overlaps the first's tests the same walls again. After a drift of
    metres the search radius holds several places, and the nearest in the drifted estimate is as
    likely a wrong one (the ACES log on wheels whose heading drifts 3° a metre: back at its start,
    the estimate 7–8 m off, every nearest candidate a corridor 7 m from the truth, the right
    keyframes 7–8 m away in the estimate): one candidate per place lets the strict tests of
    :func:`verify` find the right one among them (Olson, RAS 2009: every hypothesis within the
    uncertainty is matched, the tests reject the wrong ones). ``others`` are only the keyframes
    whose drift reaches beyond the search radius itself (:func:`find_candidates`): where the chain
    is sure to within the radius, the nearest place is the one.
    """
    chosen: list[int] = [int(i) for i in nearest]
    for i in others:
        if all(abs(int(i) - j) > 2 * submap_half_width for j in chosen):
            chosen.append(int(i))
    return np.asarray(chosen, dtype=np.intp)


def find_candidates(
    poses: np.ndarray,
    new: int,
    edge_var_xy: np.ndarray,
    edge_var_theta: np.ndarray,
    params: LoopClosureParams,
) -> list[Candidate]:
    """Old keyframes within the uncertainty-scaled search radius of keyframe ``new``, nearest first."""
    poses = np.asarray(poses, dtype=np.float64)
    last_old = new - keyframe_gap(poses, new, params)
    if last_old < 0:
        return []
    var_xy, var_th = chain_uncertainty(poses[:, :2], edge_var_xy, edge_var_theta, new)
    old = np.arange(last_old + 1)
    dist = np.hypot(poses[old, 0] - poses[new, 0], poses[old, 1] - poses[new, 1])
    radius = np.minimum(params.max_search_radius_m, params.search_radius_m + params.sigma_scale * np.sqrt(var_xy[old]))
    near = old[dist <= radius]
    order = near[np.argsort(dist[near], kind="stable")]
    if params.distinct_places and order.size:
        drifted = params.sigma_scale * np.sqrt(var_xy[order]) > params.search_radius_m
        order = distinct_places(order[:1], order[1:][drifted[1:]], params.submap_half_width)
    chosen = list(order[: params.max_candidates])
    if params.anchor_candidate and dist[0] <= params.max_search_radius_m and 0 not in chosen:
        chosen.append(0)  # the map's own frame, as far as any candidate may be: see LoopSection.anchor_candidate
    out = []
    for i in chosen:
        sxy = max(params.min_std_m**2, float(var_xy[i]))
        sth = max(params.min_std_rad**2, float(var_th[i]))
        out.append(
            Candidate(
                old=int(i),
                new=int(new),
                prior=relative_pose(poses[i], poses[new]),
                prior_covariance=np.diag([sxy, sxy, sth]),
                distance_m=float(dist[i]),
            )
        )
    return out


def verify(
    candidate: Candidate,
    target: Target | None,
    source_xy: np.ndarray,
    sensor_xy: np.ndarray,
    icp: IcpParams,
    params: LoopClosureParams,
    observed: ObservedArea | None = None,
) -> Verdict:
    """Run the acceptance tests of the module docstring; ``target`` is in ``candidate.old``'s frame.

    ``observed``: what the submap's keyframes saw (same frame), for ``overlap_fitness``.
    """
    if target is None or len(target) == 0:
        return _reject(candidate, "empty submap", "no points around the candidate")
    verdict = _verify_from(candidate.prior, candidate, target, source_xy, sensor_xy, icp, params, observed)
    if verdict.accepted or verdict.reason not in RESCUED or params.search is None:
        return verdict
    first = verdict
    # ICP from the prior found no good match: start it where the branch-and-bound search says,
    # over the window the correction may span
    limit_m, limit_rad = correction_limits(candidate, params)
    search = replace(
        params.search,
        window_xy_m=max(params.search.window_xy_m, limit_m),
        window_theta_rad=max(params.search.window_theta_rad, limit_rad),
    )
    window = search_window(candidate.prior, target, source_xy, sensor_xy, search)
    if window is None or np.allclose(window.found.pose, candidate.prior):
        return verdict
    verdict = _verify_from(window.found.pose, candidate, target, source_xy, sensor_xy, icp, params, observed)
    if (verdict.accepted or verdict.tentative) and params.search_ambiguity_ratio > 0:
        rival = window.rival(params.search_peak_separation_m, params.search_ambiguity_ratio)
        if rival:
            verdict = _reject(candidate, "ambiguous", rival, fitness=verdict.fitness, rmse_m=verdict.rmse_m)
    # a tentative closure from the prior stays one unless the search's start did better
    return first if first.tentative and not (verdict.accepted or verdict.tentative) else verdict


#: Rejections of a match that failed (not of a good match that was inconsistent or ambiguous):
#: only these are tried again from the correlative search's pose.
RESCUED = frozenset({"no convergence", "few correspondences", "low inlier ratio", "high residual"})


def _verify_from(
    start: np.ndarray,
    candidate: Candidate,
    target: Target,
    source_xy: np.ndarray,
    sensor_xy: np.ndarray,
    icp: IcpParams,
    params: LoopClosureParams,
    observed: ObservedArea | None = None,
) -> Verdict:
    """The tests of :func:`verify` on ICP started at ``start`` (always judged against ``candidate.prior``)."""
    result = match_scan(target, source_xy, start, icp, sensor_xy=sensor_xy)
    if params.accept_degenerate and result.converged and result.degenerate:
        result = _matched_at_prior(result, candidate.prior, target, source_xy, sensor_xy, icp, params)
    fit = dict(fitness=result.fitness, rmse_m=result.rmse_m)
    # 1. a good match
    if not result.converged:
        return _reject(candidate, "no convergence", "ICP did not converge", **fit)
    if result.correspondences < params.min_correspondences:
        return _reject(candidate, "few correspondences", f"{result.correspondences} correspondences", **fit)
    short: Verdict | None = None  # the quality threshold the match missed (it may still wait for a set)
    if result.fitness < params.min_fitness and not _fits_where_seen(result, source_xy, params, observed, fit):
        short = _reject(candidate, "low inlier ratio", f"inlier ratio {result.fitness:.2f}", **fit)
    elif not result.rmse_m <= params.max_rmse_m:
        short = _reject(candidate, "high residual", f"residual {result.rmse_m * 1e3:.1f} mm", **fit)
    if short is not None and not _near_miss(result, params):
        return short
    # 2. every direction observed, or (accept_degenerate) only the observed ones used
    if result.degenerate and not params.accept_degenerate:
        return short or _reject(candidate, "degenerate", "a direction is unconstrained", **fit)
    icp_information = result.edge_information * params.information_scale
    observed_dirs = ObservedDirections.of(icp_information) if result.degenerate else None
    if observed_dirs is not None and observed_dirs.dof == 0:
        return short or _reject(candidate, "degenerate", "no direction is constrained", **fit)
    # 3. consistent with the odometry chain
    correction = result.pose - candidate.prior
    correction[2] = float(wrap_angle(correction[2]))
    measurement = result.pose.copy()
    if observed_dirs is not None:  # along the free direction the closure says nothing: keep the prior there
        correction = observed_dirs.constrained_part(correction, candidate.prior_covariance)
        measurement = candidate.prior + correction
        measurement[2] = float(wrap_angle(measurement[2]))
    limit_m, limit_rad = correction_limits(candidate, params)
    if math.hypot(correction[0], correction[1]) > limit_m:
        moved = f"moves {math.hypot(correction[0], correction[1]):.3f} m"
        return short or _reject(candidate, "large correction", moved, **fit)
    if abs(correction[2]) > limit_rad:
        return short or _reject(candidate, "large correction", f"turns {correction[2]:.3f} rad", **fit)
    # judged with the information the closure would enter the pose graph with
    if observed_dirs is None:
        icp_cov = np.linalg.pinv(icp_information, hermitian=True)
        chi2 = float(correction @ np.linalg.solve(candidate.prior_covariance + icp_cov, correction))
        gate_chi2 = params.gate_chi2
    else:
        chi2 = observed_dirs.chi2(correction, candidate.prior_covariance)
        gate_chi2 = same_level_gate(params.gate_chi2, FULL_DOF, observed_dirs.dof)
    fit["chi2"] = chi2
    if chi2 > gate_chi2:
        return short or _reject(candidate, "inconsistent with odometry", f"chi2 {chi2:.1f}", **fit)
    # 4. unambiguous: no other alignment one corridor away fits as well
    if params.ambiguity_shift_m > 0:
        for shift in ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)):
            start = candidate.prior + np.array([shift[0], shift[1], 0.0]) * params.ambiguity_shift_m
            other = match_scan(target, source_xy, start, icp, sensor_xy=sensor_xy)
            apart = other.pose - result.pose
            apart[2] = float(wrap_angle(apart[2]))
            if observed_dirs is not None:  # a shift along the free direction lands on the match's own ridge
                apart = observed_dirs.constrained_part(apart, candidate.prior_covariance)
            elsewhere = math.hypot(apart[0], apart[1]) > params.ambiguity_tolerance_m
            if elsewhere and _as_good(other, result, params):
                return short or _reject(candidate, "ambiguous", "another alignment one shift away fits as well", **fit)
    # 5. not slid along a ridge (a degenerate closure keeps the prior along its free direction already)
    if params.weak_direction_ratio > 0 and observed_dirs is None:
        slid = weak_direction_rival(
            result, candidate.prior, target, source_xy, sensor_xy, icp.max_correspondence_m,
            params.weak_direction_ratio, params.search or CorrelativeParams(),
        )
        if slid:
            return short or _reject(candidate, "ambiguous along its weakest direction", slid, **fit)
    if observed_dirs is not None:
        icp_information = observed_dirs.information
    information = rotate_information(icp_information, float(measurement[2]))
    if short is not None:  # every other test passed: it waits for closures that agree with it
        return replace(short, measurement=measurement, information=information, chi2=chi2, tentative=True)
    return Verdict(
        candidate, True, "accepted", measurement, information, fit["fitness"], fit["rmse_m"],
        overlap_fitness=fit.get("overlap_fitness", float("nan")),
    )


#: The degrees of freedom of a pose in the plane: a closure that constrains every direction.
FULL_DOF = 3

#: An eigenvalue of a closure's information below this share of the largest is a direction ICP left out
#: (:func:`mazebot.slam.icp.match_scan` removes its weak directions exactly; this only absorbs round-off).
NULL_EIGENVALUE_RATIO = 1e-9


@dataclass(frozen=True)
class ObservedDirections:
    """The directions a degenerate closure's match constrains: its information split by eigen-decomposition.

    In a straight corridor a match fixes the lateral offset and the heading exactly and says
    nothing about the position along it. The principled use of such a measurement is to keep
    it in the directions it constrains and leave the others to the rest of the estimate (Zhang,
    Kaess & Singh, "On Degeneracy of Optimization-based State Estimation Problems", ICRA 2016:
    solution remapping), so the pose graph corrects a doubled corridor without being told where
    along it the robot is. The chain of sequential edges already fixes the free direction, so the
    pose graph stays solvable with the weak eigenvalue set to zero.

    ``basis`` (3, k) holds the information's eigenvectors with non-zero eigenvalues ``values``
    (k,), ``free`` (3, 3 − k) the others; all in (x, y, θ) of the closure's old keyframe.
    """

    basis: np.ndarray
    values: np.ndarray
    free: np.ndarray

    @staticmethod
    def of(information: np.ndarray) -> ObservedDirections:
        """Split ``information`` (3×3, symmetric positive semi-definite) into observed and free directions."""
        eigval, eigvec = np.linalg.eigh(0.5 * (information + information.T))
        kept = eigval > NULL_EIGENVALUE_RATIO * max(float(eigval[-1]), 1e-300)
        return ObservedDirections(eigvec[:, kept], eigval[kept], eigvec[:, ~kept])

    @property
    def dof(self) -> int:
        """How many directions the closure constrains."""
        return int(self.values.size)

    @property
    def information(self) -> np.ndarray:
        """The information with the free directions' eigenvalues exactly zero."""
        return (self.basis * self.values) @ self.basis.T

    def constrained_part(self, offset: np.ndarray, prior_covariance: np.ndarray) -> np.ndarray:
        """``offset`` (3,) with its free component removed: the most likely one under ``prior_covariance``.

        The closure leaves ``offset + N a`` (``N`` the free directions) equally likely for every
        ``a``; the one the chain's prior finds likeliest minimizes ``(offset + N a)ᵀ Σ⁻¹ (offset + N a)``.
        Its observed components (``basisᵀ offset``) are unchanged.
        """
        free = self.free
        if free.shape[1] == 0:
            return np.asarray(offset, dtype=np.float64).copy()
        weight = np.linalg.inv(prior_covariance)
        a = -np.linalg.solve(free.T @ weight @ free, free.T @ weight @ offset)
        return np.asarray(offset + free @ a, dtype=np.float64)

    def chi2(self, correction: np.ndarray, prior_covariance: np.ndarray) -> float:
        """The correction's squared Mahalanobis distance in the observed directions alone (``dof`` degrees).

        The closure measures ``y = Uᵀ x`` (``U`` the basis) with covariance ``Λ⁻¹``; the chain
        predicts it with ``Uᵀ Σ U``; the innovation ``Uᵀ correction``.
        """
        u = self.basis
        innovation = u.T @ correction
        covariance = u.T @ prior_covariance @ u + np.diag(1.0 / self.values)
        return float(innovation @ np.linalg.solve(covariance, innovation))


#: A degenerate match farther than this along its free direction from the prior is matched again there.
REMATCH_ALONG_M = 0.05


def _matched_at_prior(
    result: IcpResult,
    prior: np.ndarray,
    target: Target,
    source_xy: np.ndarray,
    sensor_xy: np.ndarray,
    icp: IcpParams,
    params: LoopClosureParams,
) -> IcpResult:
    """A degenerate match matched again where the prior puts the robot along the corridor (its free direction).

    ICP keeps its start along a direction it cannot observe, and a start the correlative search
    found lies anywhere on the corridor's ridge, metres from the prior. The match's offset across
    the corridor and its heading are only right for that place (a real corridor bends, its doors
    and ends pull a little): on the ACES log with the stand-in odometry such matches were 2–4.5°
    and 0.1–0.2 m off the corrected poses while the prior was 0.1–0.2 m off along the corridor.
    Solution remapping (Zhang, Kaess & Singh, ICRA 2016) takes the prior's value along the free
    direction; the observed ones are then measured there, from the match's heading and offset.
    """
    free = ObservedDirections.of(result.edge_information * params.information_scale).free
    if free.shape[1] != 1 or np.hypot(free[0, 0], free[1, 0]) < 0.5:  # not a corridor's free translation
        return result
    along_xy = free[:2, 0] / np.hypot(free[0, 0], free[1, 0])
    along_m = float(along_xy @ (result.pose[:2] - prior[:2]))
    if abs(along_m) <= REMATCH_ALONG_M:
        return result
    start = result.pose.copy()
    start[:2] -= along_m * along_xy
    return match_scan(target, source_xy, start, icp, sensor_xy=sensor_xy)


def same_level_gate(gate_chi2: float, dof: int, to_dof: int) -> float:
    """The chi² threshold on ``to_dof`` degrees of freedom with the false-alarm rate ``gate_chi2`` has on ``dof``."""
    if to_dof == dof:
        return gate_chi2
    level = float(gammainc(dof / 2.0, gate_chi2 / 2.0))
    return float(2.0 * gammaincinv(to_dof / 2.0, level))


def _near_miss(result: IcpResult, params: LoopClosureParams) -> bool:
    """A match short of ``min_fitness`` / ``max_rmse_m`` by less than the set's margins (``set_verify`` on)."""
    return (
        params.set_verify
        and result.fitness >= params.set_fitness_ratio * params.min_fitness
        and result.rmse_m <= params.set_rmse_ratio * params.max_rmse_m
    )


def _fits_where_seen(
    result: IcpResult,
    source_xy: np.ndarray,
    params: LoopClosureParams,
    observed: ObservedArea | None,
    fit: dict[str, float],
) -> bool:
    """The inlier ratio among the points the submap could have seen reaches ``min_fitness`` (``overlap_fitness``).

    Every inlier found a submap wall, so it lies where the submap saw; the ratio is the
    inliers over the source points inside the observed area (:mod:`mazebot.slam.overlap`),
    and at least ``min_overlap`` of the points must be there: a scan that shares a sliver
    with the submap says little however well the sliver fits. ``fit`` gets the ratio.
    """
    if not params.overlap_fitness or observed is None:
        return False
    points = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    if points.shape[0] == 0:
        return False
    seen = observed.contains(transform_points(result.pose, points), params.overlap_margin_m)
    share = float(seen.mean())
    ratio = min(1.0, result.correspondences / max(int(seen.sum()), 1))
    fit["overlap_fitness"] = ratio
    return share >= params.min_overlap and ratio >= params.min_fitness


def correction_limits(candidate: Candidate, params: LoopClosureParams) -> tuple[float, float]:
    """How far (m, rad) a closure may move ``candidate``'s prior: the fixed limits, or more with a drifted chain.

    With ``correction_sigmas`` k > 0 the limits are at least k standard deviations of the
    prior's chain uncertainty. A fixed cap suits a maze, where every closure comes a few
    keyframes after the last and a corridor one cell over fits as well as the right one;
    after a long loop in a building the drift grows with the distance driven, and a cap
    below it rejects exactly the closure that is needed (the Intel log, a 35 m corridor at
    the start: 1.8 m of drift, every closure back to the start rejected at a 1.5 m cap).
    The chi² test against the same covariance still applies, and the robust weights of the
    optimization (:mod:`mazebot.slam.robust_closures`) still judge the accepted ones.
    """
    if params.correction_sigmas <= 0:
        return params.max_correction_m, params.max_correction_rad
    cov = candidate.prior_covariance
    k = params.correction_sigmas
    return (
        max(params.max_correction_m, k * math.sqrt(max(float(cov[0, 0]), float(cov[1, 1])))),
        max(params.max_correction_rad, k * math.sqrt(float(cov[2, 2]))),
    )


@dataclass(frozen=True)
class WindowSearch:
    """A branch-and-bound search over a closure's window: its best pose, and what it searched."""

    found: CorrelativeResult
    table: LikelihoodTable
    source_xy: np.ndarray  # the points searched with (:func:`mazebot.slam.correlative.select_points`)
    sensor_xy: np.ndarray
    prior: np.ndarray
    search: CorrelativeParams

    def rival(self, separation_m: float, ratio: float) -> str:
        """Empty, or why the window is ambiguous: another peak farther than ``separation_m`` from the best,
        not on the best's own ridge, scores at least ``ratio`` of it (:func:`mazebot.slam.correlative.runner_up`).

        After metres of drift the window spans metres of corridor, and the best of two
        look-alikes is as likely the wrong one: on the ACES log with odometry whose heading
        drifts 7° a metre, a closure 7.5 m along a corridor from the right place was found by
        the search and passed every other test of :func:`verify`.
        """
        other = runner_up(
            self.table, self.source_xy, self.prior, self.search.window_xy_m, self.search.window_theta_rad,
            self.found, separation_m, ratio, self.sensor_xy,
        )
        if other.score <= 0:
            return ""
        apart = math.hypot(*(other.pose[:2] - self.found.pose[:2]))
        return f"another alignment {apart:.1f} m away scores {other.score / self.found.score:.2f} of the best"


def search_window(
    prior: np.ndarray,
    target: Target,
    source_xy: np.ndarray,
    sensor_xy: np.ndarray,
    search: CorrelativeParams | None,
) -> WindowSearch | None:
    """Where ICP starts: the best pose of a branch-and-bound search about the prior (None: the prior itself).

    A prior that drifted by more than ICP's basin (half a metre after a long loop in a
    building) makes ICP miss a closure that is there (Hess et al., ICRA 2016, section V:
    the closure search over a window). The search only picks the start; every test of
    :func:`verify` still judges the ICP result against the prior, so a window wider than
    ``max_correction_m`` cannot let a larger correction through. A search that scores
    below ``min_score`` leaves the prior.
    """
    prior = np.asarray(prior, dtype=np.float64)
    if search is None or (search.window_xy_m <= 0 and search.window_theta_rad <= 0):
        return None
    src = select_points(source_xy, sensor_xy, search)
    crop = (prior[:2], search.max_range_m + search.window_xy_m + 3.0 * search.sigma_m + 0.5)
    table = LikelihoodTable(target.points, search.resolution_m, search.sigma_m, search.levels, crop=crop)
    found = correlative_match(table, src, prior, search.window_xy_m, search.window_theta_rad, sensor_xy)
    if found.score < search.min_score:
        return None
    return WindowSearch(found, table, src, np.asarray(sensor_xy, dtype=np.float64), prior, search)


def weakest_translation(information: np.ndarray) -> np.ndarray:
    """The unit translation (2,) a match's information (3×3, x y θ) pins least, its heading left free.

    The information of the position alone, whatever the heading, is the Schur complement of the
    heading's block (the marginal's information); its smallest eigenvalue's vector is the direction
    along which the scan fits about as well a little way off: along a corridor, its axis.
    """
    info = 0.5 * (np.asarray(information, dtype=np.float64) + np.asarray(information, dtype=np.float64).T)
    position = info[:2, :2]
    if info[2, 2] > 0:
        position = position - np.outer(info[:2, 2], info[2, :2]) / info[2, 2]
    return np.asarray(np.linalg.eigh(position)[1][:, 0], dtype=np.float64)


def weak_direction_rival(
    result: IcpResult,
    prior: np.ndarray,
    target: Target,
    source_xy: np.ndarray,
    sensor_xy: np.ndarray,
    separation_m: float,
    ratio: float,
    search: CorrelativeParams,
) -> str:
    """Empty, or why ``result`` slid the chain along its weakest direction where the scan fits no better.

    Along a corridor the scan fits the walls all along it; what pins the match there is a door
    frame, the corridor's end, or a submap that stops short of where the scan still sees walls, so
    that the scan fits best where most of it lies over the submap. On the ACES log two closures
    came 1.7 m and 2.8 m along a corridor from the right place, each claiming 3 cm, the prior
    within 7 cm of the truth: the submap's keyframes had kept walls only to 4–6 m ahead, and the
    scan slid back along the corridor onto them. A match is only to be believed along such a
    direction where its score there stands out. The scan is scored (the correlative table of
    :mod:`mazebot.slam.correlative`, ``search``'s cells and smoothing and points) at the match's
    heading along the match's weakest direction (:func:`weakest_translation`), from
    ``separation_m`` (ICP's gate: a start nearer would converge back to the match) to where the
    prior lies along it; a pose scoring ``ratio`` of the match's own says the scan cannot tell the
    match from the way back to the chain's estimate, and the closure is refused (Olson,
    "Recognizing places using spectrally clustered local matches", RAS 2009: a match is accepted
    only where no other hypothesis within the prior's uncertainty explains the data about as well;
    the ratio as in Lowe, IJCV 2004, section 7.1). Only the way back toward the prior is asked: a
    match at the prior with a ridge running on beyond it moves the chain nowhere along the ridge.
    """
    along = weakest_translation(result.edge_information)
    pose = np.asarray(result.pose, dtype=np.float64)
    slide_m = float(along @ (np.asarray(prior, dtype=np.float64)[:2] - pose[:2]))
    if abs(slide_m) < separation_m:
        return ""
    points = select_points(source_xy, sensor_xy, search)
    sensor_m = math.hypot(*np.asarray(sensor_xy, dtype=np.float64).reshape(2))
    centre = pose[:2] + 0.5 * slide_m * along
    reach_m = 0.5 * abs(slide_m) + sensor_m + search.max_range_m + 3.0 * search.sigma_m + 0.5
    table = LikelihoodTable(target.points, search.resolution_m, search.sigma_m, levels=0, crop=(centre, reach_m))
    steps = np.arange(separation_m, abs(slide_m) + 1e-9, search.resolution_m) * math.copysign(1.0, slide_m)
    poses = np.column_stack((pose[0] + steps * along[0], pose[1] + steps * along[1], np.full(steps.size, pose[2])))
    own = float(table.score(pose[None, :], points)[0])
    scores = table.score(poses, points)
    best = int(np.argmax(scores))
    if own <= 0 or scores[best] < ratio * own:
        return ""
    back_m = abs(float(steps[best]))
    return f"{scores[best] / own:.2f} of its score {back_m:.1f} m back toward the prior along its weakest direction"


def _as_good(other: IcpResult, match: IcpResult, params: LoopClosureParams) -> bool:
    """Does ``other`` explain the scan about as well as ``match``? (Relative, so range limits do not hide it.)"""
    return (
        other.converged
        and other.correspondences >= params.min_correspondences
        and other.fitness >= params.ambiguity_fitness_ratio * match.fitness
        and other.rmse_m <= params.ambiguity_rmse_ratio * max(match.rmse_m, 1e-3)
    )


def _reject(candidate: Candidate, reason: str, detail: str, **fit: float) -> Verdict:
    nan = float("nan")
    return Verdict(
        candidate, False, reason, candidate.prior.copy(), np.zeros((3, 3)), fitness=fit.get("fitness", 0.0),
        rmse_m=fit.get("rmse_m", nan), chi2=fit.get("chi2", nan), overlap_fitness=fit.get("overlap_fitness", nan),
        detail=detail,
    )
