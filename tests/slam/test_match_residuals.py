"""The recent sequential matches' residuals and the doubt about a match that stands far out of them."""

from __future__ import annotations

import pytest

from mazebot.slam.match_residuals import MIN_RESIDUALS, MatchResiduals


def test_a_residual_four_times_the_recent_median_is_in_doubt() -> None:
    residuals = MatchResiduals(ratio=4.0, scans=50)
    for k in range(30):
        residuals.add(0.015 + 0.001 * (k % 5))  # median 17 mm
    assert residuals.limit_m() == pytest.approx(4.0 * 0.017)
    assert residuals.in_doubt(0.2)  # a match 30° off on the Intel log
    assert not residuals.in_doubt(0.06)


def test_no_doubt_before_enough_matches_nor_when_off() -> None:
    residuals = MatchResiduals(ratio=4.0, scans=50)
    for _ in range(MIN_RESIDUALS - 1):
        residuals.add(0.01)
    assert not residuals.in_doubt(1.0)
    residuals.add(0.01)
    assert residuals.in_doubt(1.0)
    off = MatchResiduals(ratio=0.0, scans=50)
    for _ in range(3 * MIN_RESIDUALS):
        off.add(0.01)
    assert not off.in_doubt(1.0)


def test_only_the_recent_matches_count() -> None:
    """A building's residuals change from room to room: the median follows the last ``scans`` matches."""
    residuals = MatchResiduals(ratio=4.0, scans=20)
    for _ in range(20):
        residuals.add(0.05)  # a sparse, cluttered stretch
    assert not residuals.in_doubt(0.15)
    for _ in range(20):
        residuals.add(0.01)  # a clean corridor
    assert residuals.in_doubt(0.15)
