"""Online calibration of the odometry's distance scale: ``dx_true = (1 + m)·dx``.

Wheels whose mean diameter is off by a percent make every odometry step a percent too
long or too short (Borenstein & Feng, *Measurement and correction of systematic odometry
errors in mobile robots*, IEEE T-RA 1996: the scale error ``E_s``). Where a scan match
fixes the pose along the direction of travel the error is corrected scan by scan; along a
corridor, where the match leaves that direction to the prediction, the map's steps take
the odometry's length, and a corridor of 30 m comes out 0.6 m long at 2 %.

The scale is learnt only from matches that fix the direction of travel: the step between
two such matches' poses along the robot's heading (``Δx_slam``), against the raw odometry's
``dx``, gives ``Δx_slam − dx = m·dx``. The matches' own poses, not the filter's, which leans
on the prediction and so on the scale already applied (a scale not yet applied would be
learnt short of itself). The estimate: instrumental variables with the matched step
``Δx_slam`` as the instrument for ``dx`` (whose own noise would lean least squares towards
zero), exponential forgetting, and the heteroscedasticity-robust variance ``v`` (White 1980,
HC1; :class:`mazebot.slam.forgotten_regression.ForgottenRegression`). What is applied is the
estimate's posterior mean under a prior ``m ~ N(0, τ²)`` on how far a robot's wheels are off
(:data:`WHEEL_SCALE_PRIOR_STD`): ``m·τ²/(τ² + v)``, nothing while one or two steps say little,
nearly all once the steps driven pin the scale down, with no test to pass first (Gelman et al.,
*Bayesian Data Analysis*, 3rd ed., 2013, §2.5: the normal mean's posterior under a normal
prior). White odometry noise gets its estimate's scatter, shrunk the same way.

The prior may also enter the fit, as ``σ²/τ²`` in its cross products for a noise ``σ`` on each step
(``step_noise_m``), which shrinks the estimate a second time by as much as the steps' ``Σ dx²`` is
short of it. That steadies a laser log's first observations (steps of 0.1-1 m under white noise of
centimetres, where the robust variance of a few steps says too little). A robot's steps between two
revolutions are a few centimetres, matched to about a millimetre (1.5 mm RMS about the true scale on
a 4×4 tour): there ``σ`` 1 cm halved what the tour learnt of a wheel scale 2 % off, the steps
themselves saying 1.99 %, so the robot applies the prior once (``σ`` 0).

Example::

    cal = DistanceCalibration()
    cal.observe(raw_increment, matched_increment)   # between two matches that fix the direction of travel
    cal.correct(increment)                         # what the filter predicts with
"""

from __future__ import annotations

import math

import numpy as np

from mazebot.slam.forgotten_regression import ForgottenRegression

#: a match fixes the direction of travel unless its weak direction's translation lies within 60° of it
#: (the cosine below): a corridor driven along, not one crossed
WEAK_ALONG_TRAVEL_COS = 0.5

#: the prior's standard deviation of the wheels' mean scale: a robot's wheels are a couple of percent off their
#: nominal diameter (tyres compressed under the robot's weight, worn, or a diameter taken from a datasheet), so an
#: estimate whose own standard deviation is a fifth of this is applied at 96 %, one as uncertain as this at half
WHEEL_SCALE_PRIOR_STD = 0.02


def fixes_travel(degenerate: bool, weak_direction: np.ndarray | None, heading_rad: float) -> bool:
    """Whether a match (ICP's ``degenerate`` and ``weak_direction`` in the map's axes) fixes the pose along the
    robot's heading ``heading_rad``."""
    if not degenerate or weak_direction is None:
        return not degenerate
    weak_xy = np.asarray(weak_direction, dtype=np.float64)[:2]
    norm = float(np.hypot(weak_xy[0], weak_xy[1]))
    if norm == 0.0:
        return True  # the weak direction is a pure turn
    along = abs(weak_xy[0] * math.cos(heading_rad) + weak_xy[1] * math.sin(heading_rad)) / norm
    return along < WEAK_ALONG_TRAVEL_COS


class DistanceCalibration:
    """The odometry's distance scale ``m``, learnt from scan matches, applied as far as they pin it down (module
    docstring)."""

    def __init__(
        self,
        memory_scans: float = 1000.0,
        prior_std: float = WHEEL_SCALE_PRIOR_STD,
        limit: float = 0.1,
        step_noise_m: float = 0.0,
    ) -> None:
        self.forgetting = 1.0 - 1.0 / max(float(memory_scans), 1.0)
        self.limit = float(limit)
        self.prior_var = float(prior_std) ** 2
        self.estimate = 0.0  # m applied: the learnt one's posterior mean
        self.learnt = 0.0  # m as estimated
        # the instrumental-variable fit, the prior's share in its cross products (none: applied once, docstring)
        self._fit = ForgottenRegression(
            self.forgetting, np.array([[(float(step_noise_m) / float(prior_std)) ** 2]]), limit=self.limit
        )
        self.observations = 0
        self.applied_observations = 0  # observations after which an estimate was applied

    def correct(self, increment: np.ndarray) -> np.ndarray:
        """The increment (dx, dy, dθ) with its translation scaled by ``1 + m``."""
        out = np.array(increment, dtype=np.float64).reshape(3)
        out[:2] *= 1.0 + self.estimate
        return out

    def correct_many(self, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corrected translations of many increments (the arrays themselves while nothing is applied: every
        revolution's de-skew passes through here, with the calibration off too)."""
        if self.estimate == 0.0:
            return dx, dy
        factor = 1.0 + self.estimate
        return dx * factor, dy * factor

    def observe(self, raw_increment: np.ndarray, true_increment: np.ndarray) -> None:
        """One step: the raw odometry increment and the increment between the matches that fixed the direction of
        travel at its two ends."""
        phi = float(raw_increment[0])
        z = float(true_increment[0])
        if phi == 0.0 or z == 0.0:
            return  # says nothing of the scale (and a first step with z·φ = 0 would leave the fit undefined)
        self.observations += 1
        self._fit.update(np.array([z]), np.array([phi]), z - phi)
        self.learnt = float(self._fit.estimate[0])
        var = self.variance()
        self.estimate = self.learnt * self.prior_var / (self.prior_var + var) if math.isfinite(var) else 0.0
        self.applied_observations += int(self.estimate != 0.0)

    def variance(self) -> float:
        """The learnt scale's robust variance (HC1's correction; infinite before there are two observations)."""
        return float(self._fit.variance()[0])

    def wald(self) -> float:
        """The learnt scale's Wald statistic against zero (0 before there are two observations)."""
        return float(self._fit.wald()[0])
