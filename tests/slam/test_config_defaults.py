"""The defaults each SLAM step sees are the config's: one source for every tuning value.

The daemon builds its parameters from the config (``SlamParams.from_config``); a step's
parameter object built without arguments (in tests, benches, offline tools) must be the
same SLAM, not one the robot never runs.
"""

from __future__ import annotations

import dataclasses

from mazebot.config import Config
from mazebot.slam.correlative import CorrelativeParams
from mazebot.slam.ekf import MotionNoise
from mazebot.slam.endpoint_smoothing import EndpointSmoothing
from mazebot.slam.icp import IcpParams
from mazebot.slam.keyframes import NormalParams
from mazebot.slam.loop_closure import LoopClosureParams
from mazebot.slam.preprocess import PrepareParams
from mazebot.slam.slam import GridParams, SlamParams
from mazebot.slam.wall_lattice import LatticeParams


def _daemon() -> SlamParams:
    config = Config()
    return SlamParams.from_config(config.slam, config.lidar, config.planner)  # as mazebot.main builds it


def test_slam_params_without_arguments_are_the_daemons() -> None:
    assert SlamParams() == _daemon()


def test_each_steps_defaults_are_the_daemons() -> None:
    daemon = _daemon()
    assert IcpParams() == daemon.icp
    assert NormalParams() == daemon.normals
    assert MotionNoise() == daemon.motion
    assert GridParams() == daemon.grid
    assert PrepareParams() == daemon.prepare
    assert LatticeParams() == daemon.lattice
    assert EndpointSmoothing() == daemon.map_smoothing
    assert CorrelativeParams() == daemon.correlative
    assert LoopClosureParams(search=daemon.loop.search) == daemon.loop


def test_the_facades_own_values_are_the_config_sections() -> None:
    config, daemon = Config(), _daemon()
    for part in ("filter", "matching", "keyframes", "graph", "walls", "map"):
        section = getattr(config.slam, part)
        for f in dataclasses.fields(section):
            assert getattr(daemon, f.name) == getattr(section, f.name), f"slam.{part}.{f.name}"


def test_the_values_that_had_drifted_are_the_configs() -> None:
    """Before the sections, the steps' own defaults differed from the config's here; the config's held."""
    params = SlamParams()
    assert params.map_hit_depth_m == 0.006
    assert params.prepare.max_range_m == 8.0
    assert params.lattice is not None and params.lattice.pitch_search == 0.08
    assert params.loop.search is not None and params.loop.search.window_xy_m == 0.1


def test_the_maze_pitch_is_the_planners() -> None:
    config = Config()
    config.planner.cell_size_m = 0.25
    params = SlamParams.from_config(config.slam, config.lidar, config.planner)
    assert params.lattice is not None and params.lattice.pitch_m == 0.25
