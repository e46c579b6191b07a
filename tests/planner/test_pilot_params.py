"""The pilot and the control tick see the configuration's values, defaults included.

:class:`PilotParams` and :class:`MotorControl` take the config sections themselves,
so a default is written once (in ``mazebot/config.py``) and a value set in ``config.toml``
reaches the part that uses it without a hand-written mapping in between.
"""

from __future__ import annotations

import operator

import pytest

from mazebot.config import Config, parse_config
from mazebot.planner.pilot import Pilot, PilotParams
from mazebot.tasks.control_task import MotorControl

#: A configuration with every value checked below away from its default (and within its bounds).
CHANGED = {
    "planner": {"goal_tolerance_m": 0.08, "progress_revolutions": 120, "dwell_revolutions": 20,
                "retry_after_m": 1.1, "max_attempts": 4, "horizon_s": 1.5, "stuck_timeout_s": 5.0,
                "mode": "frontier", "max_recoveries": 5, "stand_still_revolutions": 60},
    "drive": {"max_speed_mps": 0.25, "max_yaw_rate_radps": 1.0, "max_accel_mps2": 0.5, "max_yaw_accel_radps2": 2.5},
    "robot": {"footprint_radius_m": 0.1, "clearance_m": 0.03},
    "control": {"brake_decel_mps2": 0.7, "stop_margin_m": 0.05, "side_margin_m": 0.02, "max_wheel_accel_mps2": 1.5,
                "command_ttl_ticks": 12, "scan_timeout_ticks": 25, "deadline_s": 0.2},
    "lidar": {"min_range_m": 0.12},
}

#: (a part of the pilot, its attribute) -> (config section, key)
PILOT_READS = {
    ("explorer", "goal_tolerance_m"): ("planner", "goal_tolerance_m"),
    ("explorer", "progress_revolutions"): ("planner", "progress_revolutions"),
    ("explorer", "dwell_revolutions"): ("planner", "dwell_revolutions"),
    ("explorer", "retry_after_m"): ("planner", "retry_after_m"),
    ("explorer", "max_attempts"): ("planner", "max_attempts"),
    ("explorer", "mode_setting"): ("planner", "mode"),
    ("explorer", "footprint_radius_m"): ("robot", "footprint_radius_m"),
    ("explorer", "clearance_m"): ("robot", "clearance_m"),
    ("explorer", "lidar_min_range_m"): ("lidar", "min_range_m"),
    ("local.dwa", "max_speed_mps"): ("drive", "max_speed_mps"),
    ("local.dwa", "max_yaw_rate_radps"): ("drive", "max_yaw_rate_radps"),
    ("local.dwa", "max_accel_mps2"): ("drive", "max_accel_mps2"),
    ("local.dwa", "max_yaw_accel_radps2"): ("drive", "max_yaw_accel_radps2"),
    ("local.dwa", "brake_decel_mps2"): ("control", "brake_decel_mps2"),
    ("local.dwa", "stop_margin_m"): ("control", "stop_margin_m"),
    ("local.dwa", "footprint_radius_m"): ("robot", "footprint_radius_m"),
    ("local.dwa", "clearance_m"): ("robot", "clearance_m"),
    ("local.dwa", "horizon_s"): ("planner", "horizon_s"),
    ("local", "stuck_timeout_s"): ("planner", "stuck_timeout_s"),
    ("local", "max_recoveries"): ("planner", "max_recoveries"),
    ("still", "limit_revolutions"): ("planner", "stand_still_revolutions"),
}

#: (a part of the control tick, its attribute) -> (config section, key)
CONTROL_READS = {
    ("safety.guard", "margin_m"): ("control", "stop_margin_m"),
    ("safety.guard", "side_margin_m"): ("control", "side_margin_m"),
    ("safety.guard", "brake_decel_mps2"): ("control", "brake_decel_mps2"),
    ("safety.guard", "footprint_radius_m"): ("robot", "footprint_radius_m"),
    ("safety", "command_ttl_ticks"): ("control", "command_ttl_ticks"),
    ("safety", "scan_timeout_ticks"): ("control", "scan_timeout_ticks"),
    ("safety.watchdog", "deadline_s"): ("control", "deadline_s"),
    ("wheels", "max_wheel_accel_mps2"): ("control", "max_wheel_accel_mps2"),
}


@pytest.mark.parametrize("config", [Config(), parse_config(CHANGED)], ids=["defaults", "changed"])
def test_the_pilot_sees_the_configs_values(config: Config) -> None:
    pilot = Pilot(PilotParams.from_config(config))
    for (part, attribute), (section, key) in PILOT_READS.items():
        seen = operator.attrgetter(f"{part}.{attribute}")(pilot)
        assert seen == getattr(getattr(config, section), key), f"pilot.{part}.{attribute} vs [{section}] {key}"


@pytest.mark.parametrize("config", [Config(), parse_config(CHANGED)], ids=["defaults", "changed"])
def test_the_control_tick_sees_the_configs_values(config: Config) -> None:
    control = MotorControl.from_config(config)
    for (part, attribute), (section, key) in CONTROL_READS.items():
        seen = operator.attrgetter(f"{part}.{attribute}")(control)
        assert seen == getattr(getattr(config, section), key), f"control.{part}.{attribute} vs [{section}] {key}"
    assert control.period_s == config.daemon.control_period_s
    assert control.jog_ttl_s == config.motors.command_ttl_s


def test_every_changed_value_differs_from_its_default() -> None:
    default = Config()
    for section, values in CHANGED.items():
        for key, value in values.items():
            assert getattr(getattr(default, section), key) != value, f"[{section}] {key} is its default"
