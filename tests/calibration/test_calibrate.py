"""``mazebot calibrate`` against the simulator's ground truth: the true robot differs from its config
in wheel sizes, track width, lidar yaw, an encoder's direction and the motor channels."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mazebot.calibration.geometry import CalibrationError, Pulse, Run, deduce_wiring, solve_geometry, yaw_error_rad
from mazebot.calibration.progress import Progress
from mazebot.calibration.result import calibrated_config, config_diff, run_ends
from mazebot.calibration.routine import STEPS
from mazebot.calibration.sim_section import same_true_robot
from mazebot.calibration_cli import run_calibration
from mazebot.cli import main
from mazebot.config import Config, load_config, render_toml
from mazebot.sim.robot import physics_params

pytestmark = pytest.mark.slow  # calibration runs on the simulated robot


def _miswired() -> Config:
    config = Config()
    sim = config.sim
    sim.wheel_diameter_left_scale = 1.03
    sim.wheel_diameter_right_scale = 1.02
    sim.track_width_scale = 1.06
    sim.lidar_mount_yaw_error_deg = 3.0
    sim.left_encoder_reversed = True
    sim.motor_channels_swapped = True
    sim.deadband = 0.1
    return config


def test_calibration_recovers_the_true_robot_of_the_simulator() -> None:
    config = _miswired()
    progress = Progress(STEPS)
    result = run_calibration(config, progress, sim=True)
    new = calibrated_config(config, result)

    true_left_m, true_right_m = 0.065 * 1.03, 0.065 * 1.02
    d, ratio = new.drive.wheel_diameter_m, new.drive.wheel_diameter_ratio
    left_m, right_m = d * 2 / (1 + ratio), d * 2 * ratio / (1 + ratio)
    assert left_m == pytest.approx(true_left_m, rel=0.005)
    assert right_m == pytest.approx(true_right_m, rel=0.005)
    assert new.drive.track_width_m == pytest.approx(0.15 * 1.06, rel=0.005)
    assert new.lidar.mount_yaw_deg == pytest.approx(3.0, abs=0.3)
    # wiring: the left wheel's motor is on channel 2, the right's on 1, polarity as before;
    # the left encoder counts the other way
    assert (new.motors.left_channel, new.motors.right_channel) == (2, 1)
    assert (new.motors.left_invert, new.motors.right_invert) == (False, True)
    assert (new.encoders.left_invert, new.encoders.right_invert) == (True, True)
    assert new.control.motor_deadband == pytest.approx(0.1, abs=0.01)
    gain = progress.step("ramp").measured["gain_right_over_left"]  # [sim] gain_right 0.97, wheels 1.02/1.03
    assert gain == pytest.approx(0.97 * 1.02 / 1.03, rel=0.02)
    assert all(step["state"] == "done" for step in progress.as_json())

    # the same physical robot, described against the calibrated config, now matches it
    truth = same_true_robot(config, new)
    sim = truth.sim
    assert not (sim.motor_channels_swapped or sim.left_encoder_reversed or sim.right_encoder_reversed)
    assert not (sim.left_motor_reversed or sim.right_motor_reversed or sim.encoder_pins_swapped)
    before, after = physics_params(config), physics_params(truth)
    assert after.track_width_m == pytest.approx(before.track_width_m, rel=1e-9)
    for side in ("left", "right"):
        true_before = before.wheel_diameter_m * getattr(before, f"wheel_diameter_{side}_scale")
        true_after = after.wheel_diameter_m * getattr(after, f"wheel_diameter_{side}_scale")
        assert true_after == pytest.approx(true_before, rel=1e-9)
        assert getattr(sim, f"wheel_diameter_{side}_scale") == pytest.approx(1.0, abs=0.005)


def test_a_wheel_that_does_not_turn_stops_the_calibration_and_writes_nothing(tmp_path: Path, capsys) -> None:
    config = Config()
    config.sim.deadband = 0.6  # the pulses cannot move the wheels
    path = tmp_path / "config.toml"
    path.write_text(render_toml(config))
    code = main(["calibrate", "--sim", "--write", "--config", str(path), "--out", str(tmp_path / "report")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0
    assert len(err) == 1 and "wiring" in err[0] and "did not move the robot" in err[0]
    assert path.read_text() == render_toml(config)
    assert not (tmp_path / "config.toml.bak").exists() and not (tmp_path / "report").exists()


def test_no_walls_in_view_stops_the_calibration_in_its_first_step_and_writes_nothing(tmp_path: Path,
                                                                                    capsys) -> None:
    config = Config()
    config.lidar.max_range_m = 0.16  # every wall of the room is farther than the lidar reaches
    progress = Progress(STEPS)
    with pytest.raises(CalibrationError, match="no walls in view"):
        run_calibration(config, progress, sim=True)
    assert [s["state"] for s in progress.as_json()] == ["failed"] + ["pending"] * 4  # the wiring step says it
    path = tmp_path / "config.toml"
    path.write_text(render_toml(config))
    code = main(["calibrate", "--sim", "--write", "--config", str(path), "--out", str(tmp_path / "report")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "step 'wiring' failed" in err[0] and "no walls in view" in err[0]
    assert path.read_text() == render_toml(config) and not (tmp_path / "config.toml.bak").exists()
    assert not (tmp_path / "report").exists()


def test_calibrate_write_keeps_a_backup_and_the_same_simulated_robot(tmp_path: Path, capsys) -> None:
    config = _miswired()
    path = tmp_path / "config.toml"
    path.write_text(render_toml(config))
    out = tmp_path / "report"
    assert main(["calibrate", "--sim", "--write", "--config", str(path), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "motors.left_channel: 1 -> 2" in printed and "[5/5]" in printed
    assert (tmp_path / "config.toml.bak").read_text() == render_toml(config)
    written = load_config(path)
    assert written.motors.left_channel == 2 and written.encoders.left_invert
    assert not written.sim.motor_channels_swapped and abs(written.sim.lidar_mount_yaw_error_deg) < 0.3
    report = json.loads((out / "calibration.json").read_text())
    assert {d["key"] for d in report["diff"]} >= {"drive.track_width_m", "lidar.mount_yaw_deg"}
    assert (out / "calibration.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # calibrating the calibrated robot again finds nothing more to change in the wiring
    again = calibrated_config(written, run_calibration(written, Progress(STEPS), sim=True))
    keys = {k for k, _, _ in config_diff(written, again)}
    assert not keys & {"motors.left_channel", "motors.right_channel", "motors.left_invert",
                       "motors.right_invert", "encoders.left_invert", "encoders.right_invert"}


def _arc(k_l: float, k_r: float, track_m: float, c_l: int, c_r: int) -> Run:
    d_l, d_r = k_l * c_l, k_r * c_r
    s, th = 0.5 * (d_l + d_r), (d_r - d_l) / track_m
    chord = s if th == 0 else s * math.sin(th / 2) / (th / 2)
    kind = "straight" if c_l * c_r > 0 else "turn"
    return Run(kind, c_l, c_r, chord * math.cos(th / 2), chord * math.sin(th / 2), th)


def test_geometry_is_exact_on_exact_arcs() -> None:
    k_l, k_r, track_m = 2.5e-4, 2.45e-4, 0.159
    runs = [_arc(k_l, k_r, track_m, 2000, 2030), _arc(k_l, k_r, track_m, -2000, -1990),
            _arc(k_l, k_r, track_m, -3000, 3100)]
    g = solve_geometry(runs)
    assert g.left_m_per_count == pytest.approx(k_l, rel=1e-9)
    assert g.right_m_per_count == pytest.approx(k_r, rel=1e-9)
    assert g.track_width_m == pytest.approx(track_m, rel=1e-9)
    assert g.worst_arc_residual < 1e-9
    # a lidar turned by 3° sees every chord 3° the other way
    yaw = math.radians(3.0)
    turned = [Run(r.kind, r.left_counts, r.right_counts,
                  r.x_m * math.cos(-yaw) - r.y_m * math.sin(-yaw),
                  r.x_m * math.sin(-yaw) + r.y_m * math.cos(-yaw), r.theta_rad) for r in runs]
    assert yaw_error_rad(turned) == pytest.approx(yaw, abs=1e-9)


def test_wiring_names_each_wheel_from_the_pivot() -> None:
    # output "left" turns the right wheel backwards (CW and backward), counted by the left input upwards
    # output "right" turns the left wheel forwards (CW and forward), counted by the right input
    wiring = deduce_wiring([Pulse("left", 300, 0, -0.02, 0.0, -0.3), Pulse("right", 0, 280, 0.02, 0.0, -0.3)])
    assert wiring.wheel_of_output == {"left": "right", "right": "left"}
    assert wiring.output_reversed == {"left": True, "right": False}
    assert wiring.wheel_of_encoder == {"left": "right", "right": "left"}
    assert wiring.encoder_reversed == {"left": True, "right": False}
    with pytest.raises(CalibrationError, match="no encoder counted"):
        deduce_wiring([Pulse("left", 3, 0, 0.02, 0.0, -0.3)])


def test_the_report_chains_the_runs_from_the_start() -> None:
    # each run is measured in the frame of its own start: forward then back ends where it began,
    # and a quarter turn then a straight run ends to the side
    runs = [Run("straight", 3000, 3000, 0.8, 0.0, 0.0), Run("straight", -3000, -3000, -0.8, 0.0, 0.0),
            Run("turn", -500, 500, 0.0, 0.0, math.pi / 2), Run("straight", 1000, 1000, 0.3, 0.0, 0.0)]
    ends = run_ends(runs)
    assert ends[:, :2] == pytest.approx(np.array([[0.8, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.3]]), abs=1e-12)
    assert ends[-1, 2] == pytest.approx(math.pi / 2)
