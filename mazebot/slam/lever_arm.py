"""Online calibration of where the tracked sensor sits relative to the point the odometry measures.

A laser log's odometry is the robot's (the wheels' axle centre); the SLAM tracks the laser.
Where the laser is mounted ``m = (m_x, m_y)`` ahead of or beside that centre (with the
same heading), the laser's step over an odometry step ``S`` is ``M⁻¹ ∘ S ∘ M``: the same
turn, and the translation ``S_t + (R(S_θ) − I) m``. A turn in place of 90° moves a laser
10 cm ahead of the axle by 14 cm that the odometry never saw, and the prediction of every
scan after a turn is off by it; a log's ``PARAM robot_frontlaser_offset`` may be missing
or wrong (on the corrected logs here the turns themselves put ACES's laser about 7 cm and
Intel's about 10 cm ahead of the odometry's centre, where their logs say 0).

The translation is linear in ``m``: after each pair of consecutively matched scans the
step the SLAM found ``L`` and the odometry's step ``S`` (heading and distance already
calibrated) give two equations ``L_t − S_t = (R(L_θ) − I) m``, rows
``(cos L_θ − 1, −sin L_θ)`` and ``(sin L_θ, cos L_θ − 1)``: straight driving says nothing
(both rows vanish), turns say it all. This is the sensor-position part of the joint
calibration of odometry and sensor of Censi, Franchi, Marchionni & Oriolo (IEEE T-RO 29(2),
2013), there solved once over a whole log, here over exponentially forgotten sums
(:class:`mazebot.slam.forgotten_regression.ForgottenRegression`) as the heading calibration
does, and applied only as far as each coordinate's Wald statistic passes the same
alpha-spending test (:func:`mazebot.slam.ekf.spent_chi2`): odometry made from a log's own
laser poses has no lever arm, and nothing is applied there.

**Held once shown** (``held``: ``[slam.filter] lever_arm_held``, off by default). A laser's
mount does not move. The alpha-spending test decides once that a coordinate is not zero (a
sequential test stops at its first rejection: Wald, *Sequential Analysis*, 1947; the spent level
bounds the chance that it ever passes on pure noise); held, that coordinate is from then on
applied as the fit's estimate, still refined by every observation, rather than re-tested after
each one. Re-tested, an estimate whose Wald statistic sits near the growing threshold is applied
on some stretches and withdrawn on others (ACES: applied, withdrawn from the 113th matched turn
to the 183rd, applied again), each switch moving the prediction of every turn by
``(R(θ) − I) m``, and the matches made meanwhile teach the fit a smaller mount (0.069 → 0.045 m).
Measured on the four corrected logs on their robots' own odometry: Intel 0.100 → 0.088 m RMS,
ACES 0.104 → 0.110 m (max 0.48 → 0.36 m), Freiburg 101 and Seattle the same within a millimetre:
not the default, since one log's RMS is worse.

Example::

    arm = LeverArmCalibration(memory_scans=1000.0, limit_m=0.5, false_alarm=0.001)
    arm.observe(odometry_step, matched_step)   # after each pair of matched scans
    arm.correct(odometry_step)                 # the tracked sensor's predicted step
"""

from __future__ import annotations

import math

import numpy as np

from mazebot.slam.ekf import significance_shrinkage, spent_chi2
from mazebot.slam.forgotten_regression import ForgottenRegression

#: A matched step turning less than this says too little about the lever arm to be worth a row
#: (its rows are at most ``2 sin(θ/2)`` ≈ 0.05 long: a few millimetres of odometry noise would swamp them).
MIN_TURN_RAD = 0.05

#: The prior's standard deviation on each coordinate (a laser is mounted within a robot's half-length).
PRIOR_STD_M = 0.5

#: The noise of one row's translation the prior is weighed against (a matched step's few centimetres).
ROW_NOISE_STD_M = 0.03


class LeverArmCalibration:
    """``m`` of ``L_t − S_t = (R(L_θ) − I) m``, learnt from matched steps and applied where significant."""

    def __init__(
        self, memory_scans: float = 1000.0, limit_m: float = 0.5, false_alarm: float = 0.001, held: bool = False
    ) -> None:
        forgetting = 1.0 - 1.0 / max(2.0 * float(memory_scans), 1.0)  # two rows an observation
        prior = (ROW_NOISE_STD_M / PRIOR_STD_M) ** 2 * np.eye(2)
        self._fit = ForgottenRegression(forgetting, prior, limit=float(limit_m))
        self.false_alarm = float(false_alarm)
        self.held = bool(held)  # a coordinate whose test has passed stays applied, whole
        self.observations = 0  # matched steps that turned enough to be used
        self.applied_observations = 0  # observations after which any coordinate was applied
        self.estimate = np.zeros(2)  # applied: the learnt m shrunk by the significance test (held: whole once shown)
        self.shown = np.zeros(2, dtype=bool)  # coordinates whose test has passed (held: from then on)

    @property
    def learnt(self) -> np.ndarray:
        return self._fit.estimate

    def correct(self, step: np.ndarray) -> np.ndarray:
        """The tracked sensor's step for the odometry's step ``(dx, dy, dθ)``."""
        out = np.array(step, dtype=np.float64).reshape(3)
        if not np.any(self.estimate):
            return out
        c, s = math.cos(out[2]), math.sin(out[2])
        mx, my = self.estimate
        out[0] += (c - 1.0) * mx - s * my
        out[1] += s * mx + (c - 1.0) * my
        return out

    def observe(self, odometry_step: np.ndarray, matched_step: np.ndarray) -> None:
        """One pair of consecutively matched scans: the odometry's step (calibrated, before the lever arm)
        and the step between the two matched poses."""
        turn = float(matched_step[2])
        if abs(turn) < MIN_TURN_RAD:
            return
        c, s = math.cos(turn), math.sin(turn)
        gap_x = float(matched_step[0]) - float(odometry_step[0])
        gap_y = float(matched_step[1]) - float(odometry_step[1])
        for row, gap in ((np.array([c - 1.0, -s]), gap_x), (np.array([s, c - 1.0]), gap_y)):
            self._fit.update(row, row, gap)
        self.observations += 1
        shrinkage = significance_shrinkage(self.wald(), self.threshold())
        self.shown |= shrinkage > 0.0
        self.estimate = self._fit.estimate * (np.where(self.shown, 1.0, shrinkage) if self.held else shrinkage)
        self.applied_observations += int(np.any(self.estimate != 0.0))

    def wald(self) -> np.ndarray:
        """Each coordinate's Wald statistic against zero (robust variance, HC1)."""
        return self._fit.wald()

    def threshold(self) -> float:
        """The Wald statistic the current observation's test asks for (0: no test, everything applied)."""
        return spent_chi2(self.false_alarm, self.observations) if self.false_alarm > 0 else 0.0
