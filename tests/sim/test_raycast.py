"""Ray casting and obstacle distances against hand-computed geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.sim import raycast
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import RayCaster, cast_rays, distance_to_obstacles, distance_to_segments
from mazebot.sim.world import World, rectangles_outline, world_from_layout

NO_CIRCLES = np.zeros((0, 3))
NO_SEGMENTS = np.zeros((0, 4))


def test_perpendicular_wall() -> None:
    wall = np.array([[1.0, -1.0, 1.0, 1.0]])
    d = cast_rays(np.array([0.0, 0.0]), np.array([0.0, np.pi]), wall, NO_CIRCLES, 10.0)
    assert d[0] == pytest.approx(1.0)
    assert np.isinf(d[1])  # facing away


def test_oblique_wall() -> None:
    # the line x + y = 2 between (2, 0) and (0, 2)
    wall = np.array([[2.0, 0.0, 0.0, 2.0]])
    angles = np.radians([0.0, 30.0, 45.0, 90.0, 135.0])
    d = cast_rays(np.zeros(2), angles, wall, NO_CIRCLES, 10.0)
    expected = [2.0, 2.0 / (math.cos(math.radians(30)) + math.sin(math.radians(30))), math.sqrt(2.0), 2.0]
    assert d[:4] == pytest.approx(expected)
    assert np.isinf(d[4])  # parallel to the wall


def test_segment_end_point_is_hit() -> None:
    wall = np.array([[1.0, 0.0, 1.0, 1.0]])
    d = cast_rays(np.zeros(2), np.array([0.0, math.atan2(1.0, 1.0), 1.0]), wall, NO_CIRCLES, 10.0)
    assert d[0] == pytest.approx(1.0)
    assert d[1] == pytest.approx(math.sqrt(2.0))
    assert np.isinf(d[2])  # passes above the top end (y = tan(1) > 1 at x = 1)


def test_circle_front_offset_and_tangent() -> None:
    circle = np.array([[3.0, 0.0, 0.5]])
    d = cast_rays(np.zeros(2), np.array([0.0]), NO_SEGMENTS, circle, 10.0)
    assert d[0] == pytest.approx(2.5)
    # origin 0.3 m to the side: the chord is at x = 3 - sqrt(0.5^2 - 0.3^2) = 2.6
    d = cast_rays(np.array([0.0, 0.3]), np.array([0.0]), NO_SEGMENTS, circle, 10.0)
    assert d[0] == pytest.approx(2.6)
    tangent = math.asin(0.5 / 3.0)
    d = cast_rays(np.zeros(2), np.array([tangent - 1e-10, tangent + 1e-3]), NO_SEGMENTS, circle, 10.0)
    assert d[0] == pytest.approx(math.sqrt(3.0**2 - 0.5**2), abs=1e-3)
    assert np.isinf(d[1])


def test_ray_starting_inside_a_circle_reports_its_surface() -> None:
    circle = np.array([[3.0, 0.0, 0.5]])
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    d = cast_rays(np.array([3.0, 0.0]), angles, NO_SEGMENTS, circle, 10.0)
    assert d == pytest.approx(np.full(8, 0.5))


def test_ray_starting_inside_a_room_hits_every_wall() -> None:
    # room [0, 2] x [0, 1] with 0.1 m walls outside it
    t = 0.1
    walls = np.array([(-t, -t, 2 + t, 0), (-t, 1, 2 + t, 1 + t), (-t, -t, 0, 1 + t), (2, -t, 2 + t, 1 + t)])
    segments = rectangles_outline(walls)
    assert segments.shape == (8, 4)  # an inner and an outer loop of 4 sides each
    origin = np.array([0.5, 0.25])
    angles = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2, np.pi / 4])
    d = cast_rays(origin, angles, segments, NO_CIRCLES, 10.0)
    assert d == pytest.approx([1.5, 0.75, 0.5, 0.25, 0.75 * math.sqrt(2.0)])


def test_misses_and_range_limit() -> None:
    wall = np.array([[5.0, -1.0, 5.0, 1.0]])
    circle = np.array([[0.0, 5.0, 0.2]])
    angles = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2])
    d = cast_rays(np.zeros(2), angles, wall, circle, 12.0)
    assert d[0] == pytest.approx(5.0)
    assert d[1] == pytest.approx(4.8)
    assert np.isinf(d[2:]).all()
    short = cast_rays(np.zeros(2), angles, wall, circle, 4.9, miss_value=0.0)
    assert short.tolist() == [0.0, pytest.approx(4.8), 0.0, 0.0]
    assert cast_rays(np.zeros(2), np.zeros(3), NO_SEGMENTS, NO_CIRCLES, 1.0).tolist() == [np.inf] * 3
    assert cast_rays(np.zeros(2), np.zeros(0), wall, circle, 1.0).shape == (0,)


def test_per_ray_origins() -> None:
    # the robot drives towards the wall during the revolution: each ray its own origin
    wall = np.array([[1.0, -1.0, 1.0, 1.0]])
    xs = np.linspace(0.0, 0.5, 6)
    origins = np.column_stack([xs, np.zeros(6)])
    d = cast_rays(origins, np.zeros(6), wall, NO_CIRCLES, 10.0)
    assert d == pytest.approx(1.0 - xs)
    circle = np.array([[0.0, 2.0, 0.5]])
    d = cast_rays(origins, np.full(6, np.pi / 2), NO_SEGMENTS, circle, 10.0)
    assert d[0] == pytest.approx(1.5)
    assert d[1] == pytest.approx(2.0 - math.sqrt(0.25 - 0.01))
    with pytest.raises(ValueError, match="origins_xy"):
        cast_rays(origins[:3], np.zeros(6), wall, NO_CIRCLES, 10.0)


def _rotate_segments(segments: np.ndarray, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    out = segments.copy()
    out[:, [0, 2]] = c * segments[:, [0, 2]] - s * segments[:, [1, 3]]
    out[:, [1, 3]] = s * segments[:, [0, 2]] + c * segments[:, [1, 3]]
    return out


def test_general_path_agrees_with_axis_aligned_path_on_a_rotated_maze() -> None:
    # Maze walls are axis aligned and take the shortcut; rotated they take the general
    # ray-segment test. Both must see the same distances.
    world = world_from_layout(generate_maze(8, 8, seed=3, kind="braided"))
    rng = np.random.default_rng(0)
    origins = rng.uniform(0.2, 8 * 0.3048 - 0.2, size=(500, 2))
    angles = rng.uniform(-np.pi, np.pi, size=500)
    straight = cast_rays(origins, angles, world.segments, NO_CIRCLES, 12.0)
    turn = 0.3
    c, s = math.cos(turn), math.sin(turn)
    turned_origins = origins @ np.array([[c, s], [-s, c]])
    turned = cast_rays(turned_origins, angles + turn, _rotate_segments(world.segments, turn), NO_CIRCLES, 12.0)
    assert np.isfinite(straight).all()  # closed maze: every ray hits
    assert turned == pytest.approx(straight, abs=1e-9)


def test_chunking_gives_the_same_answer(monkeypatch: pytest.MonkeyPatch) -> None:
    world = world_from_layout(generate_maze(6, 6, seed=2))
    angles = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    origin = np.array(world.start_pose[:2])
    whole = cast_rays(origin, angles, world.segments, world.circles, 12.0)
    monkeypatch.setattr(raycast, "CHUNK_ELEMENTS", 7)
    assert cast_rays(origin, angles, world.segments, world.circles, 12.0) == pytest.approx(whole)


def test_distance_to_obstacles() -> None:
    world = World(
        name="box",
        segments=np.array([[1.0, -1.0, 1.0, 1.0]]),
        circles=np.array([[-2.0, 0.0, 0.5]]),
        start_pose=(0.0, 0.0, 0.0),
        bounds_m=(-3.0, -2.0, 2.0, 2.0),
    )
    points = np.array(
        [
            [0.0, 0.0],  # 1 m from the wall, 1.5 m from the cylinder surface
            [1.0, 3.0],  # beyond the wall's top end: distance to the end point
            [-2.0, 0.2],  # inside the cylinder
            [-1.0, 0.0],  # 0.5 m from the cylinder, 2 m from the wall
            [4.0, 5.0],  # to the end point (1, 1)
        ]
    )
    d = distance_to_obstacles(points, world)
    assert d == pytest.approx([1.0, 2.0, 0.0, 0.5, 5.0])
    assert distance_to_segments(points, NO_SEGMENTS).tolist() == [np.inf] * 5


def test_ray_caster_reuses_its_preparation() -> None:
    world = world_from_layout(generate_maze(5, 5, seed=9, kind="rooms"))
    caster = RayCaster.for_world(world)
    origin = np.array(world.start_pose[:2])
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    expected = cast_rays(origin, angles, world.segments, world.circles, 3.0, miss_value=0.0)
    for lo in range(0, 90, 10):  # small batches, as the lidar emulator sends them
        got = caster.cast(origin, angles[lo : lo + 10], max_range_m=3.0, miss_value=0.0)
        assert got == pytest.approx(expected[lo : lo + 10])
