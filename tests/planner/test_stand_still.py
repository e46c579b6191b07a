"""The pilot's watch on a robot standing still with a goal (:class:`mazebot.planner.pilot.StandStill`)."""

from __future__ import annotations

import itertools
import math

from mazebot.planner.pilot import BACKOFF_M, WRIGGLE_FACTOR, StandStill


def test_counts_revolutions_not_ticks() -> None:
    """Planner ticks without a new revolution do not count: the clock is what the lidar saw."""
    still = StandStill(limit_revolutions=3)
    pose = (1.0, 2.0, 0.5)
    assert still.observe(pose, 1) == 0  # the first tick only marks where it stands
    reached = [still.observe(pose, scan_id) for scan_id in (1, 1, 2, 2, 3, 3, 3)]
    assert reached == [0, 0, 0, 0, 0, 0, 0]
    assert still.observe(pose, 4) == 3  # the third new revolution stood
    assert still.observe(pose, 5) == 0  # and the count starts again


def test_moving_or_turning_starts_the_count_again() -> None:
    still = StandStill(limit_revolutions=2)
    still.observe((0.0, 0.0, 0.0), 1)
    still.observe((0.0, 0.0, 0.0), 2)
    assert still.observe((0.05, 0.0, 0.0), 3) == 0  # moved 5 cm: a new mark
    assert still.observe((0.05, 0.0, 0.3), 4) == 0  # turned 0.3 rad: a new mark
    assert still.observe((0.05, 0.0, 0.3), 5) == 0
    assert still.observe((0.05, 0.01, 0.3), 6) == 2  # 1 cm of estimate jitter is standing


def test_the_backoff_follows_the_track_it_drove() -> None:
    """Back along the points it passed (known free), about BACKOFF_M of them, newest first."""
    still = StandStill()
    track = [(0.03 * i, 0.0) for i in range(10)] + [(0.27, 0.03 * i) for i in range(1, 6)]  # east, then north
    for scan_id, (x, y) in enumerate(track):
        still.observe((x, y, 0.0), scan_id)
    here = track[-1]
    path = still.backoff_path(here)
    assert path[0] == here
    assert all(p in track for p in path[1:])
    length = sum(math.dist(a, b) for a, b in itertools.pairwise(path))
    assert BACKOFF_M <= length < BACKOFF_M + 0.04
    ys = [p[1] for p in path]
    assert ys == sorted(ys, reverse=True)  # back down the northward leg first


def test_no_track_no_backoff() -> None:
    still = StandStill()
    still.observe((0.0, 0.0, 0.0), 1)
    assert still.backoff_path((0.0, 0.0)) == []


def test_wriggling_on_a_spot_is_standing_still_too() -> None:
    """Turned and shuffled 5 cm back and forth each revolution (the local planner's recoveries):
    each move starts the stand-still count again, but the robot never left its spot."""
    still = StandStill(limit_revolutions=3)
    shuffle = itertools.cycle([(0.0, 0.0, 0.0), (0.05, 0.0, 0.6), (0.02, 0.04, -0.6)])
    reached = [still.observe(next(shuffle), scan_id) for scan_id in range(1, 1 + WRIGGLE_FACTOR * 3)]
    assert reached[:-1] == [0] * (WRIGGLE_FACTOR * 3 - 1) and reached[-1] == WRIGGLE_FACTOR * 3, reached
    assert still.wriggled


def test_driving_on_slowly_is_no_wriggling() -> None:
    """4 cm a revolution, turning a little each time: the robot leaves its spot, nothing is said."""
    still = StandStill(limit_revolutions=3)
    reached = [still.observe((0.04 * k, 0.0, 0.2 * (k % 2)), k) for k in range(1, 60)]
    assert not any(reached), reached
