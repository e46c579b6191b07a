"""The CARMEN messages a log from CARMEN's own logger holds: ``RAWLASER1``-``4`` and the laser's ``PARAM`` lines.

A log that only CARMEN's laser driver and base wrote has ``RAWLASERn`` messages (their own
geometry, no pose) and ``ODOM`` readings; an old-style ``FLASER`` log may say its laser's field
of view in a ``PARAM`` line. The formats are CARMEN 0.7's (``src/logger/writelog.c``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mazebot.slam.carmen import CarmenLogError, one_laser, parse_carmen, read_carmen
from mazebot.slam.log_degrade import as_rawlaser, write_log
from mazebot.slam.slam_cli import from_first_pose, log_odometry
from tests.data_paths import carmen_log


def _rawlaser(ranges: list[float], stamp: float, kind: str = "RAWLASER1", fov_deg: float = 180.0) -> str:
    step = math.radians(fov_deg) / (len(ranges) - 1)
    head = f"0 {-math.radians(fov_deg) / 2} {math.radians(fov_deg)} {step} 81.9 0.01 0"
    return f"{kind} {head} {len(ranges)} {' '.join(map(str, ranges))} 0 {stamp} host {stamp}"


def _odom(x: float, y: float, theta: float, stamp: float) -> str:
    return f"ODOM {x} {y} {theta} 0 0 0 {stamp} host {stamp}"


def test_a_rawlaser1_has_its_own_geometry_and_the_odometry_at_its_time() -> None:
    """Beams from its own start angle and step; its pose the ODOM readings interpolated at its stamp."""
    log = parse_carmen([
        _odom(1.0, 0.0, 0.0, 10.0), _rawlaser([1.0, 2.0, 3.0], 10.5, fov_deg=100.0), _odom(2.0, 1.0, 0.2, 11.0),
    ])
    (laser,) = one_laser(log).lasers
    assert laser.kind == "RAWLASER1" and laser.max_range_m == 81.9
    np.testing.assert_allclose(np.degrees(laser.angle_rad), [-50.0, 0.0, 50.0], atol=1e-9)
    np.testing.assert_allclose(laser.pose, [1.5, 0.5, 0.1], atol=1e-12)
    np.testing.assert_allclose(log_odometry(one_laser(log)), [[1.5, 0.5, 0.1]], atol=1e-12)


def test_a_rawlaser_header_printed_with_six_decimals_spreads_its_beams_over_its_field_of_view() -> None:
    """CARMEN's logger prints 0.5° as 0.008727 rad: stepped by it, the last of 361 beams would be 0.007° off 90°."""
    ranges = " ".join(["2.0"] * 361)
    line = f"RAWLASER1 0 -1.570796 3.141593 0.008727 81.9 0.01 0 361 {ranges} 0 1.0 host 1.0"
    (laser,) = parse_carmen([_odom(0, 0, 0, 0.5), line, _odom(0, 0, 0, 1.5)]).lasers
    assert abs(math.degrees(laser.angle_rad[-1]) - 90.0) < 1e-4
    # a header whose field of view is not (n - 1) steps (n of them here) is read by its resolution
    (laser,) = parse_carmen([_odom(0, 0, 0, 0.5), line.replace("3.141593", "3.150320"), _odom(0, 0, 0, 1.5)]).lasers
    assert math.degrees(laser.angle_rad[1] - laser.angle_rad[0]) == pytest.approx(0.5, abs=1e-4)


def test_a_rawlaser_sits_where_the_logs_params_mount_it() -> None:
    """``robot_frontlaser_offset`` ahead, ``..._side_offset`` left, ``..._angular_offset`` turned (CARMEN's robot
    module's ``construct_laser_message``): the laser's pose, and the odometry the SLAM is given, are there."""
    log = parse_carmen([
        "PARAM robot_frontlaser_offset 0.2 1.0 host 1.0",
        "PARAM robot_frontlaser_side_offset 0.1 1.0 host 1.0",
        "PARAM robot_frontlaser_angular_offset 0.05 1.0 host 1.0",
        _odom(1.0, 0.0, math.pi / 2, 10.0), _rawlaser([1.0, 2.0, 3.0], 10.0), _odom(1.0, 0.0, math.pi / 2, 11.0),
    ])
    (laser,) = log.lasers
    np.testing.assert_allclose(laser.pose, [0.9, 0.2, math.pi / 2 + 0.05], atol=1e-12)
    np.testing.assert_allclose(laser.odom_pose, [1.0, 0.0, math.pi / 2], atol=1e-12)
    np.testing.assert_allclose(log_odometry(log), [laser.pose], atol=1e-12)


def test_the_rear_and_other_raw_lasers_are_taken_only_when_nothing_else_is_there() -> None:
    rear = _rawlaser([4.0, 4.0, 4.0], 10.0, kind="RAWLASER2")
    front = _rawlaser([1.0, 1.0, 1.0], 10.0)
    flaser = "FLASER 3 1 1 1 0 0 0 0 0 0 10.0 host 10.0"
    assert [r.kind for r in one_laser(parse_carmen([rear, front, rear])).lasers] == ["RAWLASER1"]
    assert [r.kind for r in one_laser(parse_carmen([rear, flaser, front])).lasers] == ["FLASER"]
    assert [r.kind for r in one_laser(parse_carmen([rear, rear])).lasers] == ["RAWLASER2", "RAWLASER2"]


def test_a_rawlasers_no_echo_reading_below_its_nominal_maximum_is_no_return() -> None:
    """CARMEN's SICK driver writes 81.90 m as the maximum and the laser 81.83 m for a missing echo."""
    log = parse_carmen([_rawlaser([1.0, 81.83, 2.0], 10.0 + k) for k in range(5)])
    assert {r.max_range_m for r in log.lasers} == {81.83}
    assert log.lasers[0].to_scan().valid.tolist() == [True, False, True]


def test_a_flaser_logs_param_sets_its_field_of_view() -> None:
    """``PARAM laser_front_laser_fov 100`` (degrees, as CARMEN's laser driver takes it): 101 beams over 100°,
    from -50°; the rear laser's own parameter for ``RLASER``; without it, 180° as before."""
    ranges = " ".join(["2.0"] * 101)
    flaser = f"FLASER 101 {ranges} 0 0 0 0 0 0 1.0 host 1.0"
    rlaser = flaser.replace("FLASER", "RLASER")
    log = parse_carmen(["PARAM laser_front_laser_fov 100 0.0 host 0.0", flaser, rlaser])
    front, back = log.lasers
    np.testing.assert_allclose(np.degrees(front.angle_rad[[0, 1, 50, 100]]), [-50.0, -49.0, 0.0, 50.0], atol=1e-9)
    np.testing.assert_allclose(np.degrees(back.angle_rad[[0, 100]]), [-90.0, 90.0], atol=1e-9)
    plain = parse_carmen([flaser]).lasers[0]
    np.testing.assert_allclose(np.degrees(plain.angle_rad[[0, 100]]), [-90.0, 90.0], atol=1e-9)


@pytest.mark.parametrize(
    ("lines", "fragment"),
    [
        ([_odom(0, 0, 0, 1.0), _rawlaser([1.0, 2.0], 1.0).replace(" 0 1.0 host", " 1.0 host")],
         "line 2: bad RAWLASER1 message"),
        ([_odom(0, 0, 0, 1.0), _rawlaser([1.0, 2.0], 1.0).replace(" 2.0 ", " x ", 1)], "line 2: bad RAWLASER1"),
        ([_odom(0, 0, 0, 1.0), "RAWLASER3 0 -1.5 3.0"], "line 2: bad RAWLASER3"),
        ([_odom(0, 0, 0, 1.0), "PARAM laser_front_laser_fov 3.14159 0.0 host 0.0"], "line 2: bad PARAM message"),
        ([_odom(0, 0, 0, 1.0), "PARAM robot_frontlaser_offset abc 0.0 host 0.0", _rawlaser([1.0, 2.0], 1.0)],
         "line 2: bad PARAM message (robot_frontlaser_offset 'abc'"),
    ],
)
def test_a_bad_rawlaser_or_param_line_is_one_error_with_its_line_number(lines: list[str], fragment: str) -> None:
    with pytest.raises(CarmenLogError) as info:
        parse_carmen(lines, source="run.log")
    message = str(info.value)
    assert message.startswith("run.log line 2: ") and fragment in message and "\n" not in message


def test_a_log_rewritten_as_rawlaser1_reads_back_the_same_scans(tmp_path: Path) -> None:
    log = one_laser(read_carmen(carmen_log("seattle-corrected.log.gz")))
    reference = np.array([r.pose for r in log.lasers])
    odometry = from_first_pose(log_odometry(log), reference)
    write_log(tmp_path / "raw.log.gz", [as_rawlaser(r) for r in log.lasers], odometry)
    back = one_laser(read_carmen(tmp_path / "raw.log.gz"))
    assert [r.kind for r in back.lasers] == ["RAWLASER1"] * len(log.lasers)
    for a, b in zip(log.lasers, back.lasers, strict=True):
        assert np.array_equal(a.range_m, b.range_m) and a.max_range_m == b.max_range_m
        assert a.timestamp_s == b.timestamp_s
        np.testing.assert_allclose(a.angle_rad, b.angle_rad, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(log_odometry(back), odometry, rtol=0.0, atol=1e-12)


@pytest.mark.slow
def test_slam_run_on_a_rawlaser1_log_gives_the_originals_trajectory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Seattle's first 150 scans rewritten as ``RAWLASER1`` + ``ODOM`` (its own wheels, placed at the first
    corrected pose): ``slam run`` gives the same trajectory as on the log itself, as close to the corrected poses.

    To the digit only because the beam angles read back bit for bit: the SLAM is that sensitive to them
    (angles 3.5e-14 rad off, the beam straight ahead no longer exactly at 0, gave 0.1752 m instead of 0.1407).
    """
    from mazebot.cli import main

    scans = 150
    log = one_laser(read_carmen(carmen_log("seattle-corrected.log.gz")))
    reference = np.array([r.pose for r in log.lasers])
    odometry = from_first_pose(log_odometry(log), reference)
    raw = tmp_path / "raw.log.gz"
    write_log(raw, [as_rawlaser(r) for r in log.lasers], odometry)
    assert {r.kind for r in read_carmen(raw).lasers} == {"RAWLASER1"}  # no pose in it: the ODOM lines place the scans
    trajectories = []
    for path in (carmen_log("seattle-corrected.log.gz"), raw):
        out = tmp_path / path.name.split(".")[0]
        args = ["slam", "run", "--carmen", str(path), "--max-scans", str(scans), "--consistency-scans", "0"]
        assert main([*args, "--out", str(out)]) == 0
        json.loads(capsys.readouterr().out)
        trajectories.append(np.loadtxt(out / "trajectory.txt")[:, 1:])
    original, rewritten = trajectories
    assert rewritten.shape == (scans, 3)
    np.testing.assert_array_equal(rewritten, original)  # to the written digit: the same scans, the same odometry
    error_m = np.hypot(*(rewritten[:, :2] - reference[:scans, :2]).T)
    assert math.sqrt(float(np.mean(error_m**2))) < 0.15  # 0.1407 m
