"""The forgotten regression shared by the odometry's calibrations (``mazebot.slam.forgotten_regression``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.slam.forgotten_regression import ForgottenRegression


def closed_form(
    z: np.ndarray, phi: np.ndarray, y: np.ndarray, forgetting: float, prior: np.ndarray, fixed: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The estimate and HC1 variance after all ``n`` rows, from the weighted sums written out with numpy.

    Row ``i`` weighs ``λⁿ⁻ⁱ``, the prior ``λⁿ``; the meat's residuals are each row's prediction error under the
    estimate from the rows before it (the closed form again, on them), with the weights squared."""
    n, k = phi.shape

    def estimate(rows: int) -> np.ndarray:
        w = forgetting ** np.arange(rows - 1, -1, -1, dtype=np.float64)
        normal = (z[:rows] * w[:, None]).T @ phi[:rows] + forgetting**rows * prior + fixed
        return np.linalg.solve(normal, (z[:rows] * w[:, None]).T @ y[:rows])

    residuals = np.array([y[i] - phi[i] @ (estimate(i) if i else np.zeros(k)) for i in range(n)])
    w = forgetting ** np.arange(n - 1, -1, -1, dtype=np.float64)
    bread = np.linalg.inv((z * w[:, None]).T @ phi + forgetting**n * prior + fixed)
    meat = (z * (w * residuals)[:, None]).T @ (z * (w * residuals)[:, None])
    weight = w.sum()
    return estimate(n), np.diag(bread @ meat @ bread.T) * weight / (weight - k)


def test_least_squares_of_two_parameters_is_the_weighted_closed_form() -> None:
    rng = np.random.default_rng(4)
    phi = np.column_stack([rng.normal(0.0, 0.4, 300), rng.uniform(0.0, 0.1, 300)])
    y = phi @ np.array([0.03, -0.2]) + rng.normal(0.0, 0.003, 300) * (1.0 + np.abs(phi[:, 0]))
    prior = np.diag([0.01, 0.04])
    fit = ForgottenRegression(0.99, prior)
    for row, value in zip(phi, y, strict=True):
        fit.update(row, row, float(value))
    want_estimate, want_var = closed_form(phi, phi, y, 0.99, prior, np.zeros((2, 2)))
    np.testing.assert_allclose(fit.estimate, want_estimate, rtol=1e-9)
    np.testing.assert_allclose(fit.variance(), want_var, rtol=1e-9)
    np.testing.assert_allclose(fit.wald(), want_estimate**2 / want_var, rtol=1e-9)


def test_one_slope_by_instrumental_variables_with_a_fixed_prior_is_the_closed_form() -> None:
    rng = np.random.default_rng(5)
    truth = rng.uniform(0.0, 0.5, 200)
    z, phi = truth + rng.normal(0.0, 0.02, 200), truth + rng.normal(0.0, 0.02, 200)
    y = 0.05 * truth + rng.normal(0.0, 0.01, 200)
    fit = ForgottenRegression(0.995, np.array([[0.2]]), fixed_prior=np.array([[0.1]]))
    for zi, phi_i, yi in zip(z, phi, y, strict=True):
        fit.update(np.array([zi]), np.array([phi_i]), float(yi))
    want_estimate, want_var = closed_form(z[:, None], phi[:, None], y, 0.995, np.array([[0.2]]), np.array([[0.1]]))
    np.testing.assert_allclose(fit.estimate, want_estimate, rtol=1e-9)
    np.testing.assert_allclose(fit.variance(), want_var, rtol=1e-9)


def test_instruments_recover_a_slope_whose_regressor_is_noisy() -> None:
    # errors in variables: least squares on a noisy regressor leans towards zero by var(noise) / var(φ),
    # the instrument (a second, independent measurement of the same quantity) does not
    rng = np.random.default_rng(6)
    truth = rng.normal(0.0, 0.1, 3000)
    phi, z = truth + rng.normal(0.0, 0.1, 3000), truth + rng.normal(0.0, 0.1, 3000)
    y = 0.5 * truth + rng.normal(0.0, 0.01, 3000)
    by_iv, by_ls = ForgottenRegression(1.0, np.zeros((1, 1))), ForgottenRegression(1.0, np.zeros((1, 1)))
    for zi, phi_i, yi in zip(z, phi, y, strict=True):
        by_iv.update(np.array([zi]), np.array([phi_i]), float(yi))
        by_ls.update(np.array([phi_i]), np.array([phi_i]), float(yi))
    assert by_iv.estimate[0] == pytest.approx(0.5, abs=4.0 * math.sqrt(by_iv.variance()[0]))
    assert by_ls.estimate[0] == pytest.approx(0.25, abs=0.03)


def test_the_robust_variance_is_the_estimates_scatter_under_heteroscedastic_noise() -> None:
    # noise ten times larger on the large regressors: the sandwich's standard deviation is the estimates' own
    # (once the first rows, whose prediction errors carry the whole slope, are forgotten)
    errors, stds = [], []
    for seed in range(200):
        rng = np.random.default_rng(seed)
        phi = rng.uniform(-1.0, 1.0, 400)
        y = 0.1 * phi + rng.normal(0.0, 0.001 + 0.01 * np.abs(phi))
        fit = ForgottenRegression(0.99, np.zeros((1, 1)))
        for phi_i, yi in zip(phi, y, strict=True):
            fit.update(np.array([phi_i]), np.array([phi_i]), float(yi))
        errors.append(fit.estimate[0] - 0.1)
        stds.append(math.sqrt(fit.variance()[0]))
    assert np.std(np.array(errors) / np.array(stds)) == pytest.approx(1.0, abs=0.12)


def test_no_variance_before_there_are_more_observations_than_parameters() -> None:
    fit = ForgottenRegression(0.9, np.eye(2), limit=0.1)
    fit.update(np.array([1.0, 0.5]), np.array([1.0, 0.5]), 3.0)
    fit.update(np.array([0.2, 1.0]), np.array([0.2, 1.0]), -3.0)
    assert np.all(np.isinf(fit.variance())) and not np.any(fit.wald())
    assert np.all(np.abs(fit.estimate) <= 0.1)  # clamped
