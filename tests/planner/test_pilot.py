"""The pilot's own bookkeeping around the DWA: what it hands the local planner as obstacles."""

from __future__ import annotations

import numpy as np

from mazebot.config import Config
from mazebot.io.scan import Scan
from mazebot.planner.pilot import Pilot, PilotParams
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.odometry import OdometryPose
from mazebot.state import SharedState

REVOLUTION_S = 0.18  # an A1's revolution


def _revolution(state: SharedState, end_s: float, x_m: float, post_ahead_m: float | None) -> None:
    """The robot at ``(x_m, 0)`` heading along x by the odometry; one revolution whose only return
    is a post straight ahead at ``post_ahead_m`` from the lidar (None: nothing within its reach)."""
    history = state.odometry_history
    assert history is not None
    history.append(end_s - REVOLUTION_S, x_m, 0.0, 0.0)
    history.append(end_s, x_m, 0.0, 0.0)
    state.odometry = OdometryPose(x_m, 0.0, 0.0)
    angle = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    rng = np.zeros(360)
    if post_ahead_m is not None:
        rng[180] = post_ahead_m  # angle 0
    state.latest_scan = Scan(angle, rng, np.full(360, 40, dtype=np.uint8),
                             np.linspace(end_s - REVOLUTION_S, end_s, 360), rng > 0)


def test_returns_remembered_in_the_blind_zone_are_forgotten_once_slam_holds_a_revolution_back() -> None:
    # the blind-zone memory is kept in the odometry frame; a slipping tyre moves that frame under
    # it (the fault suite's slip left copies of two posts around a robot standing between them,
    # and it stood for seconds with no way forward): once SLAM holds a revolution back for a bad
    # odometry, what the memory holds is no longer where it says
    pilot = Pilot(PilotParams.from_config(Config()))
    mount_x_m = pilot.params.lidar.mount_xy_m[0]
    state = SharedState()
    state.odometry_history = OdometryHistory(3.0)
    post_x_m = 0.3 + mount_x_m  # in the odometry frame: 0.3 m ahead of the lidar at the start
    _revolution(state, 1.0, 0.0, post_x_m - mount_x_m)  # seen at 0.30 m
    pilot._scan_points(state)
    _revolution(state, 1.2, 0.1, post_x_m - 0.1 - mount_x_m)  # seen at 0.20 m
    pilot._scan_points(state)
    _revolution(state, 1.4, 0.18, None)  # 0.12 m: inside the minimum range, the scan shows nothing
    ahead = pilot._scan_points(state)
    np.testing.assert_allclose(ahead, [[post_x_m - 0.18, 0.0]], atol=1e-9)  # remembered
    assert len(state.blind_zone_points) == 1

    state.slam.held_back += 1  # SLAM: that revolution only localized, its odometry was bad
    _revolution(state, 1.6, 0.18, None)
    assert pilot._scan_points(state).shape == (0, 2)
    assert len(state.blind_zone_points) == 0
    _revolution(state, 1.8, 0.18, None)  # the odometry trusted again: the memory starts again, empty
    assert pilot._scan_points(state).shape == (0, 2)
