"""Each wall face's own direction, and whether the faces seen from the start lie on one grid.

Against ground truth: boards of known turns drawn as lidar-like points; and the starts of
simulated mazes, built exactly and by hand, seen by a Slam standing there.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.config import Config
from mazebot.io.scan import Scan
from mazebot.sim.hand_maze import HandBuild, hand_geometry
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.world_source import make_world
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.slam import Slam, SlamParams
from mazebot.slam.wall_faces import Faces, face_spread, face_turns, quarter_turns


def board(centre: tuple[float, float], along_rad: float, length_m: float, normal_sign: float,
          rng: np.random.Generator, noise_m: float = 0.001) -> tuple[np.ndarray, np.ndarray]:
    """Points every 5 mm along a straight face through ``centre`` running at ``along_rad``, and its normals."""
    t = np.arange(-length_m / 2, length_m / 2, 0.005)
    direction = np.array([math.cos(along_rad), math.sin(along_rad)])
    normal = normal_sign * np.array([-direction[1], direction[0]])
    pts = np.asarray(centre) + t[:, None] * direction + rng.normal(0.0, noise_m, (t.size, 1)) * normal
    return pts, np.tile(normal, (t.size, 1))


@pytest.mark.parametrize("grid_deg", [0.0, 17.0, -38.0])
def test_each_board_s_turn_is_recovered_and_their_spread(grid_deg: float) -> None:
    rng = np.random.default_rng(1)
    grid = math.radians(grid_deg)
    turns_deg = {"left": 0.7, "right": -0.4, "ahead": 0.1}
    c, s = math.cos(grid), math.sin(grid)
    parts = [  # a corridor's two sides and the wall across its end, in the grid's frame, then turned onto it
        board((c * 0.0 - s * 0.15, s * 0.0 + c * 0.15), grid + math.radians(turns_deg["left"]), 0.5, -1.0, rng),
        board((c * 0.0 + s * 0.15, s * 0.0 - c * 0.15), grid + math.radians(turns_deg["right"]), 0.5, 1.0, rng),
        board((c * 0.45, s * 0.45), grid + math.pi / 2 + math.radians(turns_deg["ahead"]), 0.28, 1.0, rng),
    ]
    points = np.concatenate([p for p, _ in parts])
    normals = np.concatenate([n for _, n in parts])
    turns, counts = face_turns(points, normals, grid)
    assert sorted(np.degrees(turns)) == pytest.approx(sorted(turns_deg.values()), abs=0.1)
    expected = np.array(list(turns_deg.values()))
    weights = np.array([100, 100, 56])  # the points of each face (5 mm apart)
    mean = np.average(expected, weights=weights)
    rms = math.sqrt(np.average((expected - mean) ** 2, weights=weights))
    spread = face_spread(turns, counts)
    assert spread is not None and math.degrees(spread) == pytest.approx(rms, abs=0.05)


def test_one_face_gives_no_spread_and_a_post_is_no_face() -> None:
    rng = np.random.default_rng(2)
    pts, nrm = board((0.2, 0.0), math.pi / 2, 0.4, -1.0, rng)
    angles = np.linspace(0.0, math.tau, 40, endpoint=False)
    round_side = np.column_stack((np.cos(angles), np.sin(angles)))  # a 12 mm post's outward normals
    post = np.array([0.0, 0.3]) + 0.006 * round_side
    turns, counts = face_turns(np.concatenate((pts, post)), np.concatenate((nrm, round_side)), 0.0)
    assert turns.size == 1
    assert face_spread(turns, counts) is None


def standing_slam(world_build: str, seed: int, cast_scan, size: tuple[int, int] = (6, 6)) -> Slam:
    """A Slam that stood ``anchor_revolutions`` at the start of a bench maze (its pose exact), then moved."""
    config = Config()
    config.sim.maze_build = world_build
    world = make_world(config, None, seed, size)
    history = OdometryHistory()
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(100.0, 0.0, 0.0, 0.0)
    slam = Slam(SlamParams())
    pose = np.array(world.start_pose)
    for k in range(slam.params.anchor_revolutions):
        angles, ranges = cast_scan(world, pose, noise_rel=0.01, seed=k)
        valid = np.isfinite(ranges)
        times = np.linspace(0.2 * k, 0.2 * k + 0.18, 360)
        slam.update(Scan(angles, np.where(valid, ranges, 0.0), np.full(360, 47, np.uint8), times, valid), history)
    assert slam.anchored
    return slam


@pytest.mark.parametrize(("seed", "hand_min_deg"), [(1, 0.2), (3, 0.35), (8, 0.35)])
def test_boards_set_by_hand_turn_the_start_s_faces_apart_and_exact_walls_do_not(
    seed: int, hand_min_deg: float, cast_scan
) -> None:
    # the bench's hand-built 6x6 mazes of these seeds: the faces seen from the start turn 0.24-0.85 deg
    # apart (RMS; seed 1's boards there turn least, 0.24 deg once the two pairs of boards in line are
    # cut apart at their steps); the same mazes cut exactly: 0.1-0.15 deg (the lidar's noise on the
    # faces' directions)
    hand = standing_slam("hand", seed, cast_scan)
    assert hand.anchor_face_spread_rad is not None and math.degrees(hand.anchor_face_spread_rad) > hand_min_deg
    exact = standing_slam("exact", seed, cast_scan)
    assert exact.anchor_face_spread_rad is not None and math.degrees(exact.anchor_face_spread_rad) < 0.2
    assert exact.anchor_on_grid


def faces_against_boards(
    seed: int, size: tuple[int, int], start: np.ndarray, faces: Faces
) -> list[tuple[float, np.ndarray]]:
    """Each face seen from ``start`` (world pose) in the bench's hand-built maze: its turn on the maze's grid
    and the true turns of the boards under it (radians).

    A board is under a face where it lies on the face's side of the grid, within 3 cm across
    of the face's centre, and overlaps its length by more than 2 cm.
    """
    config = Config()
    layout = generate_maze(*size, seed, kind=config.sim.maze_kind, cell_size_m=config.sim.cell_size_m)
    geometry = hand_geometry(layout, HandBuild.from_sim(config.sim), seed)
    boards, angle = geometry.boards, geometry.angle_rad
    placed = faces.placed(start)
    c, s = math.cos(angle), math.sin(angle)
    u = c * placed.centre_xy[:, 0] + s * placed.centre_xy[:, 1]
    v = -s * placed.centre_xy[:, 0] + c * placed.centre_xy[:, 1]
    turns = quarter_turns(placed.normal_rad - angle)
    out = []
    for k in range(len(faces)):
        along_v = abs(math.cos(placed.normal_rad[k] - angle)) > 0.7  # the normal along u: a board along v
        across = np.where(boards[:, 2] == 0, np.abs(v[k] - boards[:, 1]), np.abs(u[k] - boards[:, 0]))
        along = np.where(boards[:, 2] == 0, np.abs(u[k] - boards[:, 0]), np.abs(v[k] - boards[:, 1]))
        overlap = boards[:, 6] / 2 + faces.half_length_m[k] - along
        out.append((float(turns[k]), boards[(boards[:, 2] == int(along_v)) & (across < 0.03) & (overlap > 0.02), 4]))
    return out


@pytest.mark.parametrize("seed", [1, 6, 9])
def test_the_faces_seen_at_rest_measure_the_boards_under_them_not_the_steps_between_boards_in_line(
    seed: int, cast_scan
) -> None:
    # the bench's hand-built 8x8 mazes: from the start of seed 6 two boards in line, turned +0.21 deg and
    # -0.75 deg, their faces a few millimetres apart across, were one face turned -2.1 deg, and the map
    # turned about the start by half a degree with the anchor it made; seeds 1 and 9 the same kind of
    # face, 0.7-1.2 deg off its boards. Cut at their steps every face stands within 0.35 deg of the
    # mean turn of the boards under it (the lidar's 1 % noise, a board's ends beside a post)
    slam = standing_slam("hand", seed, cast_scan, size=(8, 8))
    assert slam.anchor_face_spread_rad is not None  # judges the faces at rest
    faces = slam._start_faces
    assert faces is not None and len(faces) >= 3
    config = Config()
    config.sim.maze_build = "hand"
    start = np.array(make_world(config, None, seed, (8, 8)).start_pose)
    for turn, under in faces_against_boards(seed, (8, 8), start, faces):
        assert under.size >= 1
        assert abs(math.degrees(turn - float(np.mean(under)))) < 0.35
