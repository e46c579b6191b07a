"""When SLAM paints revolutions again after the wheel odometry was known bad."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.io.scan import Scan
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.relocalize import LocalizationGuard
from mazebot.slam.slam import Slam, SlamParams
from mazebot.state import Fault, SharedState
from mazebot.tasks import slam_task
from mazebot.tasks.slam_task import (
    POSE_CONFIRMED_AFTER,
    REST_AGREE,
    TRUSTED_AFTER,
    OdometryTrust,
    RestMatches,
    _at_rest,
)
from tests.tasks.test_slam_task import _static_scan


def verdicts(trust: OdometryTrust, state: SharedState, count: int, *, matched: bool, at_rest: bool) -> list[bool]:
    return [trust.observe(state, False, matched, at_rest) for _ in range(count)]


def test_after_a_slip_revolutions_at_rest_bring_the_painting_back_matched_or_not() -> None:
    """A slip, then a robot standing where ICP fits nothing (the map lacks what it sees):
    without the revolutions at rest counting, no revolution would ever be painted again."""
    state = SharedState()
    trust = OdometryTrust()
    assert not trust.observe(state, True, True)  # the slip
    assert not any(verdicts(trust, state, 50, matched=False, at_rest=False))  # driving, unmatched: no proof
    held = verdicts(trust, state, TRUSTED_AFTER, matched=False, at_rest=True)
    assert held == [False] * (TRUSTED_AFTER - 1) + [True]


def test_after_a_re_localization_or_an_odometry_fault_rest_proves_nothing() -> None:
    state = SharedState()
    trust = OdometryTrust()
    trust.distrust()  # the robot was found again: its pose itself is in doubt
    assert not any(verdicts(trust, state, 3 * TRUSTED_AFTER, matched=False, at_rest=True))
    assert verdicts(trust, state, TRUSTED_AFTER, matched=True, at_rest=False)[-1]
    state.faults.append(Fault("encoders", "the left encoder counts nothing", 0.0))
    assert not trust.observe(state, False, True, True)
    assert not any(verdicts(trust, state, 3 * TRUSTED_AFTER, matched=False, at_rest=True))


def test_after_a_re_localization_the_matches_that_confirm_the_pose_let_rest_bring_the_painting_back() -> None:
    """A kidnapped robot set down where the map has little: found, matched twice, then driven into
    walls the map does not hold, where nothing matches, and stopped. Its pose is right; without
    rest counting once the matches confirmed it, no revolution would ever be painted again."""
    state = SharedState()
    trust = OdometryTrust()
    trust.distrust()  # found again
    assert not any(verdicts(trust, state, POSE_CONFIRMED_AFTER, matched=True, at_rest=False))
    assert not any(verdicts(trust, state, 30, matched=False, at_rest=False))  # driving, unmatched: no proof
    held = verdicts(trust, state, TRUSTED_AFTER - POSE_CONFIRMED_AFTER, matched=False, at_rest=True)
    assert held == [False] * (TRUSTED_AFTER - POSE_CONFIRMED_AFTER - 1) + [True]
    # one match only is not enough: it could be a look-alike
    trust = OdometryTrust()
    trust.distrust()
    assert not any(verdicts(trust, state, POSE_CONFIRMED_AFTER - 1, matched=True, at_rest=False))
    assert not any(verdicts(trust, state, 3 * TRUSTED_AFTER, matched=False, at_rest=True))


def test_a_revolution_is_at_rest_when_the_odometry_stood_still_through_it() -> None:
    history = OdometryHistory(horizon_s=5.0)
    for k in range(100):  # still until 1 s, then 0.1 m/s ahead
        t = 0.02 * k
        history.append(t, max(0.0, t - 1.0) * 0.1, 0.0, 0.0)
    times = np.linspace(0.2, 0.9, 360)
    scan = Scan(np.linspace(0, 2 * np.pi, 360), np.ones(360), np.zeros(360, np.uint8), times, np.ones(360, bool))
    assert _at_rest(history, scan)
    moving = Scan(scan.angle_rad, scan.range_m, scan.quality, times + 0.9, scan.valid)
    assert not _at_rest(history, moving)


def test_a_revolution_at_rest_is_no_slip_and_ends_the_turns_that_add_up() -> None:
    """On a quota run the first revolutions of a stop were called slips by the turn before them."""
    pose, turned = np.zeros(3), np.array([0.0, 0.0, math.radians(0.9)])
    stopped = np.array([0.001, 0.0, math.radians(0.3)])
    for at_rest in (False, True):
        guard = LocalizationGuard()
        for _ in range(2):  # a turn: ICP corrects the heading by 0.9° a revolution, below the limits
            assert guard.slipped(pose, turned) is None
        # 2.1° in three revolutions: a slip in motion, none at rest
        assert (guard.slipped(pose, stopped, at_rest=at_rest) is None) == at_rest
    assert guard.slipped(pose, turned) is None  # and the sum began again
    assert guard.slipped(pose, turned) is None


def test_at_rest_a_disputed_match_is_not_painted_and_starts_the_count_again() -> None:
    state = SharedState()
    trust = OdometryTrust()
    assert verdicts(trust, state, 3, matched=False, at_rest=True) == [True] * 3  # trusted from the start
    assert not trust.observe(state, False, False, True, disputed=True)
    assert verdicts(trust, state, TRUSTED_AFTER, matched=True, at_rest=True)[-1]


def test_rest_matches_take_a_pose_once_enough_agree_in_a_row_at_rest() -> None:
    rest = RestMatches()
    pose = np.array([1.0, 2.0, 0.3])
    assert rest.observe(True, pose) is None
    assert rest.observe(False, pose) is None  # it moved: start again
    assert rest.observe(True, pose) is None
    assert rest.observe(True, pose + np.array([0.05, 0.0, 0.0])) is None  # elsewhere: start again from there
    assert rest.observe(True, None) is None  # matched (or no good match): no dispute
    near = [pose + np.array([0.002 * k, 0.0, 0.001 * k]) for k in range(REST_AGREE)]
    for other in near[:-1]:
        assert rest.observe(True, other) is None
    taken = rest.observe(True, near[-1])
    assert taken is not None and np.allclose(taken, np.mean(near, axis=0))
    assert rest.observe(True, pose) is None  # taken: the next dispute needs its own agreement


@pytest.mark.parametrize("error_deg", [1.7, 2.9])
async def test_a_filter_a_few_degrees_off_at_rest_is_set_right_by_the_revolutions_and_the_map_painted_again(
        error_deg: float) -> None:
    """The filter gates matches by its covariance, which nothing grows at rest: a filter that
    stopped a few degrees off refused every revolution for as long as the robot stood (each
    one a "slip", none painted: main held back 20 of 20), on a published pose that stayed wrong."""
    config = Config()
    state = SharedState()
    history = OdometryHistory(horizon_s=1000.0)
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(1000.0, 0.0, 0.0, 0.0)  # the wheels stand still all along
    state.odometry_history = history
    slam = Slam(SlamParams.from_config(config.slam, config.lidar), background=False, record_trajectory=False)
    task = slam_task.SlamTask(state, RealClock(), slam)
    end_s = 1.0
    for _ in range(25):  # the anchor: the map of the standing robot
        assert await task.on_scan(_static_scan(end_s, np.zeros(3)))
        end_s += 0.2
    assert task.trust.held_back == 0
    slam.ekf.mean[2] += math.radians(error_deg)  # a turn's late edges left the filter off, confident
    held = []
    for _ in range(20):
        before = task.trust.held_back
        assert await task.on_scan(_static_scan(end_s, np.zeros(3)))
        held.append(task.trust.held_back > before)
        end_s += 0.2
    # the disputed revolutions are not painted; then the pose is taken and TRUSTED_AFTER are matched
    assert held == [True] * (REST_AGREE + TRUSTED_AFTER - 1) + [False] * (20 - REST_AGREE - TRUSTED_AFTER + 1)
    assert abs(math.degrees(slam.ekf.mean[2])) < 0.2
    assert abs(math.degrees(state.map_from_odom[2])) < 0.2
    assert any("SLAM takes their pose" in e.message for e in state.events)


async def test_each_move_of_the_odometry_frame_is_logged_with_the_revolution_it_came_from() -> None:
    """``state.odometry_fixes``: one fix per revolution SLAM took in, named by the revolution's end
    time; those held back with their match refused not vouched for; the pose taken at rest a fix
    of no revolution; each fix starting where the one before ended, the last where SLAM is."""
    config = Config()
    state = SharedState()
    history = OdometryHistory(horizon_s=1000.0)
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(1000.0, 0.0, 0.0, 0.0)
    state.odometry_history = history
    slam = Slam(SlamParams.from_config(config.slam, config.lidar), background=False, record_trajectory=False)
    task = slam_task.SlamTask(state, RealClock(), slam)
    ends = [1.0 + 0.2 * k for k in range(25 + 10)]
    for end_s in ends[:25]:
        assert await task.on_scan(_static_scan(end_s, np.zeros(3)))
    slam.ekf.mean[2] += math.radians(2.9)  # the filter off at rest: its matches refused (held back)
    for end_s in ends[25:]:
        assert await task.on_scan(_static_scan(end_s, np.zeros(3)))
    fixes = list(state.odometry_fixes)
    assert [f.serial for f in fixes] == list(range(1, len(fixes) + 1))
    assert [f.revolution_end_s for f in fixes if f.revolution_end_s is not None] == ends
    assert all(f.vouched for f in fixes[:25])
    refused = [f for f in fixes[25:] if f.revolution_end_s is not None][:REST_AGREE]
    assert not any(f.vouched for f in refused)  # held back, matched by nothing but the odometry
    assert sum(f.revolution_end_s is None for f in fixes) == 1  # the pose taken at rest
    assert all(a.after == b.before for a, b in itertools.pairwise(fixes))
    assert fixes[-1].after == state.map_from_odom


def test_after_a_slip_a_robot_that_matches_nothing_in_motion_is_asked_to_stand_until_rest_heals_the_trust() -> None:
    """A slip in a turn, a few matched revolutions, then the robot drives past the last keyframe's
    walls: ICP fits nothing, no revolution in motion can earn the trust back, and without standing
    still the filter dead-reckons until the guard calls the robot lost. ``rest_wanted`` asks for
    the rest that heals it, and lets go once it has."""
    state = SharedState()
    trust = OdometryTrust()
    assert not trust.observe(state, True, True)  # the slip
    assert not any(verdicts(trust, state, TRUSTED_AFTER - 1, matched=True, at_rest=False))
    assert not trust.rest_wanted  # matching in motion: the trust comes back by itself
    assert not trust.observe(state, False, False)  # driven past the submap's walls: nothing fits
    assert trust.rest_wanted
    assert not any(verdicts(trust, state, 3, matched=False, at_rest=False))  # still driving: still wanted
    assert trust.rest_wanted
    assert trust.rest_wanted
    assert verdicts(trust, state, 1, matched=False, at_rest=True) == [True]  # one short of it: one revolution at rest
    assert not trust.rest_wanted  # trusted again: painted at rest, the robot drives on


def test_rest_is_not_wanted_where_it_would_not_heal_the_trust() -> None:
    """After a re-localization rest proves nothing until matches confirm the pose: standing still
    there would stand for ever, so rest is not asked for (nor after the guard lost the robot)."""
    state = SharedState()
    trust = OdometryTrust()
    trust.distrust()
    assert not any(verdicts(trust, state, 10, matched=False, at_rest=False))
    assert not trust.rest_wanted
    assert not trust.observe(state, True, True)  # a slip: rest heals
    trust.observe(state, False, False)
    assert trust.rest_wanted
    trust.distrust()
    assert not trust.rest_wanted
