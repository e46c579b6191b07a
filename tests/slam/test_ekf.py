"""The pose filter: odometry history, EKF against ground truth, and the online calibrations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.geometry import compose, relative_pose, wrap_angle
from mazebot.slam.ekf import (
    HeadingCalibration,
    MotionNoise,
    OdometryHistory,
    PoseEkf,
    TimeOffsetCalibration,
    rotate_information,
)


def test_history_interpolates_unwrapped_heading_and_forgets_old_poses() -> None:
    history = OdometryHistory(horizon_s=1.0)
    history.append(0.0, 0.0, 0.0, math.pi - 0.1)
    history.append(0.1, 0.1, 0.0, -math.pi + 0.1)  # crossed ±π: +0.2 rad, not -6.08
    x, _, th = history.at(np.array([0.05, 0.2, -1.0]))
    assert x == pytest.approx([0.05, 0.1, 0.0])
    assert th[0] == pytest.approx(math.pi)  # halfway through the short way round
    assert history.pose_at(0.05)[2] == pytest.approx(-math.pi)  # wrapped for users
    for k in range(2, 200):
        history.append(0.1 * k, 0.1 * k, 0.0, 0.0)
    oldest, newest = history.span_s
    assert newest - oldest < 1.2 and len(history) <= 12  # the horizon, and one pose before it
    with pytest.raises(ValueError, match="backwards"):
        history.append(1.0, 0.0, 0.0, 0.0)


def _drive(steps: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """True poses along arcs and the matching true increments."""
    poses = [np.zeros(3)]
    increments = []
    for k in range(steps):
        v, w = 0.05, 0.4 * math.sin(k / 15.0)  # 5 cm and up to 0.4 rad per step
        inc = np.array([v * math.cos(w / 2), v * math.sin(w / 2), w])
        increments.append(inc)
        poses.append(compose(poses[-1], inc))
    return np.array(poses), np.array(increments)


def test_ekf_fuses_biased_noisy_odometry_with_pose_fixes_to_beat_both() -> None:
    rng = np.random.default_rng(4)
    truth, increments = _drive(400, rng)
    noise = MotionNoise(xy_m2_per_m=4e-4, theta_rad2_per_m=4e-4, theta_rad2_per_rad=2.5e-3)
    ekf = PoseEkf(truth[0], noise=noise)
    dead = truth[0].copy()
    fix_std = np.array([0.02, 0.02, 0.02])
    err_ekf, err_dead, nees = [], [], []
    for k, inc in enumerate(increments, start=1):
        d = math.hypot(inc[0], inc[1])
        bias = np.array([0.02 * d, 0.0, 0.01 * d])
        odo = inc + bias + rng.standard_normal(3) * np.array([0.01 * d, 0.01 * d, 0.03 * d])
        dead = compose(dead, odo)
        ekf.predict(odo)
        if k % 5 == 0:  # a scan match every fifth step
            z = truth[k] + rng.standard_normal(3) * fix_std
            ekf.correct(z, np.diag(1.0 / fix_std**2))
        e = ekf.mean - truth[k]
        e[2] = wrap_angle(e[2])
        err_ekf.append(e)
        err_dead.append(math.hypot(*(dead[:2] - truth[k, :2])))
        nees.append(float(e @ np.linalg.solve(ekf.covariance, e)))
    err_ekf = np.array(err_ekf)
    rms_xy = math.sqrt(np.mean(err_ekf[:, 0] ** 2 + err_ekf[:, 1] ** 2))
    assert rms_xy < 0.025  # about the fixes' own noise ...
    assert rms_xy < 0.25 * math.sqrt(np.mean(np.square(err_dead)))  # ... far below dead reckoning
    assert math.degrees(math.sqrt(np.mean(err_ekf[:, 2] ** 2))) < 1.5
    # the covariance is honest: average NEES near its 3 degrees of freedom
    assert 1.0 < np.mean(nees) < 6.0


def test_unobserved_direction_keeps_the_prediction() -> None:
    # a corridor along x: the match says nothing about x, everything about y and heading
    ekf = PoseEkf(np.zeros(3), initial_std=(0.05, 0.05, 0.05))
    ekf.predict(np.array([1.0, 0.0, 0.0]))
    info = np.diag([0.0, 1e4, 1e4])
    assert ekf.correct(np.array([5.0, 0.02, 0.01]), info)
    assert ekf.mean[0] == pytest.approx(1.0, abs=1e-9)  # x: odometry, not the match's 5 m
    assert ekf.mean[1] == pytest.approx(0.02, abs=2e-3)
    assert ekf.mean[2] == pytest.approx(0.01, abs=2e-3)
    assert ekf.covariance[1, 1] < 1e-3 < ekf.covariance[0, 0]


def test_gate_refuses_a_match_far_outside_the_prediction() -> None:
    ekf = PoseEkf(np.zeros(3), initial_std=(0.01, 0.01, 0.01))
    ekf.predict(np.array([0.1, 0.0, 0.0]))
    before = ekf.mean.copy()
    assert not ekf.correct(np.array([0.4, 0.0, 0.0]), np.eye(3) * 1e4)  # 30 cm off: a false match
    np.testing.assert_array_equal(ekf.mean, before)
    assert ekf.correct(np.array([0.105, 0.0, 0.0]), np.eye(3) * 1e4)


def test_rotate_information_is_the_covariance_rotated() -> None:
    cov_world = np.diag([0.04, 0.0001, 0.01])  # long along world x
    theta = 0.7
    info_local = rotate_information(np.linalg.inv(cov_world), theta)
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])  # world -> frame at theta
    np.testing.assert_allclose(np.linalg.inv(info_local), rot @ cov_world @ rot.T, rtol=1e-9, atol=1e-12)


def test_heading_calibration_learns_unequal_wheels() -> None:
    # true heading change = (1 + s) dθ + k dx with s = 0.01, k = 0.027 rad/m (0.4 % wheel mismatch)
    rng = np.random.default_rng(2)
    cal = HeadingCalibration()
    for _ in range(600):
        raw = np.array([rng.uniform(0.0, 0.05), 0.0, rng.uniform(-0.2, 0.2)])
        true = raw.copy()
        true[2] = 1.01 * raw[2] + 0.027 * raw[0] + rng.normal(0.0, 0.003)
        cal.observe(raw, true)
    assert cal.bias_rad_per_m == pytest.approx(0.027, abs=0.004)
    assert cal.scale == pytest.approx(0.01, abs=0.004)
    corrected = cal.correct(np.array([0.04, 0.0, 0.1]))
    assert corrected[2] == pytest.approx(1.01 * 0.1 + 0.027 * 0.04, abs=5e-4)


def test_time_offset_calibration_finds_late_stamps() -> None:
    # scans stamped 12 ms late: when the turn rate changes by Δω the match disagrees by -D Δω
    rng = np.random.default_rng(3)
    offset = TimeOffsetCalibration()
    for _ in range(300):
        d_omega = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.0)
        innovation = -(0.012 - offset.offset_s) * d_omega + rng.normal(0.0, 0.002)
        offset.observe(innovation, d_omega)
        offset.observe(rng.normal(0.0, 0.002), 0.0)  # steady turning: no information, ignored
    assert offset.offset_s == pytest.approx(0.012, abs=0.002)
    assert offset.observations == 300


def test_time_offset_calibration_applies_nothing_where_the_rate_changes_do_not_explain_the_innovations() -> None:
    # true stamps (D = 0), a cheap robot's odometry: its 20 ms turn rate changes between scans by
    # its counts' quantization (σ 0.6 rad/s), and the matches disagree with its turns by slip and
    # backlash (σ 3 mrad), unrelated to those changes. Fitted plainly the offset wanders by 2-10 ms.
    for seed in range(10):
        rng = np.random.default_rng(seed)
        offset = TimeOffsetCalibration()
        for _ in range(500):
            offset.observe(rng.normal(0.0, 0.003), rng.normal(0.0, 0.6))
            assert abs(offset.offset_s) < 0.001
    # the same noise, stamps 6 ms late: found
    rng = np.random.default_rng(3)
    offset = TimeOffsetCalibration()
    for _ in range(500):
        d_omega = rng.normal(0.0, 0.6)
        offset.observe(-(0.006 - offset.offset_s) * d_omega + rng.normal(0.0, 0.003), d_omega)
    assert offset.offset_s == pytest.approx(0.006, abs=0.001)


def test_relative_increment_matches_compose() -> None:
    a, b = np.array([1.0, 2.0, 0.5]), np.array([1.5, 2.2, 0.9])
    np.testing.assert_allclose(compose(a, relative_pose(a, b)), b, atol=1e-12)


def test_history_buffer_grows_and_compacts_without_losing_poses() -> None:
    history = OdometryHistory(horizon_s=12.0, capacity=8)  # 600 poses at 50 Hz: the buffer must grow
    for k in range(3000):
        history.append(0.02 * k, 0.001 * k, -0.001 * k, 0.0)
    oldest, newest = history.span_s
    assert newest == pytest.approx(59.98) and 11.9 < newest - oldest < 12.1
    x, y, _ = history.at(np.array([50.01, 59.98]))
    assert x == pytest.approx([2.5005, 2.999]) and y == pytest.approx([-2.5005, -2.999])
    assert history.latest[0] == pytest.approx(59.98)


def test_pose_at_kept_for_a_covered_time_is_what_the_history_interpolates_whatever_comes_after() -> None:
    """pose_at keeps the pose of a time the history covers; appends, drops and repeated
    stamps afterwards must leave it equal to a fresh interpolation, bit for bit."""
    rng = np.random.default_rng(3)
    for _ in range(100):
        horizon_s = float(rng.uniform(0.2, 3.0))
        kept = OdometryHistory(horizon_s=horizon_s, capacity=int(rng.integers(4, 40)))
        fresh = OdometryHistory(horizon_s=horizon_s, capacity=100_000)  # asked only through at()
        time_s, theta = 0.0, 0.0
        asked: list[float] = []
        for _ in range(200):
            time_s += float(rng.choice([0.0, 0.005, 0.02, 0.1]))  # repeated stamps too
            theta += float(rng.normal(0.0, 2.0))
            x, y = rng.normal(size=2)
            kept.append(time_s, x, y, theta)
            fresh.append(time_s, x, y, theta)
            if rng.random() < 0.3:
                asked.append(time_s - float(rng.uniform(-0.05, 0.3)))  # ahead of, inside and behind the history
            if asked:
                q = float(rng.choice(asked[-3:]))
                xs, ys, ths = fresh.at(np.array([q]))
                expected = np.array([float(xs[0]), float(ys[0]), float(wrap_angle(ths[0]))])
                assert np.array_equal(kept.pose_at(q), expected)
