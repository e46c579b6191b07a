"""Stretches of rewritten laser logs that the SLAM lost: a turn inside one step at half the scan rate, a
short-range laser's wrong match after a blind stretch; each judged against the log's corrected poses.

The logs are rewritten in memory by :mod:`mazebot.slam.log_degrade` as another robot would have given
them (``bench/degrade_log.py`` writes the same to a file).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mazebot.config import load_config
from mazebot.geometry import relative_pose, wrap_angle
from mazebot.slam.carmen import LaserRecord, one_laser, read_carmen
from mazebot.slam.log_degrade import URG_04LX_MAX_RANGE_M, fewer_scans, no_echo_range_m, short_range
from mazebot.slam.slam import Slam, SlamParams
from mazebot.slam.slam_cli import from_first_pose, laser_log_params, log_odometry, log_updates
from tests.data_paths import carmen_log


def _laser_log_params(any_heading: bool = False, match_residual_ratio: float = 0.0) -> SlamParams:
    config = load_config(None)
    params = laser_log_params(SlamParams.from_config(config.slam, config.lidar))
    return replace(params, failed_search_any_heading=any_heading, match_residual_ratio=match_residual_ratio)


def _online_errors(
    params: SlamParams, lasers: list[LaserRecord], odometry: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each scan's online pose against its corrected pose: position error (m), heading error (deg)."""
    reference = np.array([r.pose for r in lasers])
    odometry = from_first_pose(odometry, reference)
    slam = Slam(params, initial_pose=np.zeros(3))
    poses = np.array([u.pose for u in log_updates(slam, lasers, odometry)])
    heading_deg = np.degrees(np.abs(wrap_angle(relative_pose(reference, poses)[:, 2])))
    return np.hypot(*(poses[:, :2] - reference[:, :2]).T), heading_deg


@pytest.mark.slow
def test_a_turn_inside_one_step_at_half_the_scan_rate_is_found_over_every_heading() -> None:
    """Seattle at every second scan, its first 20: the 80° turn no odometry reading saw (the log's scan 27)
    lies inside the step to the 14th kept scan, whose odometry says 21°. ICP from that prediction fails, the
    correlative window of ±30° holds nothing; searched over every heading, the scan is matched and the scans
    after it keep their heading. Without that search the step's 21° is taken, and the next scans, matched
    against the keyframe left there, carry the 80° on."""
    log = one_laser(read_carmen(carmen_log("seattle-corrected.log.gz")))
    lasers, odometry = fewer_scans(log.lasers[:40], log_odometry(log)[:40], 2)
    position_m, heading_deg = _online_errors(_laser_log_params(any_heading=True), lasers, odometry)
    assert heading_deg[14:].max() < 5.0
    assert position_m[14:].max() < 0.5


@pytest.mark.slow
def test_a_turned_look_alike_found_over_every_heading_is_refused_by_its_residual() -> None:
    """Seattle as logged, scans 0-100: at scan 97 the scan sees a room its submap never saw and ICP from the
    (right) prediction fails; the search over every heading then finds an alignment 87° off whose inlier ratio
    passes but whose residual (138 mm) is ten times the run's recent median. Refused, the odometry's step
    stands and the scans after it keep their heading."""
    log = one_laser(read_carmen(carmen_log("seattle-corrected.log.gz")))
    scans = 101
    params = _laser_log_params(any_heading=True)
    _, heading_deg = _online_errors(params, list(log.lasers[:scans]), log_odometry(log)[:scans])
    assert heading_deg[28:].max() < 5.0


@pytest.mark.slow
def test_a_match_far_worse_than_the_runs_own_is_refused_where_asked() -> None:
    """Freiburg 101 through a 4 m laser (a Hokuyo URG-04LX), scans 0-175: after three scans that see nothing
    within 4 m, ICP from the prediction at scan 154 converges with a 189 mm residual, twelve times the run's
    recent median; taken, the next matches build on it and from scan 157 on the trajectory is turned 27° and
    metres off. With ``match_residual_ratio`` 4 it is refused, the correlative search finds the right match
    (18 mm) and the stretch holds."""
    log = one_laser(read_carmen(carmen_log("freiburg-101-corrected.log.gz")))
    scans = 176
    code = no_echo_range_m(log.lasers)
    lasers = [short_range(r, URG_04LX_MAX_RANGE_M, code) for r in log.lasers[:scans]]
    params = _laser_log_params(match_residual_ratio=4.0)
    position_m, heading_deg = _online_errors(params, lasers, log_odometry(log)[:scans])
    assert heading_deg[150:].max() < 5.0
    assert position_m[150:].max() < 0.5

