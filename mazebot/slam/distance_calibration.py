"""Online calibration of the odometry's distance scale: ``dx_true = (1 + m)·dx``.

Wheels whose mean diameter is off by a percent make every odometry step a percent too
long or too short (Borenstein & Feng, *Measurement and correction of systematic odometry
errors in mobile robots*, IEEE T-RA 1996: the scale error ``E_s``). Where a scan match
fixes the pose along the direction of travel the error is corrected scan by scan; along a
corridor, where the match leaves that direction to the prediction, the map's steps take
the odometry's length, and a corridor of 30 m comes out 0.6 m long at 2 %.

The scale is learnt only from matches that fix the direction of travel: the increment of
the corrected pose between two such scans, along the robot's heading (``Δx_slam``),
against the raw odometry's ``dx`` gives ``Δx_slam − dx = m·dx``. The estimate is the
heading calibration's gated one (:class:`mazebot.slam.ekf.HeadingCalibration`) with a
single parameter: instrumental variables with the matched step ``Δx_slam`` as the
instrument for ``dx`` (whose own noise would lean least squares towards zero), exponential
forgetting, a Wald test against zero with the heteroscedasticity-robust variance (White
1980, HC1) repeated after every observation at levels spent over the run (alpha
spending), and the estimate shrunk by ``max(0, 1 − c_n / W)``: white odometry noise gets
nothing applied.

Example::

    cal = DistanceCalibration(false_alarm=0.001)
    cal.observe(raw_increment, slam_increment)   # between two matches that fix the direction of travel
    cal.correct(increment)                         # what the filter predicts with
"""

from __future__ import annotations

import math

import numpy as np

from mazebot.slam.ekf import spent_chi2

#: a match fixes the direction of travel unless its weak direction's translation lies within 60° of it
#: (the cosine below): a corridor driven along, not one crossed
WEAK_ALONG_TRAVEL_COS = 0.5


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
    """The odometry's distance scale ``m``, learnt from scan matches, applied where they show it (module docstring)."""

    def __init__(
        self,
        memory_scans: float = 1000.0,
        prior_std: float = 0.05,
        noise_std_m: float = 0.01,
        limit: float = 0.1,
        false_alarm: float = 0.0,
    ) -> None:
        self.forgetting = 1.0 - 1.0 / max(float(memory_scans), 1.0)
        self.limit = float(limit)
        self.false_alarm = float(false_alarm)
        self.estimate = 0.0  # m applied: the learnt one, shrunk by the significance test
        self.learnt = 0.0  # m as estimated
        self._cross = (float(noise_std_m) / float(prior_std)) ** 2  # Σ λⁿ⁻ⁱ z φ with the prior's share
        self._zy = 0.0
        self._meat = 0.0  # Σ λ²⁽ⁿ⁻ⁱ⁾ r² z²: the sandwich's meat
        self._weight = 0.0  # the observations as the forgetting weighs them (HC1's n)
        self.observations = 0
        self.applied_observations = 0  # observations after which an estimate was applied

    def correct(self, increment: np.ndarray) -> np.ndarray:
        """The increment (dx, dy, dθ) with its translation scaled by ``1 + m``."""
        out = np.array(increment, dtype=np.float64).reshape(3)
        out[:2] *= 1.0 + self.estimate
        return out

    def correct_many(self, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corrected translations of many increments."""
        factor = 1.0 + self.estimate
        return dx * factor, dy * factor

    def observe(self, raw_increment: np.ndarray, true_increment: np.ndarray) -> None:
        """One step: the raw odometry increment and the increment SLAM found for the same interval, both between
        matches that fix the direction of travel."""
        phi = float(raw_increment[0])
        if phi == 0.0:
            return
        z = float(true_increment[0])
        y = z - phi
        self.observations += 1
        residual = y - phi * self.learnt
        lam = self.forgetting
        self._cross = lam * self._cross + z * phi
        self._zy = lam * self._zy + z * y
        self._meat = lam**2 * self._meat + residual**2 * z**2
        self._weight = lam * self._weight + 1.0
        self.learnt = float(np.clip(self._zy / self._cross, -self.limit, self.limit))
        w, c = self.wald(), self.threshold()
        self.estimate = self.learnt * (1.0 - c / w) if w > c else 0.0
        self.applied_observations += int(self.estimate != 0.0)

    def wald(self) -> float:
        """The learnt scale's Wald statistic against zero (robust variance with HC1's correction; 0 before there
        are two observations)."""
        if self._weight <= 1.0:
            return 0.0
        var = self._meat / self._cross**2 * self._weight / (self._weight - 1.0)
        return self.learnt**2 / var if var > 0 else 0.0

    def threshold(self) -> float:
        """The Wald statistic the current observation's test asks for (0: no test)."""
        return spent_chi2(self.false_alarm, self.observations) if self.false_alarm > 0 else 0.0
