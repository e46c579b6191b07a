"""A moving revolution's match carries the de-skew's error: its covariance along the direction of travel.

A revolution of the lidar takes about 0.18 s; a robot driving at 0.3 m/s moves 5 cm in it, and
every sample is moved into the robot frame at the revolution's end by the odometry between the
sample's instant and that end (:mod:`mazebot.slam.preprocess`). The odometry there is what the
encoders counted: a cheap robot's 20 counts a motor turn are 10 mm of a wheel's travel, so each
sample's de-skew is wrong by up to a count along the direction of travel, and all the samples of
a wall seen at one instant alike. ICP then fits the scan's points well (small residuals, the
distortion is smooth) and its Hessian (:mod:`mazebot.slam.icp`) counts the points as
independent; across a corridor hundreds of wall points hold the match, but along it only the
few that face the direction of travel (the walls ahead and behind, board ends, post gaps), all
seen at one or two instants of the revolution, so along the corridor the match is off by about
the de-skew's error and not by the points' noise over their count.

Measured on a hand-built japan2013ef with the cheap robot (every sequential match of its first
60 s, ICP run again from the same guess against the submap's keyframes placed at their true
poses): along the weakest position direction the match's true error has an RMS of 5.2 mm on
moving revolutions where the filter was told 2.2 mm (χ² mean 5.8 for one degree of freedom),
1.3 mm at rest, 1.6 mm turning in place. The missing variance, about 24 mm², is the motion
model's variance of one moving revolution's increment (``xy_m2_per_m`` times its 54 mm: 22 mm²).

So the match's covariance gets the de-skew's input uncertainty, as Censi's closed form propagates
the measurement's covariance into the estimate's ("An accurate closed-form estimate of ICP's
covariance", ICRA 2007: ``Cov(x̂) = (∂²J/∂x²)⁻¹ ∂²J/∂z∂x Σ_z (∂²J/∂z∂x)ᵀ (∂²J/∂x²)⁻¹``):
here the uncertain input ``z`` is the revolution's odometry increment, which displaces the
points that hold the match along the direction of travel one for one, so its variance
(the motion model's, :class:`mazebot.slam.ekf.MotionNoise`, the same the filter's prediction
takes) adds to the match's covariance along that direction, and nowhere else:

``Σ' = Σ + v w wᵀ``, ``w = (h, 0)`` with ``h`` the direction of travel in the map frame,
``v = xy_m2_per_m · d`` for a revolution that moved ``d``. By Sherman-Morrison on the information,
``Ω' = Ω − (Ωw)(Ωw)ᵀ v / (1 + v wᵀΩw)``, defined for a singular ``Ω`` too (a degenerate match).
Across a corridor the walls' points still hold the match to millimetres; along it the filter and
the pose graph's sequential edge weigh the match and the odometry about alike.
"""

from __future__ import annotations

import math

import numpy as np


def with_variance_along(information: np.ndarray, direction_xy: np.ndarray, variance_m2: float) -> np.ndarray:
    """``information`` (3×3, x y θ) whose covariance has ``variance_m2`` more along the unit position
    direction ``direction_xy`` (2,) (Sherman-Morrison; the module's docstring)."""
    omega = np.asarray(information, dtype=np.float64)
    if variance_m2 <= 0.0:
        return omega.copy()
    w = np.array([direction_xy[0], direction_xy[1], 0.0])
    m = omega @ w
    out = omega - np.outer(m, m) * (variance_m2 / (1.0 + variance_m2 * float(w @ m)))
    return 0.5 * (out + out.T)


def deskew_information(
    information: np.ndarray, increment: np.ndarray, heading_rad: float, xy_m2_per_m: float
) -> np.ndarray:
    """A match's ``information`` (3×3, map frame) with the de-skew's variance along the direction of travel.

    ``increment`` (3,): the revolution's odometry increment ``(dx, dy, dθ)`` in the robot frame at its
    start; ``heading_rad``: the robot's heading at the revolution's end in the map frame;
    ``xy_m2_per_m``: the motion model's position variance per metre driven. A revolution that did
    not move (a turn in place, at rest) leaves the information as it is.
    """
    dx, dy, dtheta = (float(v) for v in increment)
    moved_m = math.hypot(dx, dy)
    if moved_m <= 0.0:
        return np.asarray(information, dtype=np.float64).copy()
    start_heading = heading_rad - dtheta  # the increment's frame: the robot at the revolution's start
    c, s = math.cos(start_heading), math.sin(start_heading)
    travel = np.array([c * dx - s * dy, s * dx + c * dy]) / moved_m
    return with_variance_along(information, travel, xy_m2_per_m * moved_m)
