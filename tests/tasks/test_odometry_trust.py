"""When SLAM paints revolutions again after the wheel odometry was known bad."""

from __future__ import annotations

import numpy as np

from mazebot.io.scan import Scan
from mazebot.slam.ekf import OdometryHistory
from mazebot.state import Fault, SharedState
from mazebot.tasks.slam_task import TRUSTED_AFTER, OdometryTrust, _at_rest


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
