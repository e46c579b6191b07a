"""The wall lattice: keyframes' wall faces against a maze's known cell pitch, and the priors they give."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.geometry import relative_pose
from mazebot.slam.keyframes import Keyframe
from mazebot.slam.slam import LoopClosureJob, SlamParams
from mazebot.slam.wall_lattice import FACE_CLASSES, LatticeParams, lattice_priors, measure_faces

CELL_M = 0.3048
WALL_M = 0.012
PARAMS = LatticeParams(pitch_m=CELL_M, pitch_search=0.0)  # the exact pitch (the daemon measures it within 8 %)

# a walk through the 6x6 maze fixture's cells (col, row), each a neighbour of the one before
ROUTE = [(0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (2, 1), (2, 2), (2, 3), (3, 3), (3, 2), (4, 2), (4, 3)]


def keyframe_at(world, cast_scan, index: int, pose: np.ndarray, seed: int = 0) -> Keyframe:
    """A keyframe of one revolution (1 % range noise) from ``pose``, everything in its own frame."""
    angles, ranges = cast_scan(world, pose, noise_rel=0.01, seed=seed)
    valid = np.isfinite(ranges) & (ranges > 0.15)
    hits = np.column_stack((ranges[valid] * np.cos(angles[valid]), ranges[valid] * np.sin(angles[valid])))
    return Keyframe(
        index=index,
        time_s=float(index),
        pose=np.asarray(pose, dtype=np.float64),
        hits=hits.astype(np.float32),
        match_points=hits.astype(np.float32),
        sensor_xy=np.zeros(2),
        ray_ends=hits.astype(np.float32),
        ray_hit=np.ones(len(hits), dtype=bool),
        integrated_pose=np.asarray(pose, dtype=np.float64),
    )


def route_poses(world) -> np.ndarray:
    """True poses along ROUTE: near each cell's centre (a few mm off), headings all round."""
    layout = world.maze
    rng = np.random.default_rng(4)
    rows = []
    for k, cell in enumerate(ROUTE):
        x, y = layout.cell_center_m(cell)
        rows.append((x + rng.uniform(-0.03, 0.03), y + rng.uniform(-0.03, 0.03), math.remainder(0.7 * k, math.tau)))
    return np.array(rows)


def test_a_keyframe_sees_its_faces_half_a_wall_off_the_lattice_lines(maze_world, cast_scan):
    layout = maze_world.maze
    x0, y0 = layout.origin_m  # lattice lines at x0 + i·pitch and y0 + j·pitch
    pose = np.array([*layout.cell_center_m((2, 2)), 0.4])
    pose[:2] += (0.013, -0.021)
    kf = keyframe_at(maze_world, cast_scan, 0, pose)
    faces = kf.lattice_faces(0.4, PARAMS)  # the maze's grid lies along the world's axes
    assert int((faces.count > 0).sum()) >= 3
    for k, (axis, sign) in enumerate(FACE_CLASSES):
        if faces.count[k] == 0:
            continue
        line = (x0, y0)[axis]
        # a face seen from the + side lies half a wall above its line, from the - side half below
        expected = line + sign * WALL_M / 2
        error = math.remainder(pose[axis] + faces.offset_m[k] - expected, CELL_M)
        assert abs(error) < 0.0015, (k, error)


def test_the_offsets_follow_a_small_change_of_heading_to_first_order(maze_world, cast_scan):
    pose = np.array([*maze_world.maze.cell_center_m((1, 2)), -0.9])
    kf = keyframe_at(maze_world, cast_scan, 0, pose)
    points, normals = kf.surface()
    measured = measure_faces(points, normals, kf.sensor_xy, -0.9, PARAMS)
    moved = measure_faces(points, normals, kf.sensor_xy, -0.9 + 0.004, PARAMS)
    same = (measured.count > 0) & (moved.count > 0)
    assert same.sum() >= 3
    # within half a millimetre: a point or two at a class's edges may join or leave it at the new heading
    np.testing.assert_allclose(measured.at(-0.9 + 0.004)[same], moved.offset_m[same], atol=5e-4)
    # and far closer than the offsets at the old heading
    first_order = np.abs(measured.at(-0.9 + 0.004)[same] - moved.offset_m[same]).sum()
    assert first_order < 0.5 * np.abs(measured.offset_m[same] - moved.offset_m[same]).sum()


def test_a_round_post_makes_no_face():
    angle = np.linspace(-1.2, 1.2, 60) + math.pi  # the near side of a post 0.3 m ahead, 4 cm in radius
    points = np.column_stack((0.3 + 0.04 * np.cos(angle), 0.04 * np.sin(angle)))
    normals = np.column_stack((np.cos(angle), np.sin(angle)))
    faces = measure_faces(points, normals, np.zeros(2), 0.0, PARAMS)
    assert faces.count.tolist() == [0, 0, 0, 0]


def test_the_priors_say_where_drifted_keyframes_belong_on_the_lattice(maze_world, cast_scan):
    truth = route_poses(maze_world)
    keyframes = [keyframe_at(maze_world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    faces = [kf.lattice_faces(float(p[2]), PARAMS) for kf, p in zip(keyframes, truth, strict=True)]
    drifted = truth.copy()
    drifted[6:, :2] += (0.012, -0.008)  # the chain slipped between keyframes 5 and 6
    rows, target, weight, line = lattice_priors(drifted, faces, drifted[0, :2], 0.0, PARAMS)
    assert len(rows) == len(truth) and (weight > 0).sum() >= 20
    # where they belong relative to keyframe 0 is where they truly are relative to it
    where = target + line + drifted[0, :2]
    first = int(np.flatnonzero(rows == 0)[0])
    for axis in (0, 1):
        seen = weight[:, axis] > 0
        assert seen[first]
        error = (where[seen, axis] - where[first, axis]) - (truth[rows[seen], axis] - truth[0, axis])
        assert np.abs(error).max() < 0.002, (axis, error)


def test_walls_off_the_pitch_give_no_prior(maze_world, cast_scan):
    truth = route_poses(maze_world)
    other = LatticeParams(pitch_m=0.25, pitch_search=0.0)  # the config says 25 cm cells; this maze's are 1 ft
    keyframes = [keyframe_at(maze_world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    faces = [kf.lattice_faces(float(p[2]), other) for kf, p in zip(keyframes, truth, strict=True)]
    rows, _, _, _ = lattice_priors(truth, faces, truth[0, :2], 0.0, other)
    assert len(rows) == 0


@pytest.mark.parametrize("with_lattice", [True, False])
def test_an_optimization_with_lattice_priors_takes_out_a_slip_of_the_chain(maze_world, cast_scan, with_lattice):
    """The chain says keyframes 6.. are 14 mm off; only the lattice can say otherwise."""
    truth = route_poses(maze_world)
    keyframes = [keyframe_at(maze_world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    drifted = truth.copy()
    drifted[6:, :2] += (0.012, -0.008)
    for kf, pose in zip(keyframes, drifted, strict=True):
        kf.pose = pose.copy()
    count = len(truth)
    ei, ej = np.arange(count - 1), np.arange(1, count)
    z = relative_pose(drifted[ei], drifted[ej])  # the chain as its scan matches saw it
    info = np.tile(np.diag([1 / 0.005**2, 1 / 0.005**2, 1 / 0.01**2]), (count - 1, 1, 1))
    params = SlamParams(lattice=PARAMS if with_lattice else None)
    job = LoopClosureJob(
        candidates=[],
        keyframes=keyframes,
        poses=drifted.copy(),
        integrated_poses=drifted.copy(),
        edges=(ei, ej, z, info),
        params=params,
        wall_reference_rad=0.0,
        optimize_anyway=True,
        anchor_wall=(0.0, 0.001),
    )
    result = job.run()
    assert result.poses is not None
    error = np.hypot(*(result.poses[6:, :2] - truth[6:, :2]).T)
    if with_lattice:
        assert error.max() < 0.004, error
    else:
        assert error.min() > 0.012, error
