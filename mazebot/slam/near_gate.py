"""A sequential match just under the inlier-ratio gate, taken where it agrees with the odometry's prediction.

The sequential match is refused when its inlier ratio is under ``min_match_fitness``, and
the filter then takes the odometry's step: the match's information falls from all of it to
none at one value of the ratio. On the laser logs right matches sit on that edge (a turn in
place whose scan half looks where the submap never saw; the first scan after a spin), and a
scale of a percent on the odometry or a wider inlier count tips them either way: one
refused match there leaves the odometry's heading error of the spin in the chain, and the
run ends tenths of a metre apart.

Here a match refused only for its ratio, whose ratio is still at least ``near_gate_fitness``,
is taken if it passes the filter's validation gate against the prediction: the squared
Mahalanobis distance of the match from the prediction under the innovation covariance, the
prediction's covariance plus the match's, at most ``near_gate_chi2`` (χ² of 3 degrees of
freedom; Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, 2001, 5.7). The odometry then vouches for the alignment the few inliers can not.
Its information is scaled by where the ratio lies between the lower bound and the gate
(:func:`near_gate_share`): none at the lower bound, all of it at the gate, so that the
match's weight in the filter and the pose graph no longer jumps at the gate.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from mazebot.slam.ekf import PoseEkf
from mazebot.slam.icp import IcpResult


@dataclass(frozen=True)
class NearGateMatch(IcpResult):
    """A match under ``min_match_fitness`` taken because it agrees with the prediction (:func:`agreed_near_gate`).

    Its ``fitness`` is the match's own inlier ratio; ``information`` and ``graph_information`` are
    scaled by ``share``. SLAM's acceptance test lets it through for what it is, not for its ratio.
    """

    share: float = 1.0


def near_gate_share(fitness: float, lower: float, gate: float) -> float:
    """The share of a match's information kept at inlier ratio ``fitness``: 0 at ``lower``, 1 at ``gate``, linear.

    >>> near_gate_share(0.45, 0.4, 0.5)
    0.5
    """
    if gate <= lower:
        return 1.0 if fitness >= gate else 0.0
    return float(min(max((fitness - lower) / (gate - lower), 0.0), 1.0))


def agreed_near_gate(
    match: IcpResult, ekf: PoseEkf, lower: float, gate: float, chi2_gate: float, information_scale: float
) -> NearGateMatch | None:
    """``match`` with its information scaled by :func:`near_gate_share`, if it agrees with ``ekf``'s prediction.

    ``ekf`` holds the prediction (between the filter's predict and correct); the test uses the
    information the filter would fuse (the scaled information times ``information_scale``, the
    filter's ``match_information_scale``), in the directions the match observes
    (:meth:`PoseEkf.innovation_chi2`). None when the ratio is under ``lower`` or at the gate
    already, or the match lies beyond ``chi2_gate``.
    """
    if not lower <= match.fitness < gate:
        return None
    share = near_gate_share(match.fitness, lower, gate)
    if share <= 0.0:
        return None
    information = match.information * share
    if not np.any(information) or ekf.innovation_chi2(match.pose, information * information_scale) > chi2_gate:
        return None
    values = {f.name: getattr(match, f.name) for f in fields(match)}
    values["information"] = information
    if match.graph_information is not None:
        values["graph_information"] = match.graph_information * share
    values["share"] = share
    return NearGateMatch(**values)
