"""Scan preparation: range gate, impulse rejection, de-skew against ground truth, downsampling."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.io.scan import Scan
from mazebot.sim.raycast import distance_to_segments
from mazebot.sim.world import World
from mazebot.slam import preprocess
from mazebot.slam.preprocess import (
    PrepareParams,
    impulse_mask,
    prepare_scan,
    transform_points,
    voxel_downsample,
)

CELL_M = 0.3048


def _static_scan(angles: np.ndarray, ranges: np.ndarray, t_end_s: float = 1.0) -> Scan:
    n = angles.size
    valid = np.isfinite(ranges) & (ranges > 0)
    return Scan(
        angle_rad=angles,
        range_m=np.where(valid, ranges, 0.0),
        quality=np.where(valid, 47, 0).astype(np.uint8),
        time_s=np.linspace(t_end_s - 0.18, t_end_s, n),
        valid=valid,
    )


def _cell_pose(world: World, col: int, row: int, theta: float) -> np.ndarray:
    assert world.maze is not None
    x, y = world.maze.cell_center_m((col, row))
    return np.array([x, y, theta])


def test_range_gate_drops_invalid_and_keeps_far_returns_as_no_return_beams() -> None:
    angles = np.linspace(-np.pi, np.pi, 8, endpoint=False)
    ranges = np.array([1.0, 0.1, 0.0, 1.0, 13.0, 1.0, np.nan, 1.0])
    scan = Scan(angles, np.nan_to_num(ranges), np.full(8, 47, np.uint8), np.linspace(0, 0.18, 8), ranges > 0)
    prepared = prepare_scan(scan, None, PrepareParams(median_window=1, max_range_m=12.0))
    assert prepared.range_m.tolist() == [1.0, 1.0, 1.0, 1.0]
    np.testing.assert_allclose(prepared.angle_rad, angles[[0, 3, 5, 7]])
    # the 13 m return clears space (up to max range) but is no hit
    assert prepared.free_endpoints.shape == (1, 2)
    np.testing.assert_allclose(np.hypot(*prepared.free_endpoints[0]), 12.0)
    beams = prepared.beams()
    assert beams.hit.tolist() == [True] * 4 + [False]


def test_impulses_are_removed_and_clean_walls_and_corners_are_kept(maze_world: World, cast_scan) -> None:
    rng = np.random.default_rng(5)
    total_clean_rejects = 0
    for trial in range(10):
        pose = _cell_pose(maze_world, int(rng.integers(6)), int(rng.integers(6)), float(rng.uniform(-np.pi, np.pi)))
        angles, ranges = cast_scan(maze_world, pose, noise_rel=0.01, seed=trial)
        clean = prepare_scan(_static_scan(angles, ranges), None)
        total_clean_rejects += clean.rejected_impulses
        # inject isolated spikes: readings far too short (a speck of dust, a glossy reflection)
        # on smooth wall stretches (both neighbours within 3 %), never two spikes side by side
        spiky = ranges.copy()
        prev, nxt = np.roll(ranges, 1), np.roll(ranges, -1)
        smooth = (ranges > 0.4) & (np.abs(prev - ranges) < 0.03 * ranges) & (np.abs(nxt - ranges) < 0.03 * ranges)
        spikes = rng.choice(np.flatnonzero(smooth)[::3], size=8, replace=False)
        spiky[spikes] = ranges[spikes] * 0.5
        prepared = prepare_scan(_static_scan(angles, spiky), None)
        kept = set(np.round(prepared.angle_rad, 9))
        assert not kept & set(np.round(angles[spikes], 9)), "a spike survived the median test"
        # every kept point lies on a wall (no smoothing moved it off)
        world_pts = transform_points(pose, prepared.points_full)
        d = distance_to_segments(world_pts, maze_world.segments)
        assert np.max(d) < 0.05
    # wall ends seen edge-on are single samples; the test may drop a few, never many
    assert total_clean_rejects <= 10 * 360 * 0.01


def test_impulse_mask_is_exact_on_a_monotonic_run_and_a_step() -> None:
    r = np.array([1.0, 1.1, 1.2, 1.3, 3.0, 3.0, 3.1, 3.2, 0.5, 3.3])
    keep = impulse_mask(r, 3, 0.05, 0.05, circular=False)
    assert keep.tolist() == [True] * 8 + [False, True]


@pytest.mark.parametrize("mount", [(0.0, 0.0, 0.0), (0.06, -0.02, 0.4)])
def test_deskew_with_true_poses_puts_every_sample_on_the_walls_of_the_end_pose(
    maze_world: World, moving_scan, arc_motion, mount: tuple[float, float, float]
) -> None:
    # 0.3 m/s while turning at 1 rad/s: ~5.5 cm and 10 degrees during one revolution
    start = _cell_pose(maze_world, 0, 1, np.pi / 2)
    pose_at = arc_motion(start, 0.3, 1.0)
    scan = moving_scan(maze_world, pose_at, mount=mount)
    params = PrepareParams(median_window=1, mount_x_m=mount[0], mount_y_m=mount[1], mount_yaw_rad=mount[2])
    end = np.array([float(v[0]) for v in pose_at(np.array([scan.end_time_s]))])

    deskewed = prepare_scan(scan, pose_at, params)
    on_walls = distance_to_segments(transform_points(end, deskewed.points_full), maze_world.segments)
    assert np.max(on_walls) < 1e-6
    # the beams start where the lidar was when each sample was taken
    lidar_world = transform_points(end, deskewed.origins_full)
    x, y, th = pose_at(scan.time_s[deskewed.index])
    expected = np.column_stack(
        (x + mount[0] * np.cos(th) - mount[1] * np.sin(th), y + mount[0] * np.sin(th) + mount[1] * np.cos(th))
    )
    np.testing.assert_allclose(lidar_world, expected, atol=1e-9)

    # without de-skew the same scan is smeared by centimetres
    skewed = prepare_scan(scan, None, params)
    off = distance_to_segments(transform_points(end, skewed.points_full), maze_world.segments)
    assert np.max(off) > 0.03


def test_deskewed_noisy_scan_matches_the_static_scan_at_the_end_pose(
    maze_world: World, moving_scan, arc_motion
) -> None:
    start = _cell_pose(maze_world, 0, 1, np.pi / 2)
    pose_at = arc_motion(start, 0.3, -0.8)
    moving = moving_scan(maze_world, pose_at, noise_rel=0.01, seed=1)
    end = np.array([float(v[0]) for v in pose_at(np.array([moving.end_time_s]))])
    static = moving_scan(
        maze_world,
        lambda t: (np.full_like(t, end[0]), np.full_like(t, end[1]), np.full_like(t, end[2])),
        noise_rel=0.01,
        seed=2,
    )
    d_moving = distance_to_segments(
        transform_points(end, prepare_scan(moving, pose_at).points_full), maze_world.segments
    )
    d_static = distance_to_segments(transform_points(end, prepare_scan(static, None).points_full), maze_world.segments)
    # same error distribution as a scan taken standing still at the end pose: the noise
    assert np.median(d_moving) < 1.3 * np.median(d_static) + 5e-4
    assert np.percentile(d_moving, 95) < 1.3 * np.percentile(d_static, 95) + 1e-3


def test_voxel_downsample_keeps_one_original_point_per_voxel(maze_world: World, cast_scan) -> None:
    angles, ranges = cast_scan(maze_world, _cell_pose(maze_world, 2, 2, 0.3), noise_rel=0.01)
    prepared = prepare_scan(_static_scan(angles, ranges), None, PrepareParams(voxel_size_m=0.03))
    full, match = prepared.points_full, prepared.points_match
    assert 0 < match.shape[0] < full.shape[0]
    # every match point is one of the measured points
    assert all((np.abs(full - m).sum(axis=1) == 0).any() for m in match)
    cells = np.floor(match / 0.03).astype(np.int64)
    assert np.unique(cells, axis=0).shape[0] == match.shape[0]
    # and every measured point has a match point in its voxel
    assert np.unique(np.floor(full / 0.03).astype(np.int64), axis=0).shape[0] == match.shape[0]
    assert voxel_downsample(np.zeros((0, 2)), 0.03).size == 0


def _nearest_centre_by_hand(points: np.ndarray, voxel_m: float) -> list[int]:
    """Per voxel, the first of the points nearest its centre: the definition, one point at a time."""
    best: dict[tuple[int, int], tuple[float, int]] = {}
    for i, (x, y) in enumerate(points.tolist()):
        cell = (math.floor(x / voxel_m), math.floor(y / voxel_m))
        d = (x / voxel_m - cell[0] - 0.5) ** 2 + (y / voxel_m - cell[1] - 0.5) ** 2
        if cell not in best or d < best[cell][0]:
            best[cell] = (d, i)
    return sorted(i for _, i in best.values())


@pytest.mark.parametrize("spread_m", [0.3, 40.0])  # a small box (dense pass) and a wide one (sort)
def test_voxel_downsample_keeps_the_point_nearest_each_centre_whichever_way_it_runs(monkeypatch, spread_m) -> None:
    rng = np.random.default_rng(7)
    points = rng.uniform(-spread_m, spread_m, (3000, 2))
    points[::7] = points[3::7]  # exact duplicates: the first of them wins
    points[1::11] = np.round(points[1::11], 2) + 0.005  # right at voxel centres, on a 1 cm grid
    expected = _nearest_centre_by_hand(points, 0.01)
    assert voxel_downsample(points, 0.01).tolist() == expected
    for per_point in (0, 10**9):  # force the sort, then the dense pass
        monkeypatch.setattr(preprocess, "DENSE_VOXELS_PER_POINT", per_point)
        assert voxel_downsample(points, 0.01).tolist() == expected


def test_beams_world_places_rays_from_the_lidar(maze_world: World, cast_scan) -> None:
    mount = (0.05, 0.0, np.pi / 2)
    pose = _cell_pose(maze_world, 1, 3, 0.7)
    angles, ranges = cast_scan(maze_world, pose, mount=mount)
    params = PrepareParams(mount_x_m=mount[0], mount_y_m=mount[1], mount_yaw_rad=mount[2])
    beams = prepare_scan(_static_scan(angles, ranges), None, params).beams_world(pose)
    lidar = pose[:2] + 0.05 * np.array([np.cos(0.7), np.sin(0.7)])
    np.testing.assert_allclose(beams.sensor_pose, [lidar[0], lidar[1], 0.7 + np.pi / 2])
    np.testing.assert_allclose(beams.origins, np.broadcast_to(lidar, beams.origins.shape), atol=1e-12)
    assert np.max(distance_to_segments(beams.endpoints[beams.hit], maze_world.segments)) < 1e-6


def test_params_reject_nonsense() -> None:
    with pytest.raises(ValueError, match="median_window"):
        PrepareParams(median_window=4)
    with pytest.raises(ValueError, match="min_range_m"):
        PrepareParams(min_range_m=5.0, max_range_m=1.0)


def test_deskew_of_a_revolution_from_the_simulated_spinning_lidar(maze_world: World, arc_motion) -> None:
    """The simulator's head and pose history, converted the way the driver does (CW degrees -> CCW radians)."""
    from mazebot.sim.lidar_samples import LidarParams, PoseHistory, SpinningLidar

    pose_at = arc_motion(_cell_pose(maze_world, 0, 1, np.pi / 2), 0.3, 0.9)
    history = PoseHistory(horizon_s=2.0)
    for t in np.arange(0.0, 0.6, 0.002):
        x, y, th = pose_at(np.array([t]))
        history.append(float(t), float(x[0]), float(y[0]), float(th[0]))
    head = SpinningLidar(maze_world, LidarParams(range_noise=0.0, dropout=0.0), np.random.default_rng(0))
    head.advance(0.0, history)  # the head starts turning now
    samples = head.advance(0.6, history)
    first, second = np.flatnonzero(samples.start)[:2]
    rev = slice(first, second)
    dist_m = samples.dist_mm[rev] / 1000.0
    scan = Scan(
        angle_rad=(-np.deg2rad(samples.angle_deg[rev]) + np.pi) % (2 * np.pi) - np.pi,
        range_m=dist_m,
        quality=samples.quality[rev],
        time_s=samples.time_s[rev],
        valid=samples.dist_mm[rev] > 0,
    )
    prepared = prepare_scan(scan, history.at)
    x, y, th = history.at(np.array([scan.end_time_s]))
    end = np.array([x[0], y[0], th[0]])
    d = distance_to_segments(transform_points(end, prepared.points_full), maze_world.segments)
    assert prepared.points_full.shape[0] > 200
    assert np.max(d) < 1e-3  # 0.25 mm range steps and the history's 2 ms interpolation
