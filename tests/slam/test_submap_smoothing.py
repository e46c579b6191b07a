"""The submap's points smoothed onto their local lines (``[slam.normals] smooth``) on a sparse real log.

The Seattle log (a SICK scan every ~0.9 m) starts at the east end of a 40 m corridor that the
robot drives west along, swinging its heading by up to 30° between scans. Before the first loop
closure (scan 113) the map's heading there is the sequential matches' alone, each against a
submap of the last ten keyframes.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mazebot.config import load_config
from mazebot.geometry import compose, relative_pose, wrap_angle
from mazebot.slam.carmen import read_carmen
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.slam import Slam, SlamParams
from mazebot.slam.slam_cli import laser_log_params, noisy_odometry, slam_clock
from tests.data_paths import carmen_log

#: the first corridor's scans, westward, before any loop closure
CORRIDOR_SCANS = 65


def corridor_turn_deg(smooth: bool) -> float:
    """How far the online heading turns off the corrected poses' along the first corridor.

    The mean heading error over its last ten scans minus that over its first ten, in degrees,
    with ``--odom-noise 0.05,0.05`` seed 1 as ``slam run`` makes it.
    """
    lasers = read_carmen(carmen_log("seattle-corrected.log.gz")).lasers[:CORRIDOR_SCANS]
    reference = np.array([r.pose for r in lasers])
    odometry = noisy_odometry(reference, 0.05, 0.05, np.random.default_rng(1))
    odometry = compose(reference[0], relative_pose(odometry[0], odometry))  # as run_carmen: from the first pose
    config = load_config(None)
    params = laser_log_params(SlamParams.from_config(config.slam, config.lidar))
    params = replace(params, normals=replace(params.normals, smooth=smooth))
    slam = Slam(params, initial_pose=np.zeros(3))
    history = OdometryHistory(horizon_s=1e12)
    clock = slam_clock(np.array([r.timestamp_s for r in lasers]))
    error_deg = np.zeros(len(lasers))
    for k, record in enumerate(lasers):
        history.append(clock[k], *odometry[k])
        scan = record.to_scan()
        update = slam.update(replace(scan, time_s=np.full(len(scan), clock[k])), history)
        error_deg[k] = np.degrees(wrap_angle(float(update.pose[2] - reference[k, 2])))
    assert not slam.closures  # the sequential matches alone
    return float(error_deg[-10:].mean() - error_deg[:10].mean())


@pytest.mark.slow
def test_the_smoothed_submap_turns_the_first_corridor() -> None:
    """Smoothed onto lines fitted over the logs' 0.3 m neighbourhoods, the submap turns every sequential
    match a few hundredths of a degree the same way, and the corridor's heading walks off by 1.5°
    over its 35 m (measured 1.49°); against the points as the SICK measured them it walks off by
    0.58°: the drift that leaves the finished map's first corridor bent."""
    smoothed = corridor_turn_deg(smooth=True)
    measured = corridor_turn_deg(smooth=False)
    assert smoothed > 1.2
    assert abs(measured) < 0.8
    assert abs(measured) < 0.5 * smoothed
