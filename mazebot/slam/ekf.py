"""Pose filtering: the odometry history and an EKF fusing odometry with scan-match poses.

**Odometry history.** The odometry task integrates the wheel encoders at 50 Hz or more
and appends every pose, time-stamped, to an :class:`OdometryHistory`. SLAM asks it for
the odometry pose at any time in the recent past: at each lidar sample's time (de-skew,
:func:`mazebot.slam.preprocess.prepare_scan`) and at the end of each revolution (the
filter's prediction). Headings are unwrapped before linear interpolation.

**EKF.** The state is the robot pose ``μ = (x, y, θ)`` in the map frame with its 3×3
covariance ``Σ``; the filter is the extended Kalman filter of Thrun,
Burgard & Fox (*Probabilistic Robotics*, Table 3.3), step numbers as there:

- *Prediction* (steps 2–3), the velocity motion model driven by the odometry increment
  ``u = (dx, dy, dθ)`` travelled since the last update, in the robot frame at its start
  (over one interval ``Δt`` this is ``v·Δt`` and ``ω·Δt`` integrated by the encoders)::

      μ̄ = μ ⊕ u
      Σ̄ = G Σ Gᵀ + V M Vᵀ,   G = ∂(μ ⊕ u)/∂μ,  V = ∂(μ ⊕ u)/∂u = R(θ) (block)

  The motion noise ``M`` grows with the distance ``d`` and the turn ``|dθ|`` of the
  increment (a random walk per metre and per radian, so it does not depend on the
  odometry rate): ``σ²_x = σ²_y = a_xy·d``, ``σ²_θ = a_θd·d + a_θθ·|dθ|``.
- *Correction* (steps 4–6) by a scan-match pose ``z`` (``C = I``) with its information
  matrix ``Ω`` (inverse covariance) from ICP. ICP returns ``Ω`` with zero eigenvalues
  along directions the scan does not constrain (a straight corridor), where ``Q = Ω⁻¹``
  does not exist, so the update uses the equivalent information form (Thrun et al.,
  Table 3.6; Kalman gain ``K = Σ_post Ω``)::

      Σ = (Σ̄⁻¹ + Ω)⁻¹,    μ = μ̄ + Σ Ω (z ⊖ μ̄)

  which leaves the prediction untouched along unobserved directions. A measurement
  whose innovation fails a χ² gate (Mahalanobis distance under ``Σ̄ + Ω⁺``) is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from mazebot.geometry import compose, relative_pose, wrap_angle
from mazebot.slam.forgotten_regression import ForgottenRegression
from mazebot.slam_config import MotionSection


class OdometryHistory:
    """Time-stamped odometry poses of the last ``horizon_s`` seconds, interpolated on demand.

    Example::

        history = OdometryHistory(horizon_s=3.0)
        history.append(0.00, 0.0, 0.0, 0.0)
        history.append(0.02, 0.005, 0.0, 0.01)
        history.at(np.array([0.01]))      # ((0.0025,), (0.0,), (0.005,))

    Times before the first or after the last entry are clamped to them (the robot is
    assumed to hold its pose beyond what was measured). Poses live in one numpy buffer
    (rows ``[_start, _end)``), copied into a new one when it fills, so a look-up is a single
    ``np.interp`` per coordinate over a view.
    """

    def __init__(self, horizon_s: float = 3.0, capacity: int = 512) -> None:
        if horizon_s <= 0:
            raise ValueError(f"horizon_s must be positive, got {horizon_s}")
        self.horizon_s = float(horizon_s)
        self._buf = np.zeros((max(int(capacity), 4), 4))  # columns: t, x, y, unwrapped theta
        self._start = 0
        self._end = 0
        #: (buffer, start, end) as of the last append, replaced in one assignment: what
        #: :meth:`at` reads, so a reader on another thread never sees a half-made update
        self._live: tuple[np.ndarray, int, int] = (self._buf, 0, 0)
        #: (time_s, time of the entry at or before it, pose) of the last :meth:`pose_at` that the
        #: history already covered past ``time_s``: later entries cannot change that pose
        self._settled: tuple[float, float, np.ndarray] | None = None

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, time_s: float, x_m: float, y_m: float, theta_rad: float) -> None:
        """Add the odometry pose at ``time_s`` (non-decreasing); drops entries older than the horizon."""
        if self._end > self._start:
            last_t, last_th = self._buf[self._end - 1, 0], self._buf[self._end - 1, 3]
            if time_s < last_t:
                raise ValueError(f"odometry time went backwards: {time_s} after {last_t}")
            theta_rad = last_th + math.remainder(theta_rad - last_th, math.tau)
        if self._end == self._buf.shape[0]:
            live = self._buf[self._start : self._end]
            # always a new buffer, never compacted in place: a reader on another thread (the
            # control loop) may still hold the old one with its rows
            rows = 2 * self._buf.shape[0] if live.shape[0] > self._buf.shape[0] // 2 else self._buf.shape[0]
            buf = np.zeros((rows, 4))
            buf[: live.shape[0]] = live
            self._buf, self._start, self._end = buf, 0, live.shape[0]
        self._buf[self._end] = (time_s, x_m, y_m, theta_rad)
        self._end += 1
        # keep one pose at or before the horizon, for interpolation
        t = self._buf[self._start : self._end, 0]
        drop = int(np.searchsorted(t, time_s - self.horizon_s, side="right")) - 1
        if drop > 0:
            self._start += min(drop, self._end - self._start - 2)
        self._live = (self._buf, self._start, self._end)

    @property
    def latest(self) -> tuple[float, np.ndarray] | None:
        """(time_s, pose (3,)) of the newest entry, or None."""
        buf, start, end = self._live
        if end == start:
            return None
        t, x, y, th = buf[end - 1]
        return float(t), np.array([x, y, math.remainder(th, math.tau)])

    @property
    def span_s(self) -> tuple[float, float] | None:
        """(oldest, newest) time held, or None."""
        buf, start, end = self._live
        if end == start:
            return None
        return float(buf[start, 0]), float(buf[end - 1, 0])

    def since(self, time_s: float) -> np.ndarray:
        """The entries newer than ``time_s``: rows (t, x, y, unwrapped θ), a copy (benchmarks log them)."""
        buf, start, end = self._live
        live = buf[start:end]
        return live[np.searchsorted(live[:, 0], time_s, side="right"):].copy()

    def at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Odometry poses (x, y, unwrapped θ) at the given times; the shape of ``preprocess.PoseAtTime``."""
        return self._at(self._live, times_s)  # one read: consistent while another thread appends

    @staticmethod
    def _at(
        live_rows: tuple[np.ndarray, int, int], times_s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        buf, start, end = live_rows
        if end == start:
            raise RuntimeError("no odometry recorded yet")
        live = buf[start:end]
        times = np.asarray(times_s, dtype=np.float64)
        t = live[:, 0]
        return np.interp(times, t, live[:, 1]), np.interp(times, t, live[:, 2]), np.interp(times, t, live[:, 3])

    def pose_at(self, time_s: float) -> np.ndarray:
        """The odometry pose (3,) at one time, heading wrapped to [-π, π).

        The pose at the latest scan's end is asked at the odometry rate (the control
        process's mirror) and by every planner tick: once an entry newer than ``time_s``
        is in, the two entries around it never change (entries are only appended after
        it, and dropped from the far end), so the pose is kept and handed out again, as
        long as the entry before ``time_s`` is still held.
        """
        settled = self._settled
        live_rows = self._live
        buf, start, end = live_rows
        if settled is not None and settled[0] == time_s and end > start and buf[start, 0] <= settled[1]:
            return settled[2].copy()
        x, y, th = self._at(live_rows, np.array([time_s]))
        pose = np.array([float(x[0]), float(y[0]), float(wrap_angle(th[0]))])
        if end > start and buf[start, 0] <= time_s < buf[end - 1, 0]:
            t = buf[start:end, 0]
            before = float(t[int(np.searchsorted(t, time_s, side="right")) - 1])
            self._settled = (float(time_s), before, pose.copy())
        return pose


@dataclass(frozen=True)
class MotionNoise(MotionSection):
    """Odometry noise of the motion model (the ``[slam.motion]`` section), with its covariance."""

    def covariance(self, increment: np.ndarray) -> np.ndarray:
        """``M`` (3×3) of an increment (dx, dy, dθ), in the robot frame at its start."""
        d = math.hypot(float(increment[0]), float(increment[1]))
        turn = abs(float(increment[2]))
        var_xy = self.xy_m2_per_m * d
        return np.diag([var_xy, var_xy, self.theta_rad2_per_m * d + self.theta_rad2_per_rad * turn])


class PoseEkf:
    """Extended Kalman filter of the robot pose in the map frame (see the module docstring).

    Example::

        ekf = PoseEkf(initial_pose=np.zeros(3), initial_std=(0.001, 0.001, 0.001))
        ekf.predict(np.array([0.10, 0.0, 0.05]))             # odometry since the last update
        ekf.correct(icp.pose, icp.information)               # a scan-match pose
        ekf.mean, ekf.covariance
    """

    def __init__(
        self,
        initial_pose: np.ndarray | None = None,
        initial_std: tuple[float, float, float] = (1e-3, 1e-3, 1e-3),
        noise: MotionNoise | None = None,
        gate_chi2: float = 16.27,
    ) -> None:
        self.mean = np.zeros(3) if initial_pose is None else np.array(initial_pose, dtype=np.float64).reshape(3)
        self.covariance = np.diag(np.square(np.asarray(initial_std, dtype=np.float64)))
        self.noise = noise or MotionNoise()
        self.gate_chi2 = float(gate_chi2)  # χ²(3) 99.9 % by default

    def predict(self, increment: np.ndarray, noise_covariance: np.ndarray | None = None) -> None:
        """Steps 2–3: move by the odometry ``increment`` (dx_m, dy_m, dθ_rad) in the robot frame."""
        u = np.asarray(increment, dtype=np.float64).reshape(3)
        th = float(self.mean[2])
        c, s = math.cos(th), math.sin(th)
        g = np.array([[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0.0, 0.0, 1.0]])
        v = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        m = self.noise.covariance(u) if noise_covariance is None else np.asarray(noise_covariance, dtype=np.float64)
        self.mean = compose(self.mean, u)
        self.covariance = g @ self.covariance @ g.T + v @ m @ v.T

    def innovation_chi2(self, z: np.ndarray, information: np.ndarray) -> float:
        """Squared Mahalanobis distance of ``z`` from the prediction under ``Σ̄ + Ω⁺``, observed directions only.

        Directions where ``Ω`` is zero (a corridor's axis) carry no measurement, so the
        innovation is projected onto ``Ω``'s range first.
        """
        omega = np.asarray(information, dtype=np.float64)
        eigval, eigvec = np.linalg.eigh(0.5 * (omega + omega.T))
        strong = eigval > 1e-9 * max(float(eigval[-1]), 1e-300)
        observed = eigvec[:, strong]
        nu = observed.T @ self._innovation(z)
        # in Ω's eigenbasis its pseudo-inverse is diagonal: S = Vᵀ Σ̄ V + diag(1/λ)
        s = observed.T @ self.covariance @ observed + np.diag(1.0 / eigval[strong])
        return float(nu @ np.linalg.solve(s, nu))

    def correct(self, z: np.ndarray, information: np.ndarray, gate: bool = True) -> bool:
        """Steps 4–6 in information form; returns False (state unchanged) if the χ² gate refuses ``z``."""
        omega = np.asarray(information, dtype=np.float64).reshape(3, 3)
        if not np.any(omega):
            return False
        if gate and self.innovation_chi2(z, omega) > self.gate_chi2:
            return False
        posterior_info = np.linalg.inv(self.covariance) + omega
        cov = np.linalg.inv(posterior_info)
        cov = 0.5 * (cov + cov.T)
        self.mean = self.mean + cov @ omega @ self._innovation(z)
        self.mean[2] = float(wrap_angle(self.mean[2]))
        self.covariance = cov
        return True

    def reset(self, pose: np.ndarray, covariance: np.ndarray | None = None) -> None:
        """Jump to ``pose`` (e.g. after a loop closure moved the map under the robot)."""
        self.mean = np.array(pose, dtype=np.float64).reshape(3)
        if covariance is not None:
            self.covariance = np.array(covariance, dtype=np.float64).reshape(3, 3)

    def _innovation(self, z: np.ndarray) -> np.ndarray:
        nu = np.asarray(z, dtype=np.float64).reshape(3) - self.mean
        nu[2] = float(wrap_angle(nu[2]))
        return nu


class HeadingCalibration:
    """Online calibration of the odometry's heading: ``dθ_true = (1 + s)·dθ + k·dx``.

    Unequal wheel diameters make the encoders see a turn where the robot drives straight
    (``k``, rad per metre; 0.4 % on a 15 cm track is 1.5°/m) and a wrong track width
    scales every turn (``s``). Both bend the de-skew of every scan the same way, and a
    bias of a few hundredths of a degree per scan chains into degrees of drift through
    the keyframes. After each scan the increments of the corrected pose (dominated by
    ICP) and of the raw odometry give one equation ``Δθ_slam − dθ = s·dθ + k·dx``;
    recursive least squares with exponential forgetting (Ljung & Söderström, *Theory and
    Practice of Recursive Identification*, 1983; the self-calibration of Roy & Thrun,
    ICRA 1999) estimates ``(s, k)``, clamped to ``±limit``.

    With ``false_alarm`` α > 0 an estimate is applied only where the matches show it.
    The odometry's own heading noise is in the regressor ``dθ`` as well as in ``y``, so
    least squares on it leans ``s`` towards ``−var(noise) / var(dθ)`` (errors in
    variables: a bias of the estimator, not of the wheels, and as significant as any
    once enough turns are seen). The gated estimate therefore takes the matched turn
    ``Δθ_slam`` as the instrument for ``dθ`` (instrumental variables, Söderström & Stoica,
    *Instrumental Variable Methods for System Identification*, 1983): ``θ̂ = (Σ λⁿ⁻ⁱ zφᵀ)⁻¹
    Σ λⁿ⁻ⁱ z y`` with ``z = (Δθ_slam, dx)``, ``φ = (dθ, dx)``, the same forgetting
    (:class:`mazebot.slam.forgotten_regression.ForgottenRegression`, with its variance). Each of
    ``s`` and ``k`` is tested against zero by its Wald statistic ``W = θ̂² / var``, its
    variance the heteroscedasticity-robust ("sandwich") one (White, Econometrica 1980: the
    residuals' own spread, whatever the odometry's noise; a turn of a radian is noisier than
    a straight metre) with its small-sample correction ``n / (n − 2)`` (HC1, MacKinnon &
    White, J. Econometrics 1985; ``n`` the observations as the forgetting weighs them), and
    shrunk by ``max(0, 1 − c_n / W)``: nothing while the evidence is within what white noise
    gives, all of it once the bias stands far out, and no jump between.

    The test is repeated after every matched scan, hundreds of times a run, so its level
    must account for the repetition: at a fixed 0.1 % a run of white noise crosses it now
    and then (the Intel log with white odometry noise: on the 2nd, 43rd or 102nd scan,
    depending on the seed), and what is applied for a while turns the map. The ``n``-th
    test is at level ``α / (n (n + 1))``, whose sum over every ``n`` is ``α``: by the union
    bound the estimate is applied anywhere in a run of white noise with probability at
    most ``α`` (alpha spending, the sequential-testing practice of spreading a test's level
    over its looks; Lan & DeMets, Biometrika 1983). The threshold grows slowly: χ² of one
    degree of freedom 12.1 at the first test, 28.4 at the 100th, 37.0 at the 900th for
    α = 0.001, while a real bias's ``W`` grows with the scans (hundreds to thousands on the
    logs with odometry four times the systematic model's defaults). Without the test,
    odometry whose errors are white has its noise learnt as a bias, and the map turns about
    its start with it.

    Example::

        cal = HeadingCalibration()
        cal.observe(raw_increment, slam_increment)    # after each matched scan
        cal.correct(raw_increment)                      # what the filter and de-skew use
    """

    def __init__(
        self,
        memory_scans: float = 1000.0,
        prior_std: tuple[float, float] = (0.05, 0.05),
        noise_std_rad: float = 0.003,
        limit: float = 0.1,
        false_alarm: float = 0.0,
    ) -> None:
        self.forgetting = 1.0 - 1.0 / max(float(memory_scans), 1.0)
        self.estimate = np.zeros(2)  # (s, k) applied: the learnt ones, shrunk by the significance test
        self.learnt = np.zeros(2)  # (s, k) as estimated
        self._p = np.diag(np.square(np.asarray(prior_std, dtype=np.float64)))
        self._max_var = float(np.max(np.diag(self._p)))
        self._noise_var = float(noise_std_rad) ** 2
        self.limit = float(limit)
        self.false_alarm = float(false_alarm)
        self.applied_observations = 0  # observations after which an estimate was applied
        # the gated estimate's instrumental-variable fit, the prior's share in its cross products
        self._fit = ForgottenRegression(self.forgetting, self._noise_var * np.linalg.inv(self._p), limit=self.limit)
        self.observations = 0

    @property
    def scale(self) -> float:
        return float(self.estimate[0])

    @property
    def bias_rad_per_m(self) -> float:
        return float(self.estimate[1])

    def correct(self, increment: np.ndarray) -> np.ndarray:
        """The increment (dx, dy, dθ) with its heading change corrected."""
        out = np.array(increment, dtype=np.float64).reshape(3)
        out[2] = (1.0 + self.estimate[0]) * out[2] + self.estimate[1] * out[0]
        return out

    def correct_many(self, dx: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
        """Corrected heading changes of many increments (forward travel ``dx``, raw ``dtheta``)."""
        return (1.0 + self.estimate[0]) * dtheta + self.estimate[1] * dx

    def observe(self, raw_increment: np.ndarray, true_increment: np.ndarray) -> None:
        """One RLS step: the raw odometry increment and the increment SLAM found for the same interval."""
        phi = np.array([float(raw_increment[2]), float(raw_increment[0])])
        if not np.any(phi):
            return
        y = float(wrap_angle(float(true_increment[2]) - float(raw_increment[2])))
        self.observations += 1
        if self.false_alarm > 0:
            self._observe_gated(phi, y, float(true_increment[2]))
            return
        p = self._p / self.forgetting
        gain = p @ phi / (self._noise_var + phi @ p @ phi)
        self.learnt = np.clip(self.learnt + gain * (y - phi @ self.learnt), -self.limit, self.limit)
        p = p - np.outer(gain, phi @ p)
        # forgetting must not wind up the directions nothing excites (driving straight says
        # nothing about s): clamp the covariance's eigenvalues to the prior's largest
        w, v = np.linalg.eigh(0.5 * (p + p.T))
        self._p = (v * np.minimum(w, self._max_var)) @ v.T
        self.estimate = self.learnt.copy()

    def _observe_gated(self, phi: np.ndarray, y: float, matched_turn_rad: float) -> None:
        """The instrumental-variable step and the significance test (the class docstring)."""
        self._fit.update(np.array([matched_turn_rad, float(phi[1])]), phi, y)
        self.learnt = self._fit.estimate
        self.estimate = self.learnt * significance_shrinkage(self.wald(), self.threshold())
        self.applied_observations += int(np.any(self.estimate != 0))

    def wald(self) -> np.ndarray:
        """Each learnt parameter's Wald statistic against zero (``θ̂² / var``, robust variance with HC1's
        correction; 0 before there are more observations than parameters)."""
        return self._fit.wald()

    def threshold(self) -> float:
        """The Wald statistic the current observation's test asks for: χ²₁ at level ``α / (n (n + 1))`` (0: no test)."""
        if self.false_alarm <= 0:
            return 0.0
        return spent_chi2(self.false_alarm, self.observations)


def significance_shrinkage(wald: np.ndarray | float, threshold: float) -> np.ndarray:
    """What share of each estimate to apply: nothing while its Wald statistic ``W`` is under ``threshold``
    ``c``, then ``1 − c/W`` (positive-part shrinkage: an estimate just past its test is applied only by
    as much as it stands out of the noise, so that crossing the threshold moves nothing abruptly)."""
    w = np.asarray(wald, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.where(w > threshold, 1.0 - threshold / np.where(w > 0, w, 1.0), 0.0)


def spent_chi2(false_alarm: float, observations: int) -> float:
    """The χ²₁ threshold of the ``n``-th test of one estimate when ``false_alarm`` is spent over them all.

    The ``n``-th test (``n = observations``, at least 1) is at level ``α / (n (n + 1))``, whose sum
    over every ``n`` is ``α``: by the union bound an estimate tested after every observation of
    pure noise passes anywhere with probability at most ``α`` (alpha spending; Lan & DeMets,
    Biometrika 1983). χ² of one degree of freedom is a normal variable's square.
    """
    n = max(int(observations), 1)
    level = false_alarm / (n * (n + 1.0))
    return NormalDist().inv_cdf(1.0 - level / 2.0) ** 2


class TimeOffsetCalibration:
    """Online estimate of how late the lidar's time stamps are against the odometry's.

    A scan stamped ``t`` whose samples were really taken at ``t − D`` makes SLAM de-skew
    and predict with the odometry of the wrong moment. While the robot turns steadily the
    filter cannot tell (every pose is off by the same ``ω·D``), but when the turn rate
    changes between two scans by ``Δω`` the scan match disagrees with the odometry
    prediction by ``ν_θ ≈ −(D − S)·Δω``, ``S`` the offset applied to that scan (the idea of
    online temporal calibration, Qin & Shen, IROS 2018). Only scans with ``|Δω|`` above
    ``min_rate_change`` (turns starting or ending) are used. With ``φ = −Δω`` each such
    scan gives ``y = ν_θ + φ·(S − S₀) = φ·δ``, ``δ = D − S₀`` the offset beyond the start value
    ``S₀``, and ``δ`` is estimated by least squares with exponential forgetting (``memory_scans``)
    and a prior of ``prior_std_s`` about zero, never forgotten
    (:class:`mazebot.slam.forgotten_regression.ForgottenRegression`, with its variance).

    **Applied only as far as the matches show it.** The turn rate is the odometry's over
    its last 20 ms; with cheap encoders (the bench's cheap robot: 20 counts a motor
    revolution, backlash) its changes between scans are mostly the counts' quantization,
    and the innovation is the turn's slip and backlash, not a stamp offset: on the bench's
    hand-built 8×8 seed 6 the two were uncorrelated (ρ = −0.05 over 259 turn starts, 0.02
    over 257 ends), yet the plain estimate wandered to 4–10 ms and every turn left the
    filter's heading ``ω·S`` off (0.4° at 1.2 rad/s) while the true stamps were within
    0.5 ms of the samples. So, as the heading calibration does, ``δ`` is tested against zero
    by its Wald statistic ``W = δ̂² / var`` (the heteroscedasticity-robust variance of White,
    Econometrica 1980, with HC1's ``n / (n − 1)``) at a level ``false_alarm`` spent over the
    tests (:func:`spent_chi2`), and ``S = S₀ + δ̂·max(0, 1 − c/W)``: nothing while the
    evidence is within what noise gives, all of it once a real offset stands out (stamps
    12 ms late with a clean rate: ``W`` in the thousands after 300 turn changes).

    Example::

        offset = TimeOffsetCalibration()
        offset.observe(innovation_theta_rad, rate_change_radps)   # after each matched scan
        offset.offset_s                                             # subtract from the scan's stamps
    """

    def __init__(
        self,
        initial_s: float = 0.0,
        memory_scans: float = 500.0,
        prior_std_s: float = 0.01,
        noise_std_rad: float = 0.005,
        min_rate_change: float = 0.2,
        limits_s: tuple[float, float] = (-0.05, 0.1),
        max_innovation_rad: float = 0.05,
        false_alarm: float = 0.001,
    ) -> None:
        self.initial_s = float(initial_s)
        self.offset_s = self.initial_s
        self.learnt_s = 0.0  # δ̂: the offset beyond initial_s as estimated, before the test shrinks it
        self.forgetting = 1.0 - 1.0 / max(float(memory_scans), 1.0)
        self.min_rate_change = float(min_rate_change)
        self.limits_s = limits_s
        self.max_innovation_rad = float(max_innovation_rad)
        self.false_alarm = float(false_alarm)
        # least squares (the instrument is φ itself), the prior's share added to Σ λⁿ⁻ⁱ φ² at every solve, never
        # forgotten
        prior = float(noise_std_rad) ** 2 / float(prior_std_s) ** 2
        self._fit = ForgottenRegression(self.forgetting, np.zeros((1, 1)), fixed_prior=np.array([[prior]]))
        self.observations = 0

    def observe(self, innovation_theta_rad: float, rate_change_radps: float) -> None:
        """One observation ``ν_θ = φ·(D − S)`` with ``φ = −Δω``; sets ``offset_s`` from the tested estimate.

        Innovations beyond ``max_innovation_rad`` (a bad match, a slip) are ignored.
        """
        phi = -float(rate_change_radps)
        innovation = float(wrap_angle(innovation_theta_rad))
        if abs(phi) < self.min_rate_change or abs(innovation) > self.max_innovation_rad:
            return
        y = innovation + phi * (self.offset_s - self.initial_s)
        self._fit.update(np.array([phi]), np.array([phi]), y)
        self.observations += 1
        self.learnt_s = float(self._fit.estimate[0])
        applied = self.learnt_s * self._shrinkage()
        self.offset_s = float(np.clip(self.initial_s + applied, *self.limits_s))

    def wald(self) -> float:
        """The learnt offset's Wald statistic against zero (robust variance, HC1; 0 before two observations)."""
        return float(self._fit.wald()[0])

    def _shrinkage(self) -> float:
        if self.false_alarm <= 0:
            return 1.0
        return float(significance_shrinkage(self.wald(), spent_chi2(self.false_alarm, self.observations)))


def odometry_increment(odom_from: np.ndarray, odom_to: np.ndarray) -> np.ndarray:
    """The motion (dx, dy, dθ) from one odometry pose to another, in the robot frame at the first."""
    return relative_pose(odom_from, odom_to)


def rotate_information(information: np.ndarray, theta_rad: float) -> np.ndarray:
    """Re-express a pose information matrix given in a frame into one rotated by ``-theta_rad``.

    A pose error ``δ`` in world axes is ``A δ`` in the axes of a frame at heading ``θ``
    (``A = diag(R(θ)ᵀ, 1)``), so the information becomes ``A⁻ᵀ Ω A⁻¹``.
    """
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    a_inv = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = a_inv.T @ np.asarray(information, dtype=np.float64) @ a_inv
    return 0.5 * (out + out.T)
