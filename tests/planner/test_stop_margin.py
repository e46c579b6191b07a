"""The planner and the emergency stop keep the same margin ahead.

``[control] stop_margin_m`` is the free distance the safety layer keeps beyond the
stopping distance. The DWA must count the same margin when it calls an arc admissible,
or a larger setting makes the safety layer stop arcs the planner chose as safe: the
robot would brake, re-plan the same arc, and stutter towards every wall.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.config import parse_config
from mazebot.planner.dwa import LocalCostmap, PathTrack
from mazebot.planner.pilot import Pilot, PilotParams
from mazebot.tasks.control_task import MotorControl


def wall_ahead(distance_m: float) -> np.ndarray:
    """Robot-frame points of a wall across the path, ``distance_m`` ahead, sampled every 5 mm."""
    y = np.arange(-0.5, 0.5, 0.005)
    return np.column_stack((np.full_like(y, distance_m), y))


@pytest.mark.parametrize("stop_margin_m", [0.03, 0.12, 0.25])
def test_no_arc_the_planner_chooses_is_one_the_emergency_stop_refuses(stop_margin_m: float) -> None:
    config = parse_config({"control": {"stop_margin_m": stop_margin_m}})
    dwa = Pilot(PilotParams.from_config(config)).local.dwa
    guard = MotorControl.from_config(config).safety.guard
    assert dwa.stop_margin_m == guard.margin_m == stop_margin_m
    chosen_moving = 0
    for distance_m in np.arange(0.2, 0.8, 0.02):
        wall = wall_ahead(float(distance_m))
        for v0 in (0.0, 0.1, 0.2):
            costmap = LocalCostmap(wall, footprint_radius_m=dwa.footprint_radius_m, clearance_m=dwa.clearance_m)
            choice = dwa.plan((0.0, 0.0, 0.0), (v0, 0.0), costmap, PathTrack([(0.0, 0.0), (2.0, 0.0)]))
            if choice.v_mps <= 0.0:
                continue
            chosen_moving += 1
            verdict = guard.check(wall, choice.v_mps, choice.w_radps)
            assert not verdict.stop, (
                f"wall {distance_m:.2f} m ahead, v0 {v0}: the planner chose "
                f"({choice.v_mps:.3f} m/s, {choice.w_radps:.3f} rad/s), the guard said {verdict.reason}"
            )
    assert chosen_moving > 10  # the planner drove towards the wall before stopping short of it
    assert math.isfinite(dwa.stopping_distance_m(0.2))
