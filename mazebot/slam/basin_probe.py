"""How far a scan match's basin holds along its weakest direction: ICP restarted beside it.

ICP's information is its Hessian at the solution (:mod:`mazebot.slam.icp`), a statement about
the cost within a few millimetres of it. Along a corridor that a few door frames cross it is
wrong by orders of magnitude: at the match those frames' points have small residuals and full
weight, and they claim the position along the corridor to 2-3 mm; a few centimetres along it
their residuals are several times the robust kernel's scale, their weight vanishes, and the
cost is flat. ICP started there stays there. On the Intel log's in-place turn at the start the
second scan's match sits 0.12 m along the corridor from the corrected poses with a Hessian σ
of 2.5 mm along it, and ICP started 0.05 or 0.1 m to either side ends where it started; the
odometry, right within 22 mm, is outvoted 170 to 1 and the map hangs on that slide. Zhang's
degeneracy test (the Hessian's eigenvalue ratio) does not fire: at the solution the direction
is not weak, only a few centimetres away.

The probe asks the cost itself, at the scale that matters. Along the weakest direction ``u`` of
the match's position information (the corridor), ICP is started at the match ``± probe_m`` and
run as usual; where each run ends says how far the basin pulls back. The positions along ``u``
that ICP cannot tell from the match span ``[min(e₋, 0), max(e₊, 0)]`` (``e±`` the ends' offsets
along ``u``); a uniform distribution over an interval of half-width ``a`` has variance ``a²/3``.
Where that exceeds the Hessian's variance along ``u``, the match's covariance is widened along
``u`` alone (a rank-one update, below): every other direction keeps the Hessian's information.
Fused with the odometry (the filter's correction, the pose graph's sequential edge), the
odometry then decides along the corridor where ICP cannot, and ICP decides everything else.
This is the sampled-cost covariance of Olson ("Real-Time Correlative Scan Matching", ICRA 2009,
section IV: the match's covariance from the cost over the whole window, which a corridor
stretches into a long ellipse), taken along the one direction where the Hessian and the cost
disagree, with ICP's own robust cost instead of a likelihood table.

**The rank-one update.** With ``w = (u, 0)`` and ``Ω`` the information, ``q = wᵀΩw`` is the
information along ``u`` with the other directions held (the Hessian's curvature along ``u``).
Adding ``β`` of variance along ``w`` to the covariance (``Σ' = Σ + β w wᵀ``) is, by
Sherman-Morrison, ``Ω' = Ω − γ (Ωw)(Ωw)ᵀ`` with ``γ = β / (1 + β q)``, defined for a
singular ``Ω`` too; ``β = v − 1/q`` makes ``wᵀΩ'w = 1/v`` (the probe's variance ``v``), and the
covariance of any direction orthogonal to ``w`` is unchanged.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import replace

import numpy as np

from mazebot.slam.icp import IcpParams, IcpResult, Target, match_scan_steps


def weakest_position_direction(information: np.ndarray) -> tuple[np.ndarray, float]:
    """The unit position direction ``u`` (2,) the information holds least, and its information there (m⁻²).

    The eigenvector of the smallest eigenvalue of the position block ``Ω[:2, :2]`` (the
    information along a position direction with the heading held).
    """
    values, vectors = np.linalg.eigh(np.asarray(information, dtype=np.float64)[:2, :2])
    return vectors[:, 0].copy(), float(values[0])


def widened_along(information: np.ndarray, direction_xy: np.ndarray, variance_m2: float) -> np.ndarray:
    """``information`` (3×3) with its covariance widened along the position direction so that the
    information along it is ``1 / variance_m2`` (the module's rank-one update); unchanged where it holds less."""
    omega = np.asarray(information, dtype=np.float64)
    w = np.array([direction_xy[0], direction_xy[1], 0.0])
    q = float(w @ omega @ w)
    if variance_m2 <= 0.0 or q * variance_m2 <= 1.0:
        return omega.copy()
    m = omega @ w
    gamma = 1.0 / q - 1.0 / (q * q * variance_m2)
    out = omega - gamma * np.outer(m, m)
    return 0.5 * (out + out.T)


def basin_variance_m2(ends_m: tuple[float, float]) -> float:
    """The variance along the probed direction of the positions ICP cannot tell from the match.

    ``ends_m``: where ICP started below and above the match ended, as offsets along the
    direction (m). They span, with the match, an interval taken as uniform: ``a²/3``, ``a``
    its half-width.
    """
    low, high = min(ends_m[0], 0.0), max(ends_m[1], 0.0)
    half = 0.5 * (high - low)
    return half * half / 3.0


def probed_steps(
    target: Target,
    source_xy: np.ndarray,
    match: IcpResult,
    probe_m: float,
    params: IcpParams,
    prediction_covariance: np.ndarray,
    sensor_xy: np.ndarray | None = None,
) -> Generator[None, None, tuple[IcpResult, float]]:
    """``match`` with its information widened along its weakest position direction as far as
    ICP's basin fails to hold there, and the variance it was widened to (m²; 0: left as it was,
    the basin holding within the Hessian's variance, or not probed).

    ICP is restarted from ``match.pose ± probe_m`` along that direction (two runs; a stage
    yields between them). Probed only where the prediction (``prediction_covariance``, the
    filter's after the odometry step) is surer along that direction than the widest the probe
    can make the match, ``probe_m²/3``: the span ICP cannot tell apart is an upper bound on its
    looseness (along the Intel log's corridors ICP started 0.1 m off stays there, yet the
    residual there is two or three times the match's), and where the odometry is looser still,
    widening gives the odometry's error a say the match's residual does not grant it (the Intel
    log at ``0.1,0.1`` without this test: 241-260 matches a run widened, seed 2 from 0.136 to
    0.346 m). A degenerate match is left alone: its weak direction already carries no
    information. Both the filter's ``information`` and the pose graph's
    ``graph_information`` are widened alike.
    """
    if probe_m <= 0.0 or match.degenerate:
        return match, 0.0
    direction, held = weakest_position_direction(match.information)
    predicted = float(direction @ np.asarray(prediction_covariance, dtype=np.float64)[:2, :2] @ direction)
    if predicted >= probe_m * probe_m / 3.0:
        return match, 0.0
    ends = []
    for sign in (-1.0, 1.0):
        start = match.pose.copy()
        start[:2] += sign * probe_m * direction
        yield
        run = yield from match_scan_steps(target, source_xy, start, params, sensor_xy=sensor_xy)
        # a run that found too little to match there tells the place apart: the basin holds
        ends.append(float(direction @ (run.pose[:2] - match.pose[:2])) if run.correspondences else 0.0)
    variance = basin_variance_m2((ends[0], ends[1]))
    if variance * held <= 1.0:
        return match, 0.0
    graph = None if match.graph_information is None else widened_along(match.graph_information, direction, variance)
    widened = replace(
        match, information=widened_along(match.information, direction, variance), graph_information=graph
    )
    return widened, variance
