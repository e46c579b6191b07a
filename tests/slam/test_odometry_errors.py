"""The systematic odometry model: its errors have the statistics it was asked for."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.errors import UsageError
from mazebot.geometry import relative_pose, wrap_angle
from mazebot.slam.odometry_errors import SystematicOdometryModel, parse_systematic, systematic_odometry


def _straight(steps: int, step_m: float = 0.5) -> np.ndarray:
    return np.column_stack((np.arange(steps + 1) * step_m, np.zeros(steps + 1), np.zeros(steps + 1)))


def _turns(steps: int, step_rad: float = 0.5) -> np.ndarray:
    return np.column_stack((np.zeros(steps + 1), np.zeros(steps + 1), wrap_angle(np.arange(steps + 1) * step_rad)))


def test_wheel_scales_make_a_distance_scale_and_a_heading_drift_on_straights() -> None:
    model = SystematicOdometryModel(0.02, 0.03, 0.0, 0.0, track_width_m=0.4)
    odo, drawn, _ = systematic_odometry(_straight(100), model, (0.0, 0.0), np.random.default_rng(3))
    steps = relative_pose(odo[:-1], odo[1:])
    # Borenstein & Feng: a straight metre is (1 + (e_l + e_r)/2) long and turns by (e_r - e_l)/b'
    scale = 1.0 + 0.5 * (drawn.left_scale + drawn.right_scale)
    np.testing.assert_allclose(np.hypot(steps[:, 0], steps[:, 1]), 0.5 * scale, rtol=1e-9)
    believed_b = 0.4 * (1.0 + drawn.track_scale)
    np.testing.assert_allclose(steps[:, 2], 0.5 * (drawn.right_scale - drawn.left_scale) / believed_b, rtol=1e-9)
    assert abs(drawn.right_scale - drawn.left_scale) > 1e-3  # the seed drew a mismatch: the test means something


def test_in_place_turns_are_scaled_by_the_wheels_over_the_track() -> None:
    model = SystematicOdometryModel(0.02, 0.03, 0.0, 0.0)
    odo, drawn, _ = systematic_odometry(_turns(60), model, (0.0, 0.0), np.random.default_rng(4))
    turned = np.unwrap(odo[:, 2])[-1]
    expected = 60 * 0.5 * (1.0 + 0.5 * (drawn.left_scale + drawn.right_scale)) / (1.0 + drawn.track_scale)
    assert turned == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(odo[:, :2], 0.0, atol=1e-12)  # turning in place does not move it


def test_drawn_errors_have_the_asked_spread_over_seeds() -> None:
    model = SystematicOdometryModel(0.01, 0.02, 0.005, 0.0)
    drawn = [model.draw(np.random.default_rng(seed)) for seed in range(3000)]
    for name, std in (("left_scale", 0.01), ("right_scale", 0.01), ("track_scale", 0.02),
                      ("initial_bias_rad_per_m", 0.005)):
        values = np.array([getattr(d, name) for d in drawn])
        assert np.std(values) == pytest.approx(std, rel=0.06)
        assert abs(np.mean(values)) < 4 * std / math.sqrt(len(values))
    left = np.array([d.left_scale for d in drawn])
    right = np.array([d.right_scale for d in drawn])
    assert abs(np.corrcoef(left, right)[0, 1]) < 0.06  # each wheel its own error


def test_the_heading_bias_is_a_random_walk_in_distance() -> None:
    walk = 0.004
    model = SystematicOdometryModel(0.0, 0.0, 0.0, walk)
    path = _straight(100, step_m=0.5)  # 50 m
    biases = np.array([systematic_odometry(path, model, (0.0, 0.0), np.random.default_rng(s))[2] for s in range(500)])
    # variance grows with the distance travelled: σ_walk² · s (here after 12.5 m and 50 m; 500 runs: ±19 % at 3σ)
    for k, metres in ((25, 12.5), (100, 50.0)):
        assert np.var(biases[:, k]) == pytest.approx(walk**2 * metres, rel=0.2)
    # and the bias turns the odometry: its heading is the integral of β over the distance
    odo, _, bias = systematic_odometry(path, model, (0.0, 0.0), np.random.default_rng(7))
    np.testing.assert_allclose(np.unwrap(odo[:, 2])[-1], np.sum(bias[:-1]) * 0.5, rtol=1e-9)


def test_the_same_seed_gives_the_same_odometry_and_white_noise_is_added() -> None:
    path = _straight(50)
    a = systematic_odometry(path, SystematicOdometryModel(), (0.05, 0.05), np.random.default_rng(1))[0]
    b = systematic_odometry(path, SystematicOdometryModel(), (0.05, 0.05), np.random.default_rng(1))[0]
    c = systematic_odometry(path, SystematicOdometryModel(), (0.0, 0.0), np.random.default_rng(1))[0]
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 0.01


@pytest.mark.parametrize("text", ["0.01,0.02", "a,b,c,d", "-0.01,0,0,0", "nan,0,0,0"])
def test_bad_systematic_settings_are_one_usage_error(text: str) -> None:
    with pytest.raises(UsageError, match="--odom-systematic"):
        parse_systematic(text)
