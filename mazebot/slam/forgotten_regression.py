"""A linear regression over exponentially forgotten sums, with the robust variance of its estimate.

The odometry's online calibrations (:class:`mazebot.slam.ekf.HeadingCalibration`,
:class:`mazebot.slam.ekf.TimeOffsetCalibration`,
:class:`mazebot.slam.distance_calibration.DistanceCalibration`) each fit ``y = φᵀθ + e`` to the
scans matched so far, the recent ones weighing most, and apply the fit only as far as its
variance allows. This is that fit, once:

- **Estimate** (instrumental variables, Söderström & Stoica, *Instrumental Variable Methods
  for System Identification*, 1983; least squares when the instrument ``z`` is the regressor
  ``φ``), over sums forgotten by ``λ`` per observation (Ljung & Söderström, *Theory and
  Practice of Recursive Identification*, 1983)::

      θ̂ = (P₀ λⁿ + Σ λⁿ⁻ⁱ zᵢφᵢᵀ + R)⁻¹ Σ λⁿ⁻ⁱ zᵢyᵢ

  clamped to ``±limit``. The prior's information ``P₀`` is forgotten with the observations;
  ``R`` (``fixed_prior``) is added to every solve and never forgotten.
- **Variance**: the heteroscedasticity-robust ("sandwich") one (White, Econometrica 1980),
  the residuals' own spread whatever the noise's model, with the weights forgetting as the
  sums do and the small-sample correction ``n / (n − k)`` of HC1 (MacKinnon & White,
  J. Econometrics 1985), ``n = Σ λⁿ⁻ⁱ`` the observations as the forgetting weighs them and
  ``k`` the parameters::

      B = (P₀ λⁿ + Σ λⁿ⁻ⁱ zᵢφᵢᵀ + R)⁻¹,   var θ̂ = B (Σ λ²⁽ⁿ⁻ⁱ⁾ rᵢ² zᵢzᵢᵀ) Bᵀ · n / (n − k)

  with ``rᵢ = yᵢ − φᵢᵀθ̂`` the residual of the estimate before the observation (a recursive
  fit's prediction error).

What is observed, what test the estimate must pass and how far it is applied stay with each
calibration. A single parameter's arithmetic is the scalar one (a division, squares by
``**``), not a 1×1 matrix's, whose LAPACK solve and products round differently: the
calibrations' runs are functions of their seed, to the last digit.

Example::

    fit = ForgottenRegression(forgetting=0.999, prior_information=np.array([[0.25]]), limit=0.1)
    fit.update(instrument=np.array([0.31]), regressor=np.array([0.30]), observed=0.01)
    fit.estimate, fit.variance(), fit.wald()
"""

from __future__ import annotations

import math

import numpy as np


class ForgottenRegression:
    """``θ`` of ``y = φᵀθ + e`` by instrumental variables over exponentially forgotten sums, with its HC1
    variance (module docstring)."""

    def __init__(
        self,
        forgetting: float,
        prior_information: np.ndarray,
        fixed_prior: np.ndarray | None = None,
        limit: float = math.inf,
    ) -> None:
        self.forgetting = float(forgetting)  # λ, per observation
        self.limit = float(limit)
        self._cross = np.array(prior_information, dtype=np.float64)  # P₀ λⁿ + Σ λⁿ⁻ⁱ z φᵀ
        self.parameters = self._cross.shape[0]  # k
        self._fixed = None if fixed_prior is None else np.array(fixed_prior, dtype=np.float64)
        self._zy = np.zeros(self.parameters)  # Σ λⁿ⁻ⁱ z y
        self._meat = np.zeros_like(self._cross)  # Σ λ²⁽ⁿ⁻ⁱ⁾ r² z zᵀ
        self.weight = 0.0  # n = Σ λⁿ⁻ⁱ
        self.estimate = np.zeros(self.parameters)  # θ̂, clamped

    def update(self, instrument: np.ndarray, regressor: np.ndarray, observed: float) -> None:
        """One observation ``y`` with its regressor ``φ`` and instrument ``z`` (each of ``k`` values)."""
        z = np.asarray(instrument, dtype=np.float64)
        phi = np.asarray(regressor, dtype=np.float64)
        residual = observed - phi @ self.estimate
        lam = self.forgetting
        self._cross = lam * self._cross + np.outer(z, phi)
        self._zy = lam * self._zy + z * observed
        # the weights forget as the sums do: the sandwich's meat with the weights squared
        self._meat = lam**2 * self._meat + residual**2 * self._outer_square(z)
        self.weight = lam * self.weight + 1.0
        self.estimate = np.clip(self._solve(self._normal(), self._zy), -self.limit, self.limit)

    def variance(self) -> np.ndarray:
        """Each parameter's robust variance with HC1's correction (infinite before there are more observations
        than parameters)."""
        if self.weight <= self.parameters:
            return np.full(self.parameters, math.inf)
        normal = self._normal()
        if self.parameters == 1:
            spread = self._meat[0] / normal[0, 0] ** 2
        else:
            bread = np.linalg.inv(normal)
            spread = np.diag(bread @ self._meat @ bread.T)
        return spread * self.weight / (self.weight - self.parameters)

    def wald(self) -> np.ndarray:
        """Each parameter's Wald statistic against zero, ``θ̂² / var`` (0 where the variance is 0 or infinite)."""
        var = self.variance()
        known = (var > 0.0) & (var < math.inf)
        square = self.estimate**2 if self.parameters > 1 else np.array([self.estimate[0] ** 2])
        return np.where(known, square / np.where(known, var, 1.0), 0.0)

    def _normal(self) -> np.ndarray:
        return self._cross if self._fixed is None else self._cross + self._fixed

    def _outer_square(self, z: np.ndarray) -> np.ndarray:
        return np.outer(z, z) if self.parameters > 1 else np.array([[z[0] ** 2]])

    def _solve(self, normal: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        return np.linalg.solve(normal, rhs) if self.parameters > 1 else rhs / normal[0]
