"""A log whose odometry is real, in CARMEN's common layouts: the SLAM gets the raw odometry, the errors the corrected
poses.

Each small log is the Intel log's first scans with their corrected poses, and a raw
odometry drawn from them (:func:`mazebot.slam.slam_cli.noisy_odometry`) written where the
layout keeps it: the ``FLASER`` odometry fields, ``ODOM`` lines between the scans (also
re-based onto each scan's corrected pose, as in the corrected Radish logs), or a
``ROBOTLASER1``'s robot pose with the laser mounted ahead of the robot.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mazebot.cli import main
from mazebot.geometry import compose, inverse, relative_pose
from mazebot.slam.carmen import parse_carmen
from mazebot.slam.slam_cli import log_odometry, noisy_odometry, same_motion

SCANS = 25
MOUNT = np.array([0.12, 0.0, 0.0])  # the ROBOTLASER1 laser, 12 cm ahead of the robot's centre


def _intel_scans(intel_log_path: Path) -> tuple[list[list[str]], np.ndarray, np.ndarray]:
    """The first scans' range tokens, their corrected poses and a raw odometry (3 cm/m, 0.03 rad/m)."""
    ranges, poses, stamps = [], [], []
    for line in intel_log_path.read_text(encoding="utf-8").splitlines():
        tokens = line.split()
        if tokens and tokens[0] == "FLASER":
            n = int(tokens[1])
            ranges.append(tokens[2 : 2 + n])
            poses.append([float(v) for v in tokens[2 + n : 5 + n]])
            stamps.append(float(tokens[2 + n + 6]))
            if len(ranges) == SCANS:
                break
    corrected = np.array(poses)
    raw = compose(np.array([3.0, -2.0, 0.7]), noisy_odometry(corrected, 0.03, 0.03, np.random.default_rng(4)))
    return ranges, corrected, np.column_stack((raw, stamps))


def _fmt(values: np.ndarray) -> str:
    return " ".join(f"{v:.6f}" for v in values)


def _flaser(r: list[str], pose: np.ndarray, odom: np.ndarray, stamp: float) -> str:
    return f"FLASER {len(r)} {' '.join(r)} {_fmt(pose)} {_fmt(odom)} {stamp:.6f} host {stamp:.6f}"


def _odom(pose: np.ndarray, stamp: float) -> str:
    return f"ODOM {_fmt(pose)} 0.1 0.0 0.0 {stamp:.6f} host {stamp:.6f}"


def _robotlaser(r: list[str], laser: np.ndarray, robot: np.ndarray, stamp: float) -> str:
    head = f"ROBOTLASER1 0 {-np.pi / 2:.6f} {np.pi:.6f} {np.pi / len(r):.8f} 81.83 0.01 0"
    tail = f"{_fmt(laser)} {_fmt(robot)} 0.1 0.0 0.5 0.3 0.0 {stamp:.6f} host {stamp:.6f}"
    return f"{head} {len(r)} {' '.join(r)} 0 {tail}"


def _layouts(intel_log_path: Path) -> dict[str, tuple[list[str], np.ndarray, np.ndarray]]:
    """Each layout's lines, the laser's corrected poses (the reference) and its raw odometry."""
    ranges, corrected, raw = _intel_scans(intel_log_path)
    stamps = raw[:, 3]
    flaser = [_flaser(r, c, o[:3], t) for r, c, o, t in zip(ranges, corrected, raw, stamps, strict=True)]
    odom_lines = []
    for k, (r, c, t) in enumerate(zip(ranges, corrected, stamps, strict=True)):
        if k:  # one reading between two scans, and one at the scan's own stamp
            odom_lines.append(_odom(0.5 * (raw[k - 1, :3] + raw[k, :3]), 0.5 * (stamps[k - 1] + t)))
        odom_lines += [_odom(raw[k, :3], t), _flaser(r, c, c, t)]  # the message's odometry fields: corrected
    rebased = []  # after each scan an ODOM line stamped 0 at its corrected pose, the odometry's motion from there
    for k, (r, c, t) in enumerate(zip(ranges, corrected, stamps, strict=True)):
        if k:
            base, since = corrected[k - 1], raw[k - 1, :3]
            middle = 0.5 * (raw[k - 1, :3] + raw[k, :3])
            rebased.append(_odom(compose(base, relative_pose(since, middle)), 0.5 * (stamps[k - 1] + t)))
            rebased.append(_odom(compose(base, relative_pose(since, raw[k, :3])), t))
        else:
            rebased.append(_odom(raw[k, :3], t))
        rebased += [_flaser(r, c, c, t), _odom(c, 0.0)]
    robot_corrected = compose(corrected, inverse(MOUNT))  # the laser sits MOUNT ahead of the robot
    laser_raw = compose(raw[:, :3], MOUNT)
    robotlaser = []
    for k, (r, c, rb, t) in enumerate(zip(ranges, corrected, robot_corrected, stamps, strict=True)):
        robotlaser += [_odom(raw[k, :3], t), _robotlaser(r, c, rb, t)]
    return {
        "flaser_odometry_fields": (flaser, corrected, raw[:, :3]),
        "odom_lines_interleaved": (odom_lines, corrected, raw[:, :3]),
        "robotlaser1": (robotlaser, corrected, laser_raw),
        "odom_lines_rebased": (rebased, corrected, raw[:, :3]),
    }


def _same_relative(a: np.ndarray, b: np.ndarray) -> None:
    """Equal up to where each starts (the SLAM anchors the odometry at the first reference pose)."""
    np.testing.assert_allclose(relative_pose(a[0], a), relative_pose(b[0], b), atol=2e-5)


@pytest.mark.parametrize(
    "layout", ["flaser_odometry_fields", "odom_lines_interleaved", "robotlaser1", "odom_lines_rebased"]
)
def test_the_slam_gets_the_raw_odometry_and_is_judged_against_the_corrected_poses(
    layout: str, intel_log_path: Path
) -> None:
    lines, corrected, raw = _layouts(intel_log_path)[layout]
    log = parse_carmen(lines)
    assert len(log.lasers) == SCANS
    np.testing.assert_allclose(np.array([r.pose for r in log.lasers]), corrected, atol=2e-6)  # the reference
    odometry = log_odometry(log)
    _same_relative(odometry, raw)
    assert not same_motion(odometry, corrected)  # 3 cm/m of noise: not the reference


@pytest.mark.slow
def test_slam_run_on_a_log_with_real_odometry_reports_its_errors(
    intel_log_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines, corrected, raw = _layouts(intel_log_path)["robotlaser1"]
    log = tmp_path / "robotlaser.log"
    log.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert main(["slam", "run", "--carmen", str(log), "--out", str(tmp_path / "o")]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["odom_model"] == "log" and stats["reference"] == "the log's poses"
    # the odometry the SLAM was given is the raw one, 3 cm/m off the corrected poses ...
    rows = np.loadtxt(tmp_path / "o" / "trajectory.txt")
    odometry = compose(corrected[0], relative_pose(raw[0], raw))
    expected = np.sqrt(np.mean(np.sum((odometry[:, :2] - corrected[:, :2]) ** 2, axis=1)))
    assert stats["error_odometry"]["rms_m"] == pytest.approx(expected, abs=1e-3)
    # ... and the SLAM's trajectory is judged against the corrected ones
    err = np.hypot(*(rows[:, 1:3] - corrected[:, :2]).T)
    assert stats["error"]["rms_m"] == pytest.approx(float(np.sqrt(np.mean(err**2))), abs=1e-3)
    assert stats["error"]["rms_m"] < stats["error_odometry"]["rms_m"]
    assert stats["odom_noise_learnt"]["pairs"] > 0


@pytest.mark.slow
def test_a_log_with_only_raw_odometry_runs_and_reports_no_errors(
    intel_log_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A raw log's laser poses are its odometry: an error "against the reference" would be against the odometry."""
    ranges, _, raw = _intel_scans(intel_log_path)
    log = tmp_path / "raw.log"
    log.write_text("\n".join(_flaser(r, o[:3], o[:3], o[3]) for r, o in zip(ranges, raw, strict=True)) + "\n",
                   encoding="utf-8")
    assert main(["slam", "run", "--carmen", str(log), "--max-scans", "12", "--out", str(tmp_path / "o")]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["scans"] == 12 and stats["reference"] is None
    for key in ("error", "error_online", "error_odometry", "error_aligned", "relative_error",
                "relative_error_odometry", "consistency_reference", "error_reference_reanchored"):
        assert stats[key] is None
    assert stats["consistency"]["scans"] >= 0  # the SLAM's own map is still judged by itself
    assert np.loadtxt(tmp_path / "o" / "trajectory.txt").shape == (12, 4)
    # --odom-noise makes odometry from those poses: then they are the reference again
    assert main(["slam", "run", "--carmen", str(log), "--odom-noise", "0.05,0.05", "--max-scans", "12",
                 "--out", str(tmp_path / "p")]) == 0
    assert json.loads(capsys.readouterr().out)["error"] is not None


def test_a_log_without_odometry_is_one_line(
    intel_log_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ranges, corrected, raw = _intel_scans(intel_log_path)
    log = tmp_path / "zero.log"
    log.write_text("\n".join(_flaser(r, c, np.zeros(3), t) for r, c, t in zip(ranges, corrected, raw[:, 3],
                                                                             strict=True)) + "\n", encoding="utf-8")
    assert main(["slam", "run", "--carmen", str(log), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no odometry" in err and "--odom-noise" in err and "\n" not in err


@pytest.mark.slow
def test_the_aces_log_on_its_robots_own_wheels_is_mapped_where_the_wheels_drift_metres(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """ACES's ``ODOM`` lines hold the robot's wheel odometry re-based onto each corrected pose.

    Read back, the first 150 scans' odometry is metres off the corrected poses (5.5 m RMS:
    the wheels' own drift, not the reference); the SLAM on it stays within 0.4 m of them
    (0.31 m RMS, max 0.68 m, with the laser's lever arm applied while its test passes; 0.20 m
    without it). Read in file order, the lines leaked the reference (odometry within 1 m)
    and the SLAM was 4 m off by scan 130.
    """
    from tests.data_paths import carmen_log

    log = carmen_log("aces-corrected.log.gz")
    assert main(["slam", "run", "--carmen", str(log), "--max-scans", "150", "--out", str(tmp_path / "o")]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["odom_model"] == "log" and stats["reference"] == "the log's poses"
    assert stats["error_odometry"]["rms_m"] > 3.0
    assert stats["error"]["rms_m"] < 0.4 and stats["error"]["max_m"] < 0.8
