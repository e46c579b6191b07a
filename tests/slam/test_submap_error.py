"""A sequential edge's covariance floor (``submap_error``): a loop home through a corridor of degenerate matches."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.geometry import compose, relative_pose, wrap_angle
from mazebot.slam.posegraph import PoseGraph
from mazebot.slam.submap_error import with_covariance_floor

SIDE_STEPS = 10  # a rectangle of four corridors, ten one-metre steps each, a quarter turn at each corner
DEGENERATE = range(2, SIDE_STEPS)  # the first corridor's matches leave the position along it free
ODOMETRY_STD = (0.05, math.radians(3.0))  # a step's odometry: position std (m), heading std (rad)
ICP_STD_M = 0.005  # what ICP's Hessian claims on each axis it fixes ...
ICP_HEADING_STD_RAD = {True: math.radians(0.2), False: math.radians(0.12)}  # ... and on the heading (degenerate?)
TRUE_HEADING_STD_RAD = math.radians(0.4)  # what the matches' headings truly err by (ACES seed 2: 0.38-0.50°)
CLOSURE_STD = (0.05, 0.02)  # the loop home's position (m) and heading (rad) std
FLOOR_STD_RAD = 0.005
SEEDS = 30


def _loop_errors(floor_std_rad: float, seed: int) -> tuple[float, float]:
    """RMS heading (rad) and position (m) error against the truth of the optimized rectangle, drawn with ``seed``."""
    rng = np.random.default_rng(seed)
    steps = [np.array([1.0, 0.0, math.pi / 2 if k == SIDE_STEPS - 1 else 0.0])
             for _ in range(4) for k in range(SIDE_STEPS)]
    truth = [np.zeros(3)]
    for step in steps:
        truth.append(compose(truth[-1], step))
    odometry_info = np.diag([ODOMETRY_STD[0] ** -2, ODOMETRY_STD[0] ** -2, ODOMETRY_STD[1] ** -2])
    graph = PoseGraph()
    graph.add_vertex(np.zeros(3))
    chain = np.zeros(3)
    for k, step in enumerate(steps):
        degenerate = k in DEGENERATE
        error = np.array([rng.normal(0.0, ICP_STD_M), rng.normal(0.0, ICP_STD_M),
                          rng.normal(0.0, TRUE_HEADING_STD_RAD)])
        icp_info = np.diag([ICP_STD_M**-2, ICP_STD_M**-2, ICP_HEADING_STD_RAD[degenerate] ** -2])
        if degenerate:
            error[0] = rng.normal(0.0, ODOMETRY_STD[0])  # the odometry's length kept along the corridor
            icp_info[0, 0] = 0.0
        z = step + error
        chain = compose(chain, z)
        graph.add_vertex(chain)
        graph.add_edge(k, k + 1, z, odometry_info + with_covariance_floor(icp_info, 0.0, floor_std_rad))
    closure_info = np.diag([CLOSURE_STD[0] ** -2, CLOSURE_STD[0] ** -2, CLOSURE_STD[1] ** -2])
    graph.add_edge(0, len(steps), relative_pose(truth[0], truth[-1]), closure_info)
    graph.optimize()
    error = graph.vertices - np.array(truth)
    heading = wrap_angle(error[:, 2])
    return float(np.sqrt(np.mean(heading**2))), float(np.sqrt(np.mean(np.sum(error[:, :2] ** 2, axis=1))))


@pytest.mark.parametrize("floor_std_rad", [0.0, FLOOR_STD_RAD])
def test_a_loop_through_a_corridor_of_degenerate_matches_is_not_closed_by_turning_the_corridor(
    floor_std_rad: float,
) -> None:
    """The matches' headings err by more than ICP's Hessian says, the tightest the most: a loop home then turns
    the corridor whose degenerate matches claim the least. With the submap's error as a floor under every
    match's covariance the headings are weighed alike and the map stays nearer the truth (over 30 draws)."""
    errors = np.array([_loop_errors(floor_std_rad, seed) for seed in range(SEEDS)])
    heading_deg, position_m = math.degrees(float(errors[:, 0].mean())), float(errors[:, 1].mean())
    if floor_std_rad == 0.0:
        assert heading_deg > 0.85 and position_m > 0.12  # ICP's claims alone: 0.88°, 0.128 m
    else:
        assert heading_deg < 0.78 and position_m < 0.11  # with the floor: 0.75°, 0.107 m


def test_the_floor_adds_its_variance_and_leaves_a_free_direction_free() -> None:
    """Ω' = (Σ + F)⁻¹ where Ω is invertible; a direction ICP left free stays free (no information made up)."""
    omega = np.array([[400.0, 20.0, 5.0], [20.0, 900.0, 0.0], [5.0, 0.0, 2.0e5]])
    floored = with_covariance_floor(omega, 0.01, 0.005)
    expected = np.linalg.inv(np.linalg.inv(omega) + np.diag([1e-4, 1e-4, 2.5e-5]))
    assert np.allclose(floored, expected, rtol=1e-9)
    degenerate = np.diag([0.0, 4.0e4, 8.0e4])
    assert with_covariance_floor(degenerate, 0.01, 0.005)[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert np.array_equal(with_covariance_floor(omega, 0.0, 0.0), omega)
