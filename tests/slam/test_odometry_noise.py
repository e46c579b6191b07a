"""The odometry noise learnt from scan matches: the prior first, then the data's own spread, robust to bad matches."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.slam.ekf import MotionNoise
from mazebot.slam.odometry_noise import OdometryNoiseEstimate

PRIOR = MotionNoise(xy_m2_per_m=0.1**2, theta_rad2_per_m=0.1**2, theta_rad2_per_rad=0.1**2, estimate=True)


def _pairs(
    rng: np.random.Generator, count: int, sigma_xy: float, sigma_th: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Odometry increments of ~1 m / ~0.3 rad and the true ones, off by the motion model's noise."""
    out = []
    for _ in range(count):
        u = np.array([rng.uniform(0.5, 1.5), rng.uniform(-0.1, 0.1), rng.uniform(-0.5, 0.5)])
        d = math.hypot(u[0], u[1])
        e = rng.standard_normal(3) * np.array([sigma_xy * math.sqrt(d), sigma_xy * math.sqrt(d),
                                               sigma_th * math.sqrt(d + abs(u[2]))])
        out.append((u, u + e))
    return out


def test_the_prior_stands_until_enough_matches_then_the_noise_is_learnt() -> None:
    rng = np.random.default_rng(3)
    estimate = OdometryNoiseEstimate(PRIOR)
    pairs = _pairs(rng, 400, 0.03, 0.02)
    for u, m in pairs[: PRIOR.estimate_min_matches - 1]:
        estimate.observe(u, m)
    assert estimate.noise == PRIOR
    for u, m in pairs[PRIOR.estimate_min_matches - 1 :]:
        estimate.observe(u, m)
    assert estimate.pairs == 400
    assert math.sqrt(estimate.noise.xy_m2_per_m) == pytest.approx(0.03, rel=0.15)
    assert math.sqrt(estimate.noise.theta_rad2_per_m) == pytest.approx(0.02, rel=0.15)
    assert estimate.noise.theta_rad2_per_rad == estimate.noise.theta_rad2_per_m


def test_a_few_wrong_matches_barely_move_the_estimate() -> None:
    rng = np.random.default_rng(5)
    estimate = OdometryNoiseEstimate(PRIOR)
    for k, (u, m) in enumerate(_pairs(rng, 200, 0.03, 0.02)):
        if k % 10 == 0:  # one match in ten is a wall one door over, 20° off
            m = m + np.array([1.0, -0.8, 0.35])
        estimate.observe(u, m)
    assert math.sqrt(estimate.noise.xy_m2_per_m) < 0.045
    assert math.sqrt(estimate.noise.theta_rad2_per_m) < 0.03


def test_perfect_odometry_stops_at_the_floor_and_a_heading_bias_counts_as_noise() -> None:
    estimate = OdometryNoiseEstimate(PRIOR)
    for _ in range(50):
        u = np.array([1.0, 0.0, 0.1])
        estimate.observe(u, u)
    assert estimate.noise.xy_m2_per_m == PRIOR.estimate_floor_xy_m2_per_m
    assert estimate.noise.theta_rad2_per_m == PRIOR.estimate_floor_theta_rad2
    biased = OdometryNoiseEstimate(PRIOR)
    for _ in range(50):  # the odometry turns 0.02 rad less than the robot on every metre
        biased.observe(np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.02]))
    assert math.sqrt(biased.noise.theta_rad2_per_m) == pytest.approx(0.02 / 0.6745, rel=1e-6)
