"""Synthetic lidar data for the SLAM building blocks, cast in simulator worlds.

Fixtures hand out worlds and small factories (pytest's importlib mode makes conftest
helpers unimportable, so the helpers travel as fixtures):

- ``maze_world``: a 6x6 braided maze of 1 ft cells with 12 mm walls.
- ``corridor_world``: two parallel walls 20 m long and one cell apart, no cross wall.
- ``room_world``: a dead-end cell whose open side leads into a 1.8 m × 1.2 m room.
- ``cast_scan(world, pose, ...)``: one static revolution as (angles, ranges) in the lidar frame.
- ``moving_scan(world, pose_at_time, ...)``: a :class:`Scan` whose samples are taken from
  the pose at each sample's own time, like the real spinning head.
- ``world_surface(world, spacing_m)``: points along every wall face with their normals
  (pointing into free space), the ground-truth map for ICP.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mazebot.io.scan import Scan
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import cast_rays
from mazebot.sim.world import World, rectangles_outline, world_from_layout
from tests.data_paths import CARMEN, carmen_log

CELL_M = 0.3048
WALL_M = 0.012
INTEL_LOG = CARMEN / "intel.gfs.log"

CastScan = Callable[..., tuple[np.ndarray, np.ndarray]]
MovingScan = Callable[..., Scan]
WorldSurface = Callable[..., tuple[np.ndarray, np.ndarray]]


@pytest.fixture(scope="session")
def intel_log_path() -> Path:
    """The Intel Research Lab CARMEN log (910 scans, GMapping-corrected poses); skips without it."""
    return carmen_log(INTEL_LOG.name)


@pytest.fixture(scope="session")
def maze_world() -> World:
    return world_from_layout(generate_maze(6, 6, seed=3, kind="braided"), WALL_M)


@pytest.fixture(scope="session")
def corridor_world() -> World:
    """A straight corridor along x, one cell wide, far longer than the lidar's range."""
    half = CELL_M / 2
    rects = np.array(
        [
            [-10.0, -half - WALL_M / 2, 10.0, -half + WALL_M / 2],
            [-10.0, half - WALL_M / 2, 10.0, half + WALL_M / 2],
        ]
    )
    return World(
        name="corridor",
        segments=rectangles_outline(rects),
        circles=np.zeros((0, 3)),
        start_pose=(0.0, 0.0, 0.0),
        bounds_m=(-10.0, -half - WALL_M, 10.0, half + WALL_M),
    )


@pytest.fixture(scope="session")
def room_world() -> World:
    """A dead-end cell (the robot at its centre, facing its open side) that opens into a room.

    From the cell the lidar sees the room through the opening only; 0.2 m further, at the
    opening, it sees the walls on either side of it too: the view of an exploring robot at
    the edge of what it has mapped.
    """
    h = WALL_M / 2
    c = CELL_M / 2
    rects = np.array(
        [
            [-c - h, -c - h, c + h, -c + h],  # the dead end's back wall
            [-c - h, -c - h, -c + h, c + h],  # its left and right walls
            [c - h, -c - h, c + h, c + h],
            [-0.9 - h, c - h, -c + h, c + h],  # the room's near wall, left and right of the opening
            [c - h, c - h, 0.9 + h, c + h],
            [-0.9 - h, c - h, -0.9 + h, 1.35 + h],  # the room's side walls and far wall
            [0.9 - h, c - h, 0.9 + h, 1.35 + h],
            [-0.9 - h, 1.35 - h, 0.9 + h, 1.35 + h],
        ]
    )
    return World(
        name="room",
        segments=rectangles_outline(rects),
        circles=np.zeros((0, 3)),
        start_pose=(0.0, 0.0, np.pi / 2),
        bounds_m=(-0.9 - WALL_M, -c - WALL_M, 0.9 + WALL_M, 1.35 + WALL_M),
    )


@pytest.fixture
def cast_scan() -> CastScan:
    """``cast_scan(world, pose, n=360, noise_rel=0.0, seed=0, max_range_m=12.0, mount=(0, 0, 0))``.

    Returns (angles_rad, ranges_m) in the lidar frame (CCW, 0 ahead); ``inf`` where no
    wall is within range. ``noise_rel`` is the range noise std as a fraction of the
    range (the A1's is about 1 %). ``mount`` places the lidar on the robot.
    """

    def cast(
        world: World,
        pose: np.ndarray,
        n: int = 360,
        noise_rel: float = 0.0,
        seed: int = 0,
        max_range_m: float = 12.0,
        mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> tuple[np.ndarray, np.ndarray]:
        x, y, th = pose
        mx, my, myaw = mount
        origin = np.array([x + mx * np.cos(th) - my * np.sin(th), y + mx * np.sin(th) + my * np.cos(th)])
        angles = np.linspace(-np.pi, np.pi, n, endpoint=False)
        ranges = cast_rays(origin, angles + th + myaw, world.segments, world.circles, max_range_m)
        if noise_rel:
            ranges = ranges * (1.0 + noise_rel * np.random.default_rng(seed).standard_normal(n))
        return angles, ranges

    return cast


@pytest.fixture
def moving_scan() -> MovingScan:
    """``moving_scan(world, pose_at_time, t0_s=0.0, period_s=1/5.5, n=360, noise_rel=0.0, seed=0, mount=(0,0,0))``.

    Sample ``i`` is taken at ``t0 + (i + 1) * period / n`` from ``pose_at_time(t)``,
    the lidar turning counter-clockwise from -180 degrees; no-return samples are invalid.
    """

    def scan(
        world: World,
        pose_at_time: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]],
        t0_s: float = 0.0,
        period_s: float = 1.0 / 5.5,
        n: int = 360,
        noise_rel: float = 0.0,
        seed: int = 0,
        mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> Scan:
        times = t0_s + (np.arange(n) + 1) * (period_s / n)
        angles = np.linspace(-np.pi, np.pi, n, endpoint=False)
        x, y, th = (np.asarray(v, dtype=np.float64) for v in pose_at_time(times))
        mx, my, myaw = mount
        origins = np.column_stack((x + mx * np.cos(th) - my * np.sin(th), y + mx * np.sin(th) + my * np.cos(th)))
        ranges = cast_rays(origins, angles + th + myaw, world.segments, world.circles, 12.0)
        if noise_rel:
            ranges = ranges * (1.0 + noise_rel * np.random.default_rng(seed).standard_normal(n))
        valid = np.isfinite(ranges)
        return Scan(
            angle_rad=angles,
            range_m=np.where(valid, ranges, 0.0),
            quality=np.where(valid, 47, 0).astype(np.uint8),
            time_s=times,
            valid=valid,
        )

    return scan


@pytest.fixture
def world_surface() -> WorldSurface:
    """``world_surface(world, spacing_m=0.01)`` -> (points (M, 2), normals (M, 2)) along every wall face."""

    def surface(world: World, spacing_m: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        pts, nrm = [], []
        for x1, y1, x2, y2 in world.segments:
            length = float(np.hypot(x2 - x1, y2 - y1))
            n = max(2, int(np.ceil(length / spacing_m)) + 1)
            u = np.linspace(0.0, 1.0, n)
            pts.append(np.column_stack((x1 + u * (x2 - x1), y1 + u * (y2 - y1))))
            # segments have the solid on their left: the right-hand normal faces free space
            nrm.append(np.tile([(y2 - y1) / length, -(x2 - x1) / length], (n, 1)))
        return np.concatenate(pts), np.concatenate(nrm)

    return surface


def straight_line_motion(
    start: np.ndarray, speed_mps: float, yaw_rate_radps: float
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Exact constant-velocity arc motion from ``start`` at time 0: a ``pose_at_time``."""

    def pose_at(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=np.float64)
        th = start[2] + yaw_rate_radps * t
        if abs(yaw_rate_radps) < 1e-12:
            return start[0] + speed_mps * t * np.cos(th), start[1] + speed_mps * t * np.sin(th), th
        r = speed_mps / yaw_rate_radps
        return start[0] + r * (np.sin(th) - np.sin(start[2])), start[1] - r * (np.cos(th) - np.cos(start[2])), th

    return pose_at


@pytest.fixture
def arc_motion() -> Callable[..., Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """``arc_motion(start_pose, speed_mps, yaw_rate_radps)`` -> ``pose_at_time`` of a constant-velocity arc."""
    return straight_line_motion
