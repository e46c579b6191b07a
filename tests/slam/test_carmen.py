"""CARMEN logs: the real Intel lab log, hand-written lines of each message type, bad lines."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mazebot.errors import EXIT_USAGE
from mazebot.slam.carmen import CarmenLogError, parse_carmen, read_carmen
from mazebot.slam.grid import FREE, UNKNOWN
from mazebot.slam.keyframes import map_rays
from mazebot.slam.preprocess import PrepareParams, prepare_scan
from mazebot.slam.slam import SlamParams
from mazebot.slam.slam_cli import laser_log_params


def _flaser(n: int = 4, ranges: str = "1 2 3 81.83") -> str:
    return f"FLASER {n} {ranges} 0.5 -0.25 0.1 0.6 -0.2 0.12 12.5 pippo 12.6"


def test_reads_the_intel_log(intel_log_path: Path) -> None:
    log = read_carmen(intel_log_path)
    assert len(log.lasers) == 910
    assert len(log.odometry) == 14541
    first = log.lasers[0]
    assert first.range_m.shape == (180,) and first.angle_rad.shape == (180,)
    # 180 beams, 1 degree apart, from the right (-90) counter-clockwise
    assert math.degrees(first.angle_rad[0]) == pytest.approx(-90.0)
    assert math.degrees(first.angle_rad[-1]) == pytest.approx(89.0)
    np.testing.assert_allclose(first.pose, [0.600266, -0.0320327, -0.354665])
    assert first.timestamp_s == pytest.approx(32.9068)
    assert first.range_m[0] == pytest.approx(1.09)
    assert first.line_number == 171
    times = np.array([rec.timestamp_s for rec in log.lasers])
    assert np.count_nonzero(np.diff(times) < 0) <= 4  # file order is time order, bar a few late messages
    # ODOM lines: zero while the robot stands, raw odometry afterwards
    assert not log.odometry[0].pose.any()
    moving = next(o for o in log.odometry if o.pose.any())
    np.testing.assert_allclose(moving.pose, [2.458e-06, -0.000999997, 0.0])
    assert moving.timestamp_s == pytest.approx(27.7902)


def test_intel_scans_are_consistent_with_their_corrected_poses(intel_log_path: Path) -> None:
    """Two scans a second apart, placed with their GMapping poses, see the same walls."""
    from scipy.spatial import cKDTree

    lasers = read_carmen(intel_log_path).lasers
    a, b = lasers[100], lasers[101]

    def world(rec):  # laser frame -> world with the record's pose
        p = rec.points_xy(20.0)
        c, s = math.cos(rec.pose[2]), math.sin(rec.pose[2])
        return p @ np.array([[c, s], [-s, c]]) + rec.pose[:2]

    d, _ = cKDTree(world(a)).query(world(b))
    assert np.median(d) < 0.05


def test_parses_flaser_robotlaser1_and_odom_lines() -> None:
    text = "\n".join(
        [
            "# CARMEN Logfile",
            "PARAM robot_length 0.5 nohost 0",
            _flaser(),
            "ROBOTLASER1 0 -1.5 3.0 1.0 8.0 0.01 0 4 1.0 2.0 3.0 4.0 2 7 8 "
            "1.0 2.0 0.5 0.9 2.0 0.5 0.1 0.0 0.2 0.1 0.0 20.0 host 20.1",
            "ODOM 1.5 2.5 0.25 0.3 0.1 0.0 30.0 host 30.1",
            "NEFF 15",
            "",
        ]
    )
    log = parse_carmen(text.splitlines())
    flaser, robot = log.lasers
    np.testing.assert_allclose(np.degrees(flaser.angle_rad), [-90.0, -45.0, 0.0, 45.0])
    np.testing.assert_allclose(flaser.range_m, [1, 2, 3, 81.83])
    np.testing.assert_allclose(flaser.pose, [0.5, -0.25, 0.1])
    np.testing.assert_allclose(flaser.odom_pose, [0.6, -0.2, 0.12])
    assert flaser.timestamp_s == 12.5 and flaser.line_number == 3
    np.testing.assert_allclose(flaser.points_xy(), [[0, -1], [2 / math.sqrt(2), -2 / math.sqrt(2)], [3, 0]], atol=1e-12)
    assert robot.kind == "ROBOTLASER1"
    np.testing.assert_allclose(robot.angle_rad, [-1.5, -0.5, 0.5, 1.5])
    np.testing.assert_allclose(robot.pose, [1.0, 2.0, 0.5])
    np.testing.assert_allclose(robot.odom_pose, [0.9, 2.0, 0.5])
    assert robot.max_range_m == 8.0 and robot.timestamp_s == 20.0
    (odom,) = log.odometry
    np.testing.assert_allclose(odom.pose, [1.5, 2.5, 0.25])
    assert (odom.tv_mps, odom.rv_radps, odom.timestamp_s) == (0.3, 0.1, 30.0)


def test_a_record_becomes_a_scan_for_prepare_scan() -> None:
    (rec,) = parse_carmen([_flaser()]).lasers
    scan = rec.to_scan()
    assert len(scan) == 4
    np.testing.assert_array_equal(scan.valid, [True, True, True, False])  # 81.83 m: the SICK saw no echo
    prepared = prepare_scan(scan, None, PrepareParams(max_range_m=30.0, median_window=1, circular=False))
    assert prepared.points_full.shape == (3, 2)
    assert prepared.free_endpoints.shape == (0, 2)
    assert prepared.time_s == 12.5


def test_a_beam_without_echo_clears_no_space_in_the_map() -> None:
    """The 81.83 m beam (45° left) leaves its line unknown; the 3 m hit ahead clears the space before its wall.

    With the laser-log settings (no-return beams would clear 20 m) a missing echo from a
    window once fanned free space far outside the Intel building.
    """
    (rec,) = parse_carmen([_flaser(ranges="3 3 3 81.83")]).lasers
    params = laser_log_params(SlamParams())
    prepared = prepare_scan(rec.to_scan(), None, params.prepare)
    ends, hit, origins = map_rays(prepared, params.map_max_range_m, params.map_smoothing, params.range_noise_rel)
    grid = params.grid.new_grid()
    for _ in range(3):  # one miss is not yet "free"
        grid.integrate(np.zeros(3), ends, hit, origins)
    three = grid.three_state()

    def state_at(angle_rad: float, ranges_m: np.ndarray) -> np.ndarray:
        rows, cols = grid.to_cell(np.column_stack((ranges_m * np.cos(angle_rad), ranges_m * np.sin(angle_rad))))
        inside = (rows >= 0) & (rows < three.shape[0]) & (cols >= 0) & (cols < three.shape[1])
        return np.where(inside, three[np.clip(rows, 0, three.shape[0] - 1), np.clip(cols, 0, three.shape[1] - 1)],
                        UNKNOWN)

    assert (state_at(math.pi / 4, np.arange(0.5, 20.0, 0.25)) == UNKNOWN).all()
    assert (state_at(0.0, np.arange(0.5, 2.8, 0.25)) == FREE).all()  # the hit ahead at 3 m


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        (_flaser(5), "line 2: bad FLASER message"),
        (_flaser(4, "1 2 x 4"), "line 2: bad FLASER message"),
        (_flaser(4, "1 2 nan 4"), "finite"),
        ("FLASER -3 1 2", "line 2: bad FLASER"),
        ("ODOM 1 2 3", "line 2: bad ODOM message (ODOM needs 10 fields, found 4)"),
        ("ROBOTLASER1 0 -1.5 3.0 1.0 8.0 0.01 0 4 1 2 3", "line 2: bad ROBOTLASER1"),
    ],
)
def test_bad_lines_are_one_clear_error_with_the_line_number(line: str, fragment: str) -> None:
    with pytest.raises(CarmenLogError) as info:
        parse_carmen([_flaser(), line], source="run.log")
    message = str(info.value)
    assert message.startswith("run.log line 2: ")
    assert fragment in message
    assert "\n" not in message
    assert info.value.exit_code == EXIT_USAGE


def test_missing_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(CarmenLogError, match="not found"):
        read_carmen(tmp_path / "nope.log")


def test_an_odd_beam_count_spans_both_ends_of_the_field_of_view() -> None:
    """361 beams of a SICK LMS at 0.5°: -90° … +90° inclusive (180 or 360 beams leave the last end out)."""
    ranges = " ".join(["2.0"] * 361)
    (rec,) = parse_carmen([f"FLASER 361 {ranges} 0 0 0 0 0 0 1.0 host 1.0"]).lasers
    np.testing.assert_allclose(np.degrees(rec.angle_rad[[0, 1, 180, 360]]), [-90.0, -89.5, 0.0, 90.0], atol=1e-9)


def _pair_corrections(path: Path, angles_of: object, pairs: int = 60) -> np.ndarray:
    """ICP's correction (dx, dy, dθ in the later scan's frame) of consecutive scans placed at their corrected poses."""
    from mazebot.config import load_config
    from mazebot.geometry import relative_pose
    from mazebot.slam.icp import Target, match_scan
    from mazebot.slam.preprocess import voxel_downsample

    config = load_config(None)
    icp = laser_log_params(SlamParams.from_config(config.slam, config.lidar)).icp
    lasers = read_carmen(path).lasers

    def points(k: int) -> np.ndarray:
        r = lasers[k].range_m
        a = angles_of(r.shape[0]) if callable(angles_of) else lasers[k].angle_rad
        ok = (r > 0.1) & (r < 30.0)
        xy = np.column_stack((r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])))
        return xy[voxel_downsample(xy, 0.05)]

    out = []
    for k in range(min(pairs, len(lasers) - 1)):
        target = Target.from_scans([(lasers[k].pose, points(k), np.zeros(2))], voxel_size_m=0.05, normal_radius_m=0.3)
        found = match_scan(target, points(k + 1), lasers[k + 1].pose, icp, sensor_xy=np.zeros(2))
        if found.converged and found.fitness > 0.6:
            out.append(relative_pose(lasers[k + 1].pose, found.pose))
    return np.array(out)


@pytest.mark.parametrize("name", ["aces-corrected.log.gz", "freiburg-101-corrected.log.gz", "seattle-corrected.log.gz"])
def test_consecutive_corrected_scans_need_no_turn_with_the_beam_angles_read(name: str) -> None:
    """The beam angles as read agree with the corrected poses: ICP moves consecutive scans placed there
    by no rotation in the median, and no sideways shift either (a beam angle convention half a beam off
    turns each scan about its own origin: a sideways shift of about 9 mm per metre and degree, not a turn)."""
    from tests.data_paths import carmen_log

    path = carmen_log(name)
    read = _pair_corrections(path, None)
    assert len(read) >= 30
    assert abs(math.degrees(float(np.median(read[:, 2])))) < 0.06
    assert abs(float(np.median(read[:, 1]))) < 0.003
    if name.startswith("aces"):  # 180 beams: centred in their 1° (−89.5° + i) is half a beam off, and shows
        centred = _pair_corrections(path, lambda n: np.radians(-90.0 + (np.arange(n) + 0.5) * 180.0 / n))
        assert float(np.median(centred[:, 1])) > 0.004


def test_the_slam_tracks_one_laser_the_front_one() -> None:
    """A front and a rear laser (or the front laser written twice) are not one sensor's scans."""
    from mazebot.slam.carmen import one_laser

    robotlaser = ("ROBOTLASER1 0 -1.5 3.0 1.0 8.0 0.01 0 4 1.0 2.0 3.0 4.0 0 "
                  "1.0 2.0 0.5 0.9 2.0 0.5 0.1 0.0 0.2 0.1 0.0 20.0 host 20.1")
    rear = _flaser(ranges="5 5 5 5").replace("FLASER", "RLASER")
    both = parse_carmen([_flaser(), rear, _flaser(), rear, "ODOM 1.5 2.5 0.25 0.3 0.1 0.0 30.0 host 30.1"])
    front = one_laser(both)
    assert [r.kind for r in front.lasers] == ["FLASER", "FLASER"] and len(front.odometry) == 1
    assert [r.kind for r in one_laser(parse_carmen([rear, rear])).lasers] == ["RLASER", "RLASER"]
    twice = parse_carmen([_flaser(), robotlaser, _flaser(), robotlaser])
    assert [r.kind for r in one_laser(twice).lasers] == ["ROBOTLASER1", "ROBOTLASER1"]
