"""Message encodings: ``/scan`` (``foxglove.LaserScan``, for display, millimetres) against the
revolution it shows, and ``/mazebot/scan_raw`` bit for bit."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mazebot.io.scan import Scan
from mazebot.record.schemas import encode, scan_from_json, transform_chain

T_NS = 1_700_000_000_250_000_000


def _revolution() -> Scan:
    """Eight samples, not in bearing order, one invalid, one beyond the 20 m text table."""
    angle = np.array([0.1, 1.0, -0.5, 2.0, 3.0, -2.0, 4.0, 5.5])  # -0.5 and -2.0 wrap to 5.78 and 4.28
    range_m = np.array([1.23449, 0.15, 2.0006, 11.9999, 0.5, 25.0004, 3.3333, 0.0])
    valid = np.array([True, True, True, True, True, True, False, False])
    quality = np.array([10, 20, 30, 40, 50, 60, 5, 0], dtype=np.uint8)
    return Scan(angle, range_m, quality, 100.0 + np.arange(8) * 0.02, valid, revolution=7)


def test_laser_scan_is_the_revolution_on_equal_bearings_in_millimetres() -> None:
    msg = json.loads(encode("/scan", _revolution(), T_NS))
    assert msg["timestamp"] == {"sec": 1_700_000_000, "nsec": 250_000_000}
    assert msg["frame_id"] == "laser" and msg["start_angle"] == 0.0
    step = 2 * math.pi / 8
    assert msg["end_angle"] == step * 7
    # bin k covers [k step, (k+1) step): 0.1->0, 1.0->1, 2.0->2, 3.0->3, 4.0->5, 4.28->5 (later wins)...
    # sorted bearings: 0.1, 1.0, 2.0, 3.0, 4.0 (invalid), 4.28, 5.5 (invalid), 5.78
    assert msg["ranges"] == [1.234, 0.15, 12.0, 0.5, 0.0, 25.0, 0.0, 2.001]
    assert msg["intensities"] == [10, 20, 40, 50, 0, 60, 0, 30]  # each with its range: bins 4 and 6 are empty


def test_raw_scan_comes_back_bit_for_bit() -> None:
    scan = _revolution()
    back = scan_from_json(json.loads(encode("/mazebot/scan_raw", scan, T_NS)))
    for name in ("angle_rad", "range_m", "quality", "time_s", "valid"):
        a, b = getattr(scan, name), getattr(back, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    assert back.revolution == 7


def test_transform_chain_composes_to_the_pose_and_places_the_lidar() -> None:
    """map -> odom is what turns the odometry into the pose; the lidar hangs off base_link unrotated."""
    pose, odometry = (1.0, 2.0, 3.0), (0.4, -0.3, -2.9)  # headings either side of ±π
    map_odom, odom_base, base_laser = transform_chain(pose, odometry, (0.05, -0.01))
    assert (map_odom.parent, map_odom.child, odom_base.parent, odom_base.child) == ("map", "odom", "odom", "base_link")
    assert (base_laser.parent, base_laser.child) == ("base_link", "laser")
    assert (base_laser.x_m, base_laser.y_m, base_laser.theta_rad) == (0.05, -0.01, 0.0)
    assert (odom_base.x_m, odom_base.y_m, odom_base.theta_rad) == odometry
    c, s = math.cos(map_odom.theta_rad), math.sin(map_odom.theta_rad)
    x = map_odom.x_m + c * odometry[0] - s * odometry[1]
    y = map_odom.y_m + s * odometry[0] + c * odometry[1]
    assert (x, y) == (pytest.approx(1.0, abs=1e-12), pytest.approx(2.0, abs=1e-12))
    assert math.remainder(map_odom.theta_rad + odometry[2] - 3.0, math.tau) == pytest.approx(0.0, abs=1e-12)
    msg = json.loads(encode("/tf", map_odom, T_NS))
    assert msg["parent_frame_id"] == "map" and msg["child_frame_id"] == "odom"
    assert msg["rotation"]["w"] == pytest.approx(math.cos(map_odom.theta_rad / 2))
