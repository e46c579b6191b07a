"""The odometry's noise, learnt from the scan matches instead of being told.

The maze robot's motion model (``[slam.motion]``) was measured on its own wheels. A laser
log of a building comes with whatever odometry its robot had, and nobody says how good
it is: a motion model much tighter than the truth makes the filter trust wrong odometry,
shrinks the correlative search window and the loop closures' search radius and
correction bounds (all grow with the chain's uncertainty) and so rejects the closures
that would undo the drift. Too loose costs little: the scan matches carry the pose.

So the noise is measured from the data: every time two consecutive scans were both
matched, the scan matches' increment ``m`` (the relative pose of the two matched poses)
is compared with the odometry's increment ``u`` over the same interval, in the robot
frame at its start. Under the motion model (:class:`mazebot.slam.ekf.MotionNoise`) an
increment that travels ``d`` metres and turns ``|Δθ|`` has position variance ``a · d``
per axis and heading variance ``b · (d + |Δθ|)`` (one coefficient per metre and per
radian, as ``--odom-noise`` and Thrun, Burgard and Fox's odometry model state them), so

    r_xy = (m − u)_x,y / √d,      r_θ = (m − u)_θ / √(d + |Δθ|)

are zero-mean with standard deviations √a and √b. Each is estimated robustly from the
newest ``estimate_window`` pairs as ``median |r| / 0.6745`` (the median absolute value of
a normal variable is 0.6745 σ): a wrong match now and then, the failure a scan matcher
has, moves a median little where it would ruin a mean square. The median *absolute* value
(not the deviation about the median) keeps a steady bias in: a heading that drifts the
same way at every step (an uncalibrated track width, Borenstein and Feng's type B error,
IEEE Trans. Robotics and Automation 1996) is noise to a model without bias.

Until ``estimate_min_matches`` pairs the prior stands (the ``[slam.motion]`` values,
which a laser log sets conservatively wide); the estimate never goes below a floor (the
matches have errors of their own, and a perfect-looking stretch must not make the filter
refuse the next match).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import replace

import numpy as np

from mazebot.geometry import wrap_angle
from mazebot.slam.ekf import MotionNoise

#: median |x| of a zero-mean normal variable, in standard deviations
MEDIAN_ABS_NORMAL = 0.6745
#: increments shorter than this (metres plus radians) are normalized as if this long: a
#: robot standing still has an odometry error of zero over zero metres, which says nothing
MIN_NORMALIZING_LENGTH = 0.05


class OdometryNoiseEstimate:
    """The motion model learnt from (odometry increment, matched increment) pairs.

    Example::

        estimate = OdometryNoiseEstimate(MotionNoise(1e-2, 1e-2, 1e-2, estimate=True))
        estimate.observe(np.array([1.0, 0.0, 0.0]), np.array([1.03, -0.02, 0.01]))
        estimate.noise            # the prior until estimate_min_matches pairs, then learnt
    """

    def __init__(self, prior: MotionNoise) -> None:
        self.prior = prior
        self._xy: deque[float] = deque(maxlen=2 * prior.estimate_window)  # two axes per pair
        self._theta: deque[float] = deque(maxlen=prior.estimate_window)
        self.pairs = 0  # pairs observed in all
        self._noise = prior

    @property
    def noise(self) -> MotionNoise:
        """The motion model to use now (the prior until enough pairs)."""
        return self._noise

    def observe(self, odometry_increment: np.ndarray, matched_increment: np.ndarray) -> None:
        """One pair of increments ``(dx, dy, dθ)`` over the same interval, each in the robot frame at its start."""
        u = np.asarray(odometry_increment, dtype=np.float64).reshape(3)
        m = np.asarray(matched_increment, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(m))):
            return
        d = math.hypot(float(u[0]), float(u[1]))
        turn = abs(float(wrap_angle(u[2])))
        e = m - u
        e_theta = float(wrap_angle(e[2]))
        root_xy = math.sqrt(max(d, MIN_NORMALIZING_LENGTH))
        root_theta = math.sqrt(max(d + turn, MIN_NORMALIZING_LENGTH))
        self._xy.extend((abs(float(e[0])) / root_xy, abs(float(e[1])) / root_xy))
        self._theta.append(abs(e_theta) / root_theta)
        self.pairs += 1
        if self.pairs >= self.prior.estimate_min_matches:
            self._noise = self._learnt()

    def _learnt(self) -> MotionNoise:
        p = self.prior
        sigma_xy = float(np.median(np.fromiter(self._xy, dtype=np.float64))) / MEDIAN_ABS_NORMAL
        sigma_theta = float(np.median(np.fromiter(self._theta, dtype=np.float64))) / MEDIAN_ABS_NORMAL
        var_theta = max(p.estimate_floor_theta_rad2, sigma_theta**2)
        return replace(
            p,
            xy_m2_per_m=max(p.estimate_floor_xy_m2_per_m, sigma_xy**2),
            theta_rad2_per_m=var_theta,
            theta_rad2_per_rad=var_theta,
        )
