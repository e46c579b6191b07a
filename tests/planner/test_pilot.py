"""The pilot's own bookkeeping around the DWA: what it hands the local planner as obstacles."""

from __future__ import annotations

import numpy as np
import pytest

from mazebot.config import Config
from mazebot.geometry import compose, inverse
from mazebot.io.scan import Scan
from mazebot.planner import pilot as pilot_module
from mazebot.planner.pilot import Pilot, PilotParams, StandStill
from mazebot.planner.safety import CollisionGuard, with_remembered
from mazebot.planner.wheel_control import DriveMode
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.odometry import OdometryPose
from mazebot.state import ODOMETRY_FIXES_KEPT, OdometryFix, RunState, SharedState

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


def _slam_fix(state: SharedState, end_s: float, slam_pose: tuple[float, float, float], vouched: bool = True) -> None:
    """SLAM's update of the revolution that ended at ``end_s`` as the SLAM task publishes it: its
    pose ``slam_pose`` (map frame) gives ``map_from_odom``, and the move goes into ``odometry_fixes``."""
    history = state.odometry_history
    assert history is not None
    after = tuple(float(v) for v in compose(slam_pose, inverse(history.pose_at(end_s))))
    serial = state.odometry_fixes[-1].serial + 1 if state.odometry_fixes else 1
    state.odometry_fixes.append(OdometryFix(serial, end_s, state.map_from_odom, after, vouched))  # type: ignore[arg-type]
    state.map_from_odom = after  # type: ignore[assignment]


def test_a_revolution_that_takes_a_dropped_ones_address_is_read_as_new(monkeypatch: pytest.MonkeyPatch) -> None:
    # CPython may give a new revolution the address, so the id(), of one already dropped. Every
    # object given one id here is that reuse at its worst: a post 0.5 m ahead in one revolution,
    # nothing in the next, the robot standing where it was. The planner must see the newer
    # revolution, and the stand-still watch must count it
    monkeypatch.setattr(pilot_module, "id", lambda obj: 1, raising=False)
    pilot = Pilot(PilotParams.from_config(Config()))
    state = SharedState()
    state.odometry_history = OdometryHistory(3.0)
    _revolution(state, 1.0, 0.0, 0.5)
    assert pilot._scan_points(state).shape == (1, 2)
    _revolution(state, 1.2, 0.0, None)
    assert pilot._scan_points(state).shape == (0, 2)

    still = StandStill(limit_revolutions=3)
    scans = []
    for end_s in (1.4, 1.6, 1.8, 2.0):
        _revolution(state, end_s, 0.0, None)
        scans.append(state.latest_scan)
    counted = [still.observe((0.0, 0.0, 0.0), scan) for scan in scans]
    assert counted == [0, 0, 0, 3]  # the first marks the place; three new revolutions stood


def test_a_leg_in_the_blind_zone_seen_before_slam_holds_revolutions_back_is_still_avoided_after_them() -> None:
    # a post seen at 0.30 and 0.20 m, then driven to 0.12 m: inside the lidar's minimum range. SLAM
    # then holds revolutions back (a brief slip: the odometry said 1 cm more than the robot drove,
    # which SLAM's match takes out; then one whose match it refused): the post must stay known,
    # where it is, to the planner and to the control loop's guard
    pilot = Pilot(PilotParams.from_config(Config()))
    mount_x_m = pilot.params.lidar.mount_xy_m[0]
    state = SharedState()
    state.odometry_history = OdometryHistory(3.0)
    post_x_m = 0.3 + mount_x_m  # in the map: 0.3 m ahead of the lidar at the start
    for end_s, x_m, seen in ((1.0, 0.0, True), (1.2, 0.1, True), (1.4, 0.18, False)):
        _revolution(state, end_s, x_m, post_x_m - x_m - mount_x_m if seen else None)
        pilot._scan_points(state)
        _slam_fix(state, end_s, (x_m, 0.0, 0.0))  # trusted, painted
    ahead = pilot._scan_points(state)
    np.testing.assert_allclose(ahead, [[post_x_m - 0.18, 0.0]], atol=1e-9)  # remembered

    _revolution(state, 1.6, 0.19, None)  # the odometry says 0.19 m, the robot is at 0.18 m
    pilot._scan_points(state)
    state.slam.held_back += 1
    _slam_fix(state, 1.6, (0.18, 0.0, 0.0))  # held back, matched
    _revolution(state, 1.8, 0.19, None)
    pilot._scan_points(state)
    state.slam.held_back += 1
    _slam_fix(state, 1.8, (0.18, 0.0, 0.0), vouched=False)  # held back, its match refused
    ahead = pilot._scan_points(state)
    np.testing.assert_allclose(ahead, [[post_x_m - 0.18, 0.0]], atol=1e-9)  # still 0.12 m ahead of the centre
    # the guard in the control loop: the scan shows nothing, the memory's copy stops a drive at the post
    odo = state.odometry
    assert odo is not None and state.blind_zone_points is not None
    guard_points = with_remembered(np.zeros((0, 2)), state.blind_zone_points, (odo.x_m, odo.y_m, odo.theta_rad))
    assert CollisionGuard(footprint_radius_m=pilot.params.robot.footprint_radius_m).check(guard_points, 0.2, 0.0).stop


def test_a_leg_in_the_blind_zone_is_kept_through_a_pause_longer_than_slams_fixes_are_kept() -> None:
    # a post driven to 0.12 m from the centre (inside the lidar's minimum range); the user then
    # stops the robot for longer than SLAM's fixes are kept, and SLAM goes on fixing the odometry
    # frame every revolution: when the robot starts again, the post must still be known
    pilot = Pilot(PilotParams.from_config(Config()))
    mount_x_m = pilot.params.lidar.mount_xy_m[0]
    state = SharedState()
    state.odometry_history = OdometryHistory(3.0)
    state.run_state = RunState.EXPLORING
    post_x_m = 0.3 + mount_x_m
    for end_s, x_m, seen in ((1.0, 0.0, True), (1.2, 0.1, True), (1.4, 0.18, False)):
        _revolution(state, end_s, x_m, post_x_m - x_m - mount_x_m if seen else None)
        pilot._scan_points(state)
        _slam_fix(state, end_s, (x_m, 0.0, 0.0))
    np.testing.assert_allclose(pilot._scan_points(state), [[post_x_m - 0.18, 0.0]], atol=1e-9)

    state.run_state = RunState.STOPPED
    for k in range(ODOMETRY_FIXES_KEPT + 44):  # one planner tick per revolution SLAM fixes at rest
        end_s = 1.6 + 0.2 * k
        state.odometry_history.append(end_s, 0.18, 0.0, 0.0)
        _slam_fix(state, end_s, (0.18, 0.0, 0.0))
        for _ in pilot.plan_steps(state, end_s):
            pass
    state.run_state = RunState.EXPLORING
    _revolution(state, 1.6 + 0.2 * (ODOMETRY_FIXES_KEPT + 44), 0.18, None)
    np.testing.assert_allclose(pilot._scan_points(state), [[post_x_m - 0.18, 0.0]], atol=1e-9)


def test_the_pilot_stands_still_while_slam_wants_rest_to_trust_the_wheels_again() -> None:
    """SLAM holds its revolutions back since a slip and fits none in motion: the pilot stops the
    wheels (revolutions at rest heal the trust) and drives on once SLAM no longer asks for rest."""
    config = Config()
    pilot = Pilot(PilotParams.from_config(config))
    state = SharedState()
    state.run_state = RunState.EXPLORING
    state.started_at_s = 0.0
    state.slam.anchored = True
    state.map = OccupancyGrid()
    state.slam.rest_wanted = True
    pilot.tick(state, 1.0)
    assert state.motion_command is not None
    assert state.motion_command.mode == DriveMode.STOP.value
    assert (state.motion_command.v_mps, state.motion_command.w_radps) == (0.0, 0.0)
    assert "after a slip" in state.planner_status
    state.slam.rest_wanted = False
    pilot.tick(state, 1.2)
    assert "after a slip" not in state.planner_status
