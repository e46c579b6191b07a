"""Message encodings: ``/scan`` (``foxglove.LaserScan``, for display, millimetres) against the
revolution it shows, and ``/mazebot/scan_raw`` bit for bit."""

from __future__ import annotations

import json
import math

import numpy as np

from mazebot.io.scan import Scan
from mazebot.record.schemas import encode, scan_from_json

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
    assert msg["frame_id"] == "base_link" and msg["start_angle"] == 0.0
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
