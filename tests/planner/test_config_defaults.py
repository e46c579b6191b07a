"""The planner's keyword defaults that name a config key are that key's default (written once, in the config)."""

from __future__ import annotations

import inspect

import pytest

from mazebot.config import Config
from mazebot.planner import dwa, exploration, global_path, maze_graph, safety, wheel_control

#: Argument name -> the config section that owns it.
OWNER = {
    "strategy": "planner", "mode": "planner", "goal_tolerance_m": "planner", "progress_revolutions": "planner",
    "dwell_revolutions": "planner", "retry_after_m": "planner", "max_attempts": "planner", "horizon_s": "planner",
    "stuck_timeout_s": "planner", "max_recoveries": "planner", "wall_thickness_m": "planner", "cell_size_m": "planner",
    "footprint_radius_m": "robot", "clearance_m": "robot",
    "track_width_m": "drive", "max_wheel_speed_mps": "drive", "max_speed_mps": "drive", "max_yaw_rate_radps": "drive",
    "max_accel_mps2": "drive", "max_yaw_accel_radps2": "drive",
    "integral_limit": "control", "max_wheel_accel_mps2": "control", "brake_decel_mps2": "control",
    "command_ttl_ticks": "control", "scan_timeout_ticks": "control", "stop_margin_m": "control",
    "deadline_s": "control",
    "min_range_m": "lidar", "max_range_m": "lidar",
}

#: Same name, another quantity: the local planner's arrival tolerance is under the explorer's
#: (the pilot passes min(0.04, 0.7 × goal_tolerance_m)).
NOT_THE_KEY = {("LocalPlanner", "goal_tolerance_m")}

MODULES = (dwa, exploration, global_path, maze_graph, safety, wheel_control)


def _defaults() -> list[tuple[str, str, object]]:
    found = []
    for module in MODULES:
        for name, obj in vars(module).items():
            if getattr(obj, "__module__", None) != module.__name__ or name.startswith("_"):
                continue
            target = obj.__init__ if inspect.isclass(obj) else obj
            if not callable(target):
                continue
            try:
                parameters = inspect.signature(target).parameters
            except (TypeError, ValueError):
                continue
            for arg, p in parameters.items():
                if arg in OWNER and p.default is not inspect.Parameter.empty and (name, arg) not in NOT_THE_KEY:
                    found.append((name, arg, p.default))
    return found


@pytest.mark.parametrize(("owner", "arg", "default"), _defaults())
def test_a_planner_default_is_the_configs(owner: str, arg: str, default: object) -> None:
    section = getattr(Config(), OWNER[arg])
    assert default == getattr(section, arg), f"{owner}({arg}=...) vs {OWNER[arg]}.{arg}"


def test_the_planner_defaults_are_checked_at_all() -> None:
    assert len(_defaults()) >= 40
