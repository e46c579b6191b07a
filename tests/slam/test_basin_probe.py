"""ICP restarted beside a match: the information along a direction its basin does not hold (``basin_probe``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mazebot.config import load_config
from mazebot.slam.basin_probe import basin_variance_m2, weakest_position_direction, widened_along
from mazebot.slam.carmen import read_carmen
from mazebot.slam.slam import Slam, SlamParams
from mazebot.slam.slam_cli import from_first_pose, laser_log_params, log_updates, noisy_odometry


def test_the_covariance_is_widened_along_one_direction_only() -> None:
    rng = np.random.default_rng(4)
    a = rng.standard_normal((3, 3))
    information = a @ a.T + np.diag([4e4, 9e4, 1e5])
    direction, held = weakest_position_direction(information)
    w = np.array([direction[0], direction[1], 0.0])
    assert held == pytest.approx(float(w @ information @ w))
    widened = widened_along(information, direction, 0.05**2)
    assert float(w @ widened @ w) == pytest.approx(1.0 / 0.05**2)  # the information along it: the probe's
    # the covariance grows along w alone: Σ' − Σ is a multiple of w wᵀ
    grown = np.linalg.inv(widened) - np.linalg.inv(information)
    np.testing.assert_allclose(grown, grown[0, 0] / w[0] ** 2 * np.outer(w, w), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(widened) > 0)
    # a probe that asks for less variance than the Hessian's leaves the information alone
    np.testing.assert_array_equal(widened_along(information, direction, 0.1 / held), information)


def test_the_basin_is_the_span_icp_cannot_tell_from_the_match() -> None:
    assert basin_variance_m2((0.0, 0.0)) == 0.0  # both runs came back
    assert basin_variance_m2((-0.1, 0.1)) == pytest.approx(0.1**2 / 3)  # both stayed: uniform over ±0.1 m
    assert basin_variance_m2((0.0, 0.04)) == pytest.approx(0.02**2 / 3)  # one side holds
    assert basin_variance_m2((0.03, -0.01)) == 0.0  # both ran past the match: it holds from both sides


@pytest.mark.parametrize("probe_m", [0.0, 0.1])
def test_the_second_scan_no_longer_claims_the_start_corridor(intel_log_path: Path, probe_m: float) -> None:
    """The Intel log starts with the robot turning in place in a corridor along the map's x axis.

    Odometry ``0.1,0.1`` seed 1. ICP's match of the second scan against the first converges
    0.12 m along the corridor from the corrected poses, with a Hessian that claims its place
    along it to a few millimetres; ICP started 0.1 m to either side stays there. Without the
    probe the sequential edge takes that claim and the whole in-place turn sits a decimetre
    along the corridor, where the odometry is within centimetres of the corrected poses. With
    ICP restarted 0.1 m to either side, the edge says what ICP can: the corridor's direction to
    centimetres, not millimetres; across it and in heading as sure as before; and the turn's
    scans lie where the corrected poses put them.
    """
    lasers = read_carmen(intel_log_path).lasers[:12]
    reference = np.array([r.pose for r in lasers])
    odometry = noisy_odometry(reference, 0.1, 0.1, np.random.default_rng(1))
    config = load_config(None)
    params = replace(laser_log_params(SlamParams.from_config(config.slam, config.lidar)), basin_probe_m=probe_m)
    slam = Slam(params, initial_pose=np.zeros(3))
    first_edge = None
    poses = np.zeros_like(reference)
    for k, update in enumerate(log_updates(slam, lasers, from_first_pose(odometry, reference))):
        poses[k] = update.pose
        if k == 1:
            assert update.matched and update.keyframe == 1
            first_edge = slam.graph.edges[-1]
    assert first_edge is not None and (first_edge.i, first_edge.j) == (0, 1)
    covariance = np.linalg.inv(first_edge.information)  # in keyframe 1's frame, turned a few degrees from the map's
    heading = float(poses[1, 2])
    along = np.array([np.cos(heading), -np.sin(heading), 0.0])  # the map's x axis in that frame
    across = np.array([np.sin(heading), np.cos(heading), 0.0])
    sigma_along, sigma_across = np.sqrt(along @ covariance @ along), np.sqrt(across @ covariance @ across)
    turn = np.arange(1, 12)  # scans 1-11, within 0.25 m of the first
    off_along = float(np.mean(poses[turn, 0] - reference[turn, 0]))
    if probe_m == 0.0:  # the Hessian's claim, and the slide it carries
        assert sigma_along < 0.005 and off_along < -0.08
    else:
        assert sigma_along > 0.02 and abs(off_along) < 0.03
        assert slam.matches_widened >= 1
    assert sigma_across < 0.005 and np.sqrt(covariance[2, 2]) < np.radians(0.5)
