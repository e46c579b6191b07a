"""The hand-built maze: the statistics asked for, and rays and truth that follow the real boards."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.config import Config
from mazebot.sim.hand_maze import HandBuild, HandLayout, hand_built_world, hand_geometry
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raster import free_reachable, true_occupancy
from mazebot.sim.raycast import RayCaster
from mazebot.sim.world_source import make_world


@pytest.fixture(scope="module")
def big_layout():
    return generate_maze(16, 16, 5, kind="braided")


def test_geometry_has_the_requested_statistics(big_layout) -> None:
    build = HandBuild()
    pitches = []
    for seed in range(20):
        geo = hand_geometry(big_layout, build, seed)
        pitches.append(geo.pitch_m / big_layout.cell_size_m - 1.0)
        # each row/column of posts within the jitter of its place on the drawn pitch
        ideal = np.arange(17) * geo.pitch_m
        assert np.abs(geo.lines_u_m - ideal).max() <= 2 * build.line_jitter_m + 1e-12
        assert np.abs(geo.lines_v_m - ideal).max() <= 2 * build.line_jitter_m + 1e-12
    pitches = np.array(pitches)
    assert np.all(np.abs(pitches) <= build.pitch_error_max)
    assert np.ptp(pitches) > build.pitch_error_max  # spread over the range, not one value
    geo = hand_geometry(big_layout, build, 3)
    offset, turn, thickness = geo.boards[:, 3], geo.boards[:, 4], geo.boards[:, 5]
    assert len(offset) > 250
    assert abs(np.std(offset) - build.wall_offset_std_m) < 0.15 * build.wall_offset_std_m
    assert abs(np.std(turn) - build.wall_turn_std_rad) < 0.15 * build.wall_turn_std_rad
    assert thickness.min() >= build.wall_thickness_min_m and thickness.max() <= build.wall_thickness_max_m
    assert np.ptp(thickness) > 0.8 * (build.wall_thickness_max_m - build.wall_thickness_min_m)
    assert geo.gaps_m.min() >= build.post_gap_min_m and geo.gaps_m.max() <= build.post_gap_max_m
    assert len(geo.clutter_uv) == build.clutter


def test_same_seed_same_maze_other_seed_other_maze(big_layout) -> None:
    a = hand_built_world(big_layout, HandBuild(), 7)
    b = hand_built_world(big_layout, HandBuild(), 7)
    c = hand_built_world(big_layout, HandBuild(), 8)
    assert np.array_equal(a.segments, b.segments) and a.start_pose == b.start_pose
    assert not np.array_equal(a.segments, c.segments)


def test_rays_hit_the_turned_and_offset_boards() -> None:
    """A ray straight at a board's face from its cell's centre meets the face where the board really stands."""
    layout = generate_maze(4, 4, 2)
    build = HandBuild(maze_angle_rad=math.radians(17.0), wall_offset_std_m=0.006, wall_turn_std_rad=math.radians(1.5))
    world = hand_built_world(layout, build, 11)
    geo = hand_geometry(layout, build, 11)
    caster = RayCaster.for_world(world)
    c, s = math.cos(geo.angle_rad), math.sin(geo.angle_rad)
    checked = 0
    for cu, cv, axis, _offset, turn, thick, _ in geo.boards:
        # a point 0.1 m off the board's centre on its +across side, inside the maze
        normal_uv = np.array([-math.sin(turn), math.cos(turn)]) if axis == 0 else np.array([math.cos(turn),
                                                                                         math.sin(turn)])
        p_uv = np.array([cu, cv]) + 0.1 * normal_uv
        if not (0.05 < p_uv[0] < geo.lines_u_m[-1] - 0.05 and 0.05 < p_uv[1] < geo.lines_v_m[-1] - 0.05):
            continue
        p = np.array([c * p_uv[0] - s * p_uv[1], s * p_uv[0] + c * p_uv[1]])
        n = np.array([c * normal_uv[0] - s * normal_uv[1], s * normal_uv[0] + c * normal_uv[1]])
        d = caster.cast(p, np.array([math.atan2(-n[1], -n[0])]), max_range_m=1.0)[0]
        assert d == pytest.approx(0.1 - 0.5 * thick, abs=1e-9)
        checked += 1
    assert checked > 10


def test_truth_follows_the_real_walls() -> None:
    config = Config()
    config.sim.maze_build = "hand"
    world = make_world(config, None, 4, (6, 6))
    layout = world.maze
    assert isinstance(layout, HandLayout)
    res = 0.01
    occupied, origin = true_occupancy(world, res)
    # every cell centre is free and maps back to its cell; the posts are solid
    for cell in [(0, 0), (2, 3), (5, 5)]:
        x, y = layout.cell_center_m(cell)
        assert layout.cell_at(x, y) == cell
        assert not occupied[int((y - origin[1]) / res), int((x - origin[0]) / res)]
    c, s = math.cos(layout.angle_rad), math.sin(layout.angle_rad)
    u, v = layout.lines_u_m[3], layout.lines_v_m[2]
    post = (c * u - s * v, s * u + c * v)
    assert occupied[int((post[1] - origin[1]) / res), int((post[0] - origin[0]) / res)]
    reach, _ = free_reachable(world, res, config.robot.footprint_radius_m)
    # the reachable floor is the maze's inside, less the walls' and the footprint's share
    inside_m2 = (layout.lines_u_m[-1] - layout.lines_u_m[0]) * (layout.lines_v_m[-1] - layout.lines_v_m[0])
    assert 0.6 * inside_m2 < reach.sum() * res**2 < 0.95 * inside_m2


def test_exact_build_is_todays_maze() -> None:
    config = Config()
    world = make_world(config, None, 4, (6, 6))
    assert type(world.maze) is not HandLayout and world.maze.origin_m == (0.0, 0.0)
    assert np.all((world.segments[:, 0] == world.segments[:, 2]) | (world.segments[:, 1] == world.segments[:, 3]))
