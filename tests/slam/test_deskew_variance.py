"""A moving revolution's match: its claimed σ along a corridor against its true errors (``deskew_variance``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.config import Config
from mazebot.slam.deskew_variance import deskew_information, with_variance_along
from mazebot.slam.icp import Target, match_scan
from mazebot.slam.params import SlamParams

CELL_M = 0.3  # a hand-built maze's pitch: boards between posts
WALL_Y_M = 0.15  # the corridor's side walls, either side of the robot
AHEAD_M, BEHIND_M = 1.8, 1.5  # the walls closing it ahead and behind
POST_GAP_M = 0.004  # the gap a post leaves between two boards
REVOLUTION_S = 0.18  # the A1 at 5.5 rev/s
SAMPLES = 360
SPEED_MPS = 0.3
COUNT_M = 0.0102  # 20 counts a motor turn: 10.2 mm of a wheel's travel a count (the cheap robot)
RANGE_NOISE = 0.01  # the A1's range noise, std over range


def _corridor_segments() -> tuple[np.ndarray, np.ndarray]:
    """Both ends (K, 2) of every board: side walls of boards with post gaps, and the two end walls."""
    starts, ends = [], []
    for y in (-WALL_Y_M, WALL_Y_M):
        for x0 in np.arange(-BEHIND_M, AHEAD_M, CELL_M):
            starts.append((x0 + POST_GAP_M / 2, y))
            ends.append((min(x0 + CELL_M, AHEAD_M) - POST_GAP_M / 2, y))
    for x in (AHEAD_M, -BEHIND_M):
        starts.append((x, -WALL_Y_M))
        ends.append((x, WALL_Y_M))
    return np.array(starts), np.array(ends)


def _ranges_m(origins_xy: np.ndarray, angles_rad: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """The nearest board each ray (N) from its origin hits (inf where none)."""
    d = np.column_stack((np.cos(angles_rad), np.sin(angles_rad)))[:, None, :]  # (N, 1, 2)
    e = (ends - starts)[None, :, :]  # (1, K, 2)
    rel = starts[None, :, :] - origins_xy[:, None, :]  # (N, K, 2)
    den = d[..., 1] * e[..., 0] - d[..., 0] * e[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (rel[..., 1] * e[..., 0] - rel[..., 0] * e[..., 1]) / den
        s = (rel[..., 1] * d[..., 0] - rel[..., 0] * d[..., 1]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0.05) & (s >= 0) & (s <= 1)
    return np.where(hit, t, np.inf).min(axis=1)


def _moving_revolution(rng: np.random.Generator, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """One revolution (robot frame at its end, the robot at the origin facing +x) driven at ``SPEED_MPS``.

    Each sample is taken from where the robot truly was, with the A1's range noise, then
    de-skewed as SLAM does: moved by the odometry's travel from the sample to the revolution's
    end, and the odometry counted whole encoder counts (a random phase of the counts).
    """
    t_s = np.arange(SAMPLES) / SAMPLES * REVOLUTION_S
    angles = rng.uniform(0.0, math.tau) + np.arange(SAMPLES) / SAMPLES * math.tau
    travel_m = SPEED_MPS * t_s
    end_m = SPEED_MPS * REVOLUTION_S
    origins = np.column_stack((travel_m - end_m, np.zeros(SAMPLES)))
    ranges = _ranges_m(origins, angles, starts, ends)
    seen = np.isfinite(ranges)
    ranges = ranges * (1.0 + RANGE_NOISE * rng.standard_normal(SAMPLES))
    phase_m = rng.uniform(0.0, COUNT_M)
    counted_m = np.floor((travel_m + phase_m) / COUNT_M) * COUNT_M
    counted_end_m = math.floor((end_m + phase_m) / COUNT_M) * COUNT_M
    x = ranges * np.cos(angles) + (counted_m - counted_end_m)
    y = ranges * np.sin(angles)
    return np.column_stack((x, y))[seen]


def _submap(starts: np.ndarray, ends: np.ndarray) -> Target:
    """The corridor's boards as a submap at their true places, a point every 5 mm, seen from the robot."""
    points = [np.linspace(a, b, max(2, int(np.hypot(*(b - a)) / 0.005))) for a, b in zip(starts, ends, strict=True)]
    return Target(np.concatenate(points), np.zeros(2))


def test_the_claimed_sigma_along_a_corridor_is_the_spread_of_the_true_errors() -> None:
    """Driving along a hand-built corridor, the cheap robot's revolutions matched against the true submap.

    Across, hundreds of board points hold the match; along, only the few on the walls ahead and
    behind, all seen at two instants of the revolution and de-skewed by an odometry that counts
    10 mm at a time. ICP's Hessian (the filter's share of it, as the filter takes it) claims the
    place along the corridor to about 2 mm; the matches' true errors along it spread more than
    twice that. With the de-skew's variance (the motion model's for the revolution's travel, the
    robot's default motion model) the claim is within a factor 2 of the spread.
    """
    params = SlamParams.from_config(Config().slam, Config().lidar)
    starts, ends = _corridor_segments()
    submap = _submap(starts, ends)
    rng = np.random.default_rng(7)
    increment = np.array([SPEED_MPS * REVOLUTION_S, 0.0, 0.0])
    errors_m, hessian_m2, claimed_m2 = [], [], []
    for _ in range(80):
        points = _moving_revolution(rng, starts, ends)
        guess = np.array([rng.normal(0.0, 0.005), rng.normal(0.0, 0.002), rng.normal(0.0, 0.002)])
        match = match_scan(submap, points, guess, params.icp)
        assert match.fitness > 0.9
        if match.degenerate:  # the few far points outweighed by the kernel: ICP keeps the guess along, as SLAM does
            continue
        filtered = match.information * params.match_information_scale
        deskewed = deskew_information(filtered, increment, 0.0, params.motion.xy_m2_per_m)
        errors_m.append(float(match.pose[0]))
        hessian_m2.append(float(np.linalg.inv(filtered)[0, 0]))
        claimed_m2.append(float(np.linalg.inv(deskewed)[0, 0]))
    assert len(errors_m) >= 70
    spread_m = math.sqrt(float(np.mean(np.square(errors_m))))
    hessian_sigma_m = math.sqrt(float(np.mean(hessian_m2)))
    claimed_sigma_m = math.sqrt(float(np.mean(claimed_m2)))
    assert spread_m > 2.0 * hessian_sigma_m  # the Hessian alone: too sure along the corridor
    assert 0.5 * spread_m < claimed_sigma_m < 2.0 * spread_m


def test_the_variance_goes_along_the_travel_only() -> None:
    rng = np.random.default_rng(3)
    a = rng.standard_normal((3, 3))
    information = a @ a.T + np.diag([4e4, 9e4, 1e5])
    heading = 0.7
    increment = np.array([0.05, 0.0, 0.02])
    out = deskew_information(information, increment, heading, 0.0004)
    grown = np.linalg.inv(out) - np.linalg.inv(information)
    travel = np.array([math.cos(heading - 0.02), math.sin(heading - 0.02), 0.0])
    np.testing.assert_allclose(grown, 0.0004 * 0.05 * np.outer(travel, travel), atol=1e-12)
    # a turn in place, at rest: nothing added
    np.testing.assert_array_equal(deskew_information(information, np.array([0.0, 0.0, 0.3]), heading, 0.0004),
                                  information)
    # a degenerate match (no information along x): the update stays defined and adds nothing there
    singular = np.diag([0.0, 9e4, 1e5])
    widened = with_variance_along(singular, np.array([1.0, 0.0]), 1e-4)
    np.testing.assert_allclose(widened, singular)
    assert with_variance_along(np.diag([1e4, 1e4, 1e4]), np.array([1.0, 0.0]), 1e-4)[0, 0] == pytest.approx(5e3)
