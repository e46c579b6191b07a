"""Endpoints moved onto their walls, and the thin walls they give the grid, against ground truth."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from mazebot.io.scan import Scan
from mazebot.sim.raster import true_occupancy
from mazebot.sim.raycast import distance_to_obstacles
from mazebot.sim.world import World
from mazebot.slam.endpoint_smoothing import EndpointSmoothing, smooth_endpoints
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.keyframes import map_rays
from mazebot.slam.preprocess import PrepareParams, prepare_scan

NOISE_REL = 0.01  # the A1's range noise


def _static_scan(world: World, pose: np.ndarray, cast_scan, seed: int) -> Scan:
    angles, ranges = cast_scan(world, pose, noise_rel=NOISE_REL, seed=seed)
    valid = np.isfinite(ranges)
    return Scan(
        angle_rad=angles,
        range_m=np.where(valid, ranges, 0.0),
        quality=np.where(valid, 47, 0).astype(np.uint8),
        time_s=np.zeros(angles.shape[0]),
        valid=valid,
    )


def _to_world(pose: np.ndarray, xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.column_stack((pose[0] + c * xy[:, 0] - s * xy[:, 1], pose[1] + s * xy[:, 0] + c * xy[:, 1]))


def _poses(world: World, count: int, seed: int) -> list[np.ndarray]:
    """Poses near the centres of the maze's cells, varied headings."""
    assert world.maze is not None
    rng = np.random.default_rng(seed)
    cells = [(c, r) for r in range(world.maze.height) for c in range(world.maze.width)]
    out = []
    for k in rng.permutation(len(cells))[:count]:
        x, y = world.maze.cell_center_m(cells[k])
        out.append(np.array([x + rng.uniform(-0.04, 0.04), y + rng.uniform(-0.04, 0.04), rng.uniform(-3, 3)]))
    return out


def test_smoothed_hits_lie_closer_to_the_true_wall_along_their_own_beams(maze_world: World, cast_scan) -> None:
    raw_err, smooth_err = [], []
    for k, pose in enumerate(_poses(maze_world, 12, seed=1)):
        prepared = prepare_scan(_static_scan(maze_world, pose, cast_scan, seed=k), None)
        hits = prepared.points_full
        smoothed = smooth_endpoints(hits, prepared.origins_full)
        # every hit stays on its beam: the bearing is what the lidar measures well
        raw_dir = np.arctan2(hits[:, 1], hits[:, 0])
        new_dir = np.arctan2(smoothed[:, 1], smoothed[:, 0])
        np.testing.assert_allclose(np.remainder(new_dir - raw_dir + np.pi, 2 * np.pi) - np.pi, 0.0, atol=1e-9)
        raw_err.append(distance_to_obstacles(_to_world(pose, hits), maze_world))
        smooth_err.append(distance_to_obstacles(_to_world(pose, smoothed), maze_world))
    raw, smooth = np.concatenate(raw_err), np.concatenate(smooth_err)
    # the typical hit (a wall face seen from nearby, ~9 neighbours) gains the most
    assert np.median(smooth) < 0.5 * np.median(raw), (np.median(raw), np.median(smooth))
    rms_raw, rms_smooth = np.sqrt(np.mean(raw**2)), np.sqrt(np.mean(smooth**2))
    assert rms_smooth < 0.75 * rms_raw, (rms_raw, rms_smooth)
    # corners and wall ends are not dragged off the walls: the worst points stay within the raw scatter
    assert np.percentile(smooth, 99.5) <= np.percentile(raw, 99.5)


def test_a_hit_without_a_line_around_it_keeps_its_range() -> None:
    origins = np.zeros((7, 2))
    # a straight wall at x = 1 ... and one stray return far off it, too few neighbours for a line
    wall = np.column_stack((np.ones(6), np.linspace(-0.05, 0.05, 6)))
    pts = np.vstack((wall, [[3.0, 2.0]]))
    out = smooth_endpoints(pts, origins, EndpointSmoothing(half_window=3), circular=False)
    np.testing.assert_allclose(out[-1], pts[-1])
    np.testing.assert_allclose(out[:6, 0], 1.0, atol=1e-12)


def test_noisy_scans_map_walls_one_cell_thin_and_free_space_up_to_them(maze_world: World, cast_scan) -> None:
    """The grid of 1 %-noise scans at known poses: occupied cells on the walls, free cells reaching them.

    Scored in the grid's own lattice against the truth raster of the world. Without the
    smoothing, ranges falling short put the cell in front of a face into the wall in
    most scans wherever the face lies a few millimetres behind a cell edge.
    """
    res = 0.02
    grid = OccupancyGrid(resolution_m=res, occupied_prob=0.75)
    for k, pose in enumerate(_poses(maze_world, 36, seed=2) * 3):
        prepared = prepare_scan(_static_scan(maze_world, pose, cast_scan, seed=100 + k), None, PrepareParams())
        ends, hit, origins = map_rays(prepared, 1.2, EndpointSmoothing(), NOISE_REL)
        grid.integrate(pose, _to_world(pose, ends), hit, _to_world(pose, origins))
    truth, _ = true_occupancy(maze_world, res, origin_m=grid.origin_m, shape=grid.shape)
    occupied, free = grid.occupied_mask(), grid.known_free_mask()
    near_truth = ndimage.binary_dilation(truth, structure=np.ones((3, 3), bool))
    # walls: every occupied cell within one cell of a true wall
    assert np.count_nonzero(occupied & ~near_truth) <= 0.002 * np.count_nonzero(occupied)
    # a free cell on a wall holds at most a 2 mm sliver of it (its centre 8 mm or more from the face)
    rr, cc = np.nonzero(free & truth)
    assert np.all(distance_to_obstacles(grid.to_world(rr, cc), maze_world) >= res / 2 - 0.002)
    # free space up to the wall: the free cells touching a wall face (inside the maze) are known free
    inside = np.zeros_like(truth)
    rows, cols = np.indices(truth.shape)
    xy = grid.to_world(rows.ravel(), cols.ravel())
    xmin, ymin, xmax, ymax = maze_world.bounds_m
    inside.reshape(-1)[:] = (xy[:, 0] > xmin) & (xy[:, 0] < xmax) & (xy[:, 1] > ymin) & (xy[:, 1] < ymax)
    band = ~truth & ndimage.binary_dilation(truth) & inside
    assert np.count_nonzero(free & band) >= 0.97 * np.count_nonzero(band), (
        np.count_nonzero(free & band), np.count_nonzero(band)
    )


def _band_and_stray(world: World, cast_scan, hit_depth_m: float, pose_error_m: float) -> tuple[float, float]:
    """Map noisy scans taken at poses known only to ``pose_error_m``: (free share of the band
    of cells touching a wall face, share of occupied cells more than one cell off a wall)."""
    res = 0.02
    grid = OccupancyGrid(resolution_m=res, occupied_prob=0.75)
    rng = np.random.default_rng(7)
    for k, pose in enumerate(_poses(world, 36, seed=2) * 3):
        prepared = prepare_scan(_static_scan(world, pose, cast_scan, seed=100 + k), None, PrepareParams())
        ends, hit, origins = map_rays(prepared, 1.2, EndpointSmoothing(), NOISE_REL, hit_depth_m)
        believed = pose + np.array([*rng.normal(0.0, pose_error_m, 2), rng.normal(0.0, np.radians(0.1))])
        grid.integrate(believed, _to_world(believed, ends), hit, _to_world(believed, origins))
    truth, _ = true_occupancy(world, res, origin_m=grid.origin_m, shape=grid.shape)
    occupied, free = grid.occupied_mask(), grid.known_free_mask()
    near_truth = ndimage.binary_dilation(truth, structure=np.ones((3, 3), bool))
    rows, cols = np.indices(truth.shape)
    xy = grid.to_world(rows.ravel(), cols.ravel())
    xmin, ymin, xmax, ymax = world.bounds_m
    inside = ((xy[:, 0] > xmin) & (xy[:, 0] < xmax) & (xy[:, 1] > ymin) & (xy[:, 1] < ymax)).reshape(truth.shape)
    band = ~truth & ndimage.binary_dilation(truth) & inside
    return (np.count_nonzero(free & band) / np.count_nonzero(band),
            np.count_nonzero(occupied & ~near_truth) / max(1, np.count_nonzero(occupied)))


def test_hits_marked_behind_the_face_keep_free_space_up_to_walls_despite_pose_error(
    maze_world: World, cast_scan
) -> None:
    """SLAM's poses are off by a few millimetres; hits marked 6 mm behind the face (inside the
    12 mm wall) keep the cell in front of a face free, and the walls on their true cells."""
    pose_error_m = 0.004
    band_at_face, _ = _band_and_stray(maze_world, cast_scan, 0.0, pose_error_m)
    band_deep, stray_deep = _band_and_stray(maze_world, cast_scan, 0.006, pose_error_m)
    assert band_deep >= 0.97, band_deep
    assert band_deep > band_at_face + 0.01, (band_at_face, band_deep)  # what the depth is for
    assert stray_deep <= 0.002, stray_deep  # the walls did not move off their cells
