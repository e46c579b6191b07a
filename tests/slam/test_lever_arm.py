"""The laser's lever arm learnt from matched turns: recovered where it is, nothing applied where it is not."""

from __future__ import annotations

import numpy as np

from mazebot.geometry import compose, inverse
from mazebot.slam.lever_arm import LeverArmCalibration


def _steps(rng: np.random.Generator, n: int) -> np.ndarray:
    """A robot's steps between scans of a laser log: about a metre, or a turn of up to 90° in place."""
    turning = rng.random(n) < 0.4
    dx = np.where(turning, rng.normal(0.0, 0.05, n), rng.uniform(0.5, 1.2, n))
    dth = np.where(turning, rng.uniform(-1.6, 1.6, n), rng.normal(0.0, 0.05, n))
    return np.column_stack((dx, rng.normal(0.0, 0.02, n), dth))


def _learn(mount: np.ndarray, seed: int, n: int = 400) -> LeverArmCalibration:
    """Odometry steps with 2 cm / 0.5° of noise; the matched steps the laser's, 1 cm / 0.1° off."""
    rng = np.random.default_rng(seed)
    arm = LeverArmCalibration(memory_scans=1000.0, false_alarm=0.001)
    m = np.array([mount[0], mount[1], 0.0])
    for true_step in _steps(rng, n):
        laser_step = compose(inverse(m), compose(true_step, m))
        odometry = true_step + rng.normal(0.0, [0.02, 0.02, 0.009])
        matched = laser_step + rng.normal(0.0, [0.01, 0.01, 0.002])
        arm.observe(odometry, matched)
    return arm


def test_a_laser_ahead_of_the_wheels_is_found_from_the_turns_and_moves_the_prediction() -> None:
    for seed in (1, 2, 3):
        arm = _learn(np.array([0.10, -0.03]), seed)
        np.testing.assert_allclose(arm.learnt, [0.10, -0.03], atol=0.006)
        # applied as far as the test allows: x, far out of the noise, nearly whole; y shrunk towards 0
        assert abs(arm.estimate[0] - 0.10) < 0.01
        assert -0.03 - 0.006 < arm.estimate[1] < 0.0
        # a turn in place of 90°: the laser 10 cm ahead moves by 14 cm the odometry never saw
        predicted = arm.correct(np.array([0.0, 0.0, np.pi / 2]))
        truth = compose(inverse(np.array([0.10, -0.03, 0.0])), compose(np.array([0.0, 0.0, np.pi / 2]),
                                                                        np.array([0.10, -0.03, 0.0])))
        np.testing.assert_allclose(predicted, truth, atol=0.02)


def test_odometry_without_a_lever_arm_is_left_as_it_is() -> None:
    """White noise alone: the test keeps every estimate out, at every step of every seed."""
    for seed in range(1, 11):
        arm = _learn(np.zeros(2), seed)
        assert arm.applied_observations == 0
        step = np.array([0.7, 0.01, 1.2])
        np.testing.assert_array_equal(arm.correct(step), step)


def test_straight_driving_says_nothing_about_it() -> None:
    arm = LeverArmCalibration(false_alarm=0.001)
    for _ in range(200):
        arm.observe(np.array([1.0, 0.0, 0.01]), np.array([1.02, 0.0, 0.01]))
    assert arm.observations == 0 and not np.any(arm.estimate)


def test_a_mount_once_shown_stays_applied_through_a_stretch_of_bad_matches() -> None:
    """A laser 6 cm ahead, shown by 100 clean matched steps; then 400 steps of which 30 % slid 0.3 m
    (matches in a long corridor): the robust variance grows, the Wald statistic falls under the spent
    threshold, and the mount that had been shown is still the one applied, within 1 cm of the truth,
    at every step from the first pass on (``held``; re-tested, it is withdrawn on every seed)."""
    mount = np.array([0.06, 0.0, 0.0])
    turn = np.array([0.0, 0.0, np.pi / 2])
    for seed in (1, 2, 3):
        rng = np.random.default_rng(seed)
        arm = LeverArmCalibration(memory_scans=1000.0, false_alarm=0.001, held=True)
        applied_x_m = []
        for i, true_step in enumerate(_steps(rng, 500)):
            laser_step = compose(inverse(mount), compose(true_step, mount))
            odometry = true_step + rng.normal(0.0, [0.02, 0.02, 0.009])
            matched = laser_step + rng.normal(0.0, [0.01, 0.01, 0.002])
            if i >= 100 and rng.random() < 0.3:
                matched[:2] += rng.normal(0.0, 0.3, 2)
            arm.observe(odometry, matched)
            applied_x_m.append(float(arm.estimate[0]))
        first = next(i for i, x in enumerate(applied_x_m) if x != 0.0)
        assert all(x != 0.0 for x in applied_x_m[first:])
        assert abs(arm.estimate[0] - mount[0]) < 0.01
        np.testing.assert_allclose(arm.correct(turn), compose(inverse(mount), compose(turn, mount)), atol=0.01)
