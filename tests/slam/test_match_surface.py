"""A match's covariance from the correlative likelihood surface about it (Olson, ICRA 2009)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mazebot.geometry import transform_points as transform
from mazebot.slam.carmen import read_carmen
from mazebot.slam.correlative import CorrelativeParams, LikelihoodTable, select_points
from mazebot.slam.icp import IcpParams, Target, match_scan
from mazebot.slam.match_surface import capped_information, surface_covariance

RESOLUTION_M = 0.05
SIGMA_M = 0.1


def _wall(a: tuple[float, float], b: tuple[float, float], n: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)[:, None]
    return np.asarray(a) * (1.0 - t) + np.asarray(b) * t


def _surface(reference_xy: np.ndarray, scan_xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    table = LikelihoodTable(reference_xy, RESOLUTION_M, SIGMA_M, 0)
    return surface_covariance(table, scan_xy, pose, SIGMA_M).covariance


def test_a_corridor_is_wide_along_and_narrow_across() -> None:
    """Two long parallel walls: nothing says where along them the scan is, everything where across."""
    reference = np.vstack([_wall((-8, -1), (8, -1), 800), _wall((-8, 1), (8, 1), 800)])
    scan = np.vstack([_wall((-4, -1), (4, -1), 120), _wall((-4, 1), (4, 1), 120)])
    pose = np.array([0.0, 0.0, 0.0])
    cov = _surface(reference, scan, pose)
    # along: the whole grid alike, a uniform spread over ±3 cells (std 2 cells)
    assert math.sqrt(cov[0, 0]) > 0.9 * 2 * RESOLUTION_M
    # across and in heading: the table's sharpness over 240 independent points, under a millimetre / 0.1°
    assert math.sqrt(cov[1, 1]) < 1e-3 and math.sqrt(cov[2, 2]) < math.radians(0.1)
    # a corridor turned by 30°: the same ellipse, turned with it
    turn = math.radians(30.0)
    rot = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    cov_turned = _surface(reference @ rot.T, scan, np.array([0.0, 0.0, turn]))
    along = np.array([math.cos(turn), math.sin(turn)])
    across = np.array([-math.sin(turn), math.cos(turn)])
    assert along @ cov_turned[:2, :2] @ along > 0.5 * (2 * RESOLUTION_M) ** 2
    assert across @ cov_turned[:2, :2] @ across < 0.05 * along @ cov_turned[:2, :2] @ along


def test_a_corner_is_narrow_both_ways() -> None:
    """Two walls at right angles fix the pose in both directions: the surface is tight."""
    # the corner off the table's cell boundaries (a wall on one reads two cells alike)
    corner = np.array([0.512, 0.371])
    reference = np.vstack([_wall((0, 0), (6, 0), 300), _wall((0, 0), (0, 6), 300)]) + corner
    scan = np.vstack([_wall((0, 0), (3, 0), 80), _wall((0, 0), (0, 3), 80)]) + corner
    cov = _surface(reference, scan, np.array([0.0, 0.0, 0.0]))
    # under a fifth of a table cell each way, and a third of the grid's heading step (about 1.1° here)
    assert math.sqrt(cov[0, 0]) < 0.2 * RESOLUTION_M and math.sqrt(cov[1, 1]) < 0.2 * RESOLUTION_M
    assert math.sqrt(cov[2, 2]) < math.radians(0.4)


def test_fewer_independent_points_widen_the_surface() -> None:
    """``point_share``: each point counted as less than an independent observation, the spread grows."""
    corner = np.array([0.512, 0.371])
    reference = np.vstack([_wall((0, 0), (6, 0), 300), _wall((0, 0), (0, 6), 300)]) + corner
    scan = np.vstack([_wall((0, 0), (3, 0), 80), _wall((0, 0), (0, 3), 80)]) + corner
    table = LikelihoodTable(reference, RESOLUTION_M, SIGMA_M, 0)
    stds = [math.sqrt(surface_covariance(table, scan, np.zeros(3), SIGMA_M, point_share=s).covariance[0, 0])
            for s in (1.0, 0.1, 0.02)]
    assert stds[0] < stds[1] < stds[2] < 2 * RESOLUTION_M


def test_the_cap_is_the_sum_of_the_covariances_and_keeps_a_singular_information() -> None:
    """``(Ω⁻¹ + Σ)⁻¹``, also where ICP's information holds nothing along a corridor."""
    omega = np.diag([4e4, 9e4, 1e5])
    sigma = np.diag([1e-4, 4e-4, 1e-6])
    assert np.allclose(capped_information(omega, sigma), np.linalg.inv(np.linalg.inv(omega) + sigma))
    corridor = np.diag([0.0, 9e4, 1e5])
    capped = capped_information(corridor, sigma)
    assert abs(capped[0, 0]) < 1e-6  # nothing along the corridor stays nothing
    assert np.isclose(capped[1, 1], 1.0 / (1.0 / 9e4 + 4e-4))
    assert np.allclose(capped_information(omega, np.zeros((3, 3))), omega, rtol=1e-6)


REAL = CorrelativeParams(resolution_m=RESOLUTION_M, sigma_m=SIGMA_M, max_range_m=10.0, max_points=250, levels=0)


def test_on_real_intel_scans_the_capped_information_is_closer_to_the_truth(intel_log_path: Path) -> None:
    """Consecutive Intel scans, GMapping's relative poses the truth: ICP's Hessian (the filter's half of it)
    is too sure of its match, and adding the surface's covariance brings the error's chi² towards its
    degrees of freedom."""
    lasers = read_carmen(intel_log_path).lasers
    chi2_icp, chi2_capped = [], []
    for k in np.linspace(30, len(lasers) - 2, 30).astype(int):
        ref, new = lasers[k], lasers[k + 1]
        ref_xy = transform(ref.pose, ref.points_xy(30.0))
        target = Target(ref_xy, viewpoints_xy=ref.pose[:2], normal_radius_m=0.3)
        start = new.pose + np.array([0.05, -0.05, 0.02])
        match = match_scan(target, new.points_xy(30.0), start, IcpParams(max_correspondence_m=0.3))
        table = LikelihoodTable(ref_xy, REAL.resolution_m, REAL.sigma_m, 0, crop=(match.pose[:2], 11.0))
        src = select_points(new.points_xy(30.0), None, REAL)
        surface = surface_covariance(table, src, match.pose, REAL.sigma_m)
        error = match.pose - new.pose
        error[2] = math.remainder(float(error[2]), math.tau)
        information = 0.5 * match.information
        chi2_icp.append(error @ information @ error)
        chi2_capped.append(error @ capped_information(information, surface.covariance) @ error)
    # measured: medians 185 and 30 (a calibrated information gives about 2.4, GMapping's own error aside)
    assert np.median(chi2_capped) < 0.5 * np.median(chi2_icp)
    assert np.all(np.array(chi2_capped) <= np.array(chi2_icp) + 1e-9)
