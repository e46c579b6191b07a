"""A robot whose wheels' mean diameter is off the configured one learns that scale as it maps.

A maker takes the tyre's diameter from a datasheet or a ruler; the rolling diameter under the
robot's weight is 0.5-2 % off it (Borenstein & Feng 1996, the scale error ``E_s``), and every
straight the odometry measures is that far off too. The simulated cheap robot below has wheels
whose ratio is calibrated (``[drive] wheel_diameter_ratio``, what ``mazebot calibrate`` finds)
and whose mean is 1 % larger or 2 % smaller than configured: its odometry's distance is off by
exactly that (``dx_true = (1 + m)·dx`` with ``m`` the wheels' mean scale minus one), which the
online distance calibration (:mod:`mazebot.slam.distance_calibration`) must find from the walls,
while the trajectory stays within the hand-built maze's ATE target against the simulator's truth.
"""

from __future__ import annotations

import math

import pytest

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import parse_config
from mazebot.slam.slam import Slam

pytestmark = pytest.mark.slow  # a simulated tour of a 4x4 maze

CHEAP_WHEEL_RATIO = 1.0305  # the cheap robot's right over left wheel (1.015 / 0.985), calibrated
ATE_RMS_TARGET_M = 0.015  # the hand-built mazes' ATE RMS target (BENCHMARKS.md)
SIGMAS = 3.0  # how far the learnt scale may stand off the truth in its own standard deviations


def _tour(wheel_mean_scale: float) -> tuple[dict, Slam]:
    """A scripted tour of a generated 4x4 maze by the cheap robot with both wheels ``wheel_mean_scale`` of
    their configured diameters; its metrics and the daemon's SLAM."""
    config = parse_config({
        "sim": {
            "robot_build": "cheap",
            "wheel_diameter_left_scale": wheel_mean_scale,
            "wheel_diameter_right_scale": wheel_mean_scale,
        },
        "drive": {"wheel_diameter_ratio": CHEAP_WHEEL_RATIO},
        "slam": {"filter": {"calibrate_distance": True}},
    })
    seen: list[Slam] = []
    metrics, _ = run_one(config, RunSpec(None, (4, 4), 1, "scripted", max_sim_s=120.0), watch_slam=seen.append)
    return metrics, seen[0]


@pytest.mark.parametrize("wheel_mean_scale", [1.01, 0.98])
def test_a_robot_whose_wheels_are_off_in_size_learns_their_scale_and_maps(wheel_mean_scale: float) -> None:
    metrics, slam = _tour(wheel_mean_scale)
    calibration = slam.distance_calibration
    learnt_std = math.sqrt(calibration.variance())
    assert learnt_std < 0.005, (calibration.observations, learnt_std)
    assert calibration.estimate == pytest.approx(wheel_mean_scale - 1.0, abs=SIGMAS * learnt_std), (
        calibration.estimate, calibration.learnt, learnt_std)
    assert metrics["done"], metrics
    assert metrics["ate_rms_m"] <= ATE_RMS_TARGET_M, metrics
