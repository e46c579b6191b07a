"""Everything :class:`mazebot.slam.slam.Slam` is tuned by, as one frozen object: :class:`SlamParams`.

The ``[slam]`` config sections (:mod:`mazebot.slam_config`) *are* the steps' parameter
objects; :class:`SlamParams` holds them side by side with the façade's own sections and
takes from ``[lidar]`` and ``[planner]`` what the steps need of them (the lidar's range
and mount, the maze's cell size). ``SlamParams()`` is the daemon's SLAM with the default
config; :meth:`SlamParams.from_config` builds it from any config, once, at the edge.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from mazebot.config import LidarConfig, PlannerConfig
from mazebot.slam.correlative import CorrelativeParams
from mazebot.slam.ekf import MotionNoise
from mazebot.slam.endpoint_smoothing import EndpointSmoothing
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.icp import IcpParams
from mazebot.slam.keyframes import NormalParams
from mazebot.slam.loop_closure import LoopClosureParams
from mazebot.slam.preprocess import PrepareParams
from mazebot.slam.wall_lattice import LatticeParams
from mazebot.slam_config import (
    FACADE_SECTIONS,
    FilterSection,
    GraphSection,
    GridSection,
    KeyframeSection,
    MapSection,
    MatchingSection,
    SlamConfig,
    WallSection,
    as_params,
    section_values,
)


@dataclass(frozen=True)
class GridParams(GridSection):
    """Occupancy grid settings, the ``[slam.grid]`` section (see :class:`mazebot.slam.grid.OccupancyGrid`),
    the lidar's minimum range: beams erase no occupied cell that close (the sensor cannot see there), and
    ``[slam.map] map_max_range_m``: nor farther than hits mark walls (too imprecise there to erase one)."""

    blind_range_m: float = LidarConfig().min_range_m
    wall_range_m: float | None = MapSection().map_max_range_m

    def new_grid(self) -> OccupancyGrid:
        return OccupancyGrid(**section_values(self))


def _daemon_default(part: str) -> Any:
    """The default of one of :class:`SlamParams`' nested parts: the daemon's, built from the default config."""
    return lambda: getattr(SlamParams.from_config(SlamConfig(), LidarConfig(), PlannerConfig()), part)


@dataclass(frozen=True)
class SlamParams(FilterSection, MatchingSection, KeyframeSection, GraphSection, WallSection, MapSection):
    """Everything :class:`Slam` is tuned by: the ``[slam]`` config and what it takes from ``[lidar]`` and ``[planner]``.

    The façade's own values are the fields of the ``[slam.filter]``, ``[slam.matching]``,
    ``[slam.keyframes]``, ``[slam.graph]``, ``[slam.walls]`` and ``[slam.map]`` sections
    side by side; the steps' parameters are the other sections. ``SlamParams()`` is the
    daemon's SLAM with the default config; ``from_config`` builds it from any config.
    """

    prepare: PrepareParams = field(default_factory=_daemon_default("prepare"))
    icp: IcpParams = field(default_factory=_daemon_default("icp"))
    normals: NormalParams = field(default_factory=_daemon_default("normals"))
    motion: MotionNoise = field(default_factory=_daemon_default("motion"))
    loop: LoopClosureParams = field(default_factory=_daemon_default("loop"))
    grid: GridParams = field(default_factory=_daemon_default("grid"))
    # hits moved along their beams onto their local wall line before mapping (None: as measured)
    map_smoothing: EndpointSmoothing | None = field(default_factory=_daemon_default("map_smoothing"))
    # the correlative search before ICP where the prediction is uncertain (None: ICP and its retries alone)
    correlative: CorrelativeParams | None = field(default_factory=_daemon_default("correlative"))
    # the walls lie on a square lattice of this pitch: a position prior per keyframe (None: no lattice)
    lattice: LatticeParams | None = field(default_factory=_daemon_default("lattice"))

    @classmethod
    def from_config(cls, slam: SlamConfig, lidar: LidarConfig, planner: PlannerConfig | None = None) -> SlamParams:
        """From the ``[slam]``, ``[lidar]`` and ``[planner]`` config sections (plain values only from here on).

        Each section carries over field by field; what is built here is only what one
        section takes from another or what a switch turns off. Without ``planner`` (a laser
        log, not a maze) there is no wall lattice; with it, and ``wall_lattice`` and
        ``walls.wall_prior`` on, the keyframes' wall faces are tied to the lattice of its
        cell size, or of the pitch measured within ``cell_size_search`` of it.
        """
        lattice = None
        if planner is not None and slam.wall_lattice and slam.walls.wall_prior:
            lattice = as_params(
                LatticeParams, slam.lattice, pitch_m=planner.cell_size_m, pitch_search=planner.cell_size_search
            )
        loop_search = None
        if slam.loop_corr_window_m > 0 or slam.loop_corr_window_rad > 0:
            loop_search = replace(
                slam.search,
                window_xy_m=slam.loop_corr_window_m,
                window_theta_rad=slam.loop_corr_window_rad,
                levels=slam.loop_corr_levels,
            )
        facade = {name: v for part in FACADE_SECTIONS for name, v in section_values(getattr(slam, part)).items()}
        facade["map_max_range_m"] = slam.map.map_max_range_m or None
        loop = as_params(LoopClosureParams, replace(slam.loop, max_range_m=slam.loop.max_range_m or None),
                         search=loop_search)
        return cls(
            **facade,
            prepare=as_params(
                PrepareParams,
                replace(slam.prepare, max_range_m=min(slam.prepare.max_range_m, lidar.max_range_m)),
                min_range_m=lidar.min_range_m,
                mount_x_m=lidar.mount_x_m,
                mount_y_m=lidar.mount_y_m,
                mount_yaw_rad=0.0,  # the driver already turned the angles into the robot frame
            ),
            icp=slam.icp,
            normals=slam.normals,
            motion=as_params(MotionNoise, slam.motion),
            loop=loop,
            grid=as_params(GridParams, slam.grid, blind_range_m=lidar.min_range_m,
                           wall_range_m=slam.map.map_max_range_m or None),
            map_smoothing=slam.smoothing if slam.map_smooth_endpoints else None,
            correlative=slam.search if slam.correlative else None,
            lattice=lattice,
        )
