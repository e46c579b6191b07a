"""What a loop-closure submap could have seen: inside its keyframes' beams, not behind their walls or their backs."""

from __future__ import annotations

import math

import numpy as np

from mazebot.slam.overlap import ObservedArea


def _half_fan(range_m: float, beams: int = 181) -> np.ndarray:
    """A 180° laser (right to left through ahead), every beam ending at ``range_m``, in the robot frame."""
    a = np.linspace(-math.pi / 2, math.pi / 2, beams)
    return np.column_stack((range_m * np.cos(a), range_m * np.sin(a)))


def test_points_inside_the_beams_are_seen_and_behind_the_wall_or_the_laser_are_not() -> None:
    area = ObservedArea.from_keyframes([np.zeros(3)], [np.zeros(2)], [_half_fan(2.0)])
    points = np.array([
        [1.5, 0.0],    # ahead, before the wall
        [0.0, 1.9],    # to the left, on the edge of the field of view
        [2.1, 0.0],    # on the wall, within the margin
        [3.0, 0.0],    # behind the wall
        [-1.0, 0.0],   # behind the laser: its 180° never looked there
    ])
    np.testing.assert_array_equal(area.contains(points, margin_m=0.2), [True, True, True, False, False])


def test_a_second_keyframe_turned_round_sees_what_the_first_did_not() -> None:
    area = ObservedArea.from_keyframes(
        [np.zeros(3), np.array([1.0, 0.0, math.pi])], [np.zeros(2), np.zeros(2)], [_half_fan(2.0), _half_fan(3.0)]
    )
    points = np.array([[-1.0, 0.0], [-1.5, 0.5], [3.0, 0.0], [-2.5, 0.0]])
    # (-1, 0) and (-1.5, 0.5) are 2 and ~2.5 m behind the second keyframe's back: ahead of it
    np.testing.assert_array_equal(area.contains(points, margin_m=0.2), [True, True, False, False])
