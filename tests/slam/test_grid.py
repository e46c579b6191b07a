"""The occupancy grid against ground-truth rasters: walls, free space, growth, deltas, rebuilds."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

import mazebot.slam.grid as grid_module
from mazebot.geometry import transform_points
from mazebot.sim.raster import true_occupancy
from mazebot.sim.world import World
from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid
from mazebot.slam.lattice_fit import PitchFit, cell_offset_on_lattice
from mazebot.slam.params import SlamParams

RES_M = 0.02


def _beams(angles: np.ndarray, ranges: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World endpoints and hit mask of a static scan; no-return beams end at 12 m."""
    hit = np.isfinite(ranges)
    r = np.where(hit, ranges, 12.0)
    a = angles + pose[2]
    return np.column_stack((pose[0] + r * np.cos(a), pose[1] + r * np.sin(a))), hit


def _hits(angles: np.ndarray, ranges: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Only the beams with a return."""
    ends, hit = _beams(angles, ranges, pose)
    return ends[hit], hit[hit]


def _tour(world: World) -> list[np.ndarray]:
    """A pose in every cell of the maze, near its centre, varied headings."""
    assert world.maze is not None
    rng = np.random.default_rng(4)
    poses = []
    for row in range(world.maze.height):
        for col in range(world.maze.width):
            x, y = world.maze.cell_center_m((col, row))
            poses.append(np.array([x + rng.uniform(-0.03, 0.03), y + rng.uniform(-0.03, 0.03), rng.uniform(-3, 3)]))
    return poses


@pytest.fixture(scope="module")
def mapped_maze(maze_world: World) -> OccupancyGrid:
    from mazebot.sim.raycast import cast_rays

    grid = OccupancyGrid(resolution_m=RES_M)
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    for pose in _tour(maze_world):
        ranges = cast_rays(pose[:2], angles + pose[2], maze_world.segments, maze_world.circles, 12.0)
        ends, hit = _beams(angles, ranges, pose)
        grid.integrate(pose, ends, hit)
    return grid


def test_perfect_scans_give_the_true_walls(mapped_maze: OccupancyGrid, maze_world: World) -> None:
    grid = mapped_maze
    truth, _ = true_occupancy(maze_world, RES_M, origin_m=grid.origin_m, shape=grid.shape)
    occupied = grid.occupied_mask()
    # F1 of occupied cells, a cell counting as right when the other side has one within a cell
    near_truth = ndimage.binary_dilation(truth, structure=np.ones((3, 3), bool))
    near_map = ndimage.binary_dilation(occupied, structure=np.ones((3, 3), bool))
    precision = np.count_nonzero(occupied & near_truth) / np.count_nonzero(occupied)
    recall = np.count_nonzero(truth & near_map) / np.count_nonzero(truth)
    f1 = 2 * precision * recall / (precision + recall)
    assert f1 >= 0.9, (precision, recall)


def test_free_cells_are_never_on_walls(mapped_maze: OccupancyGrid, maze_world: World) -> None:
    grid = mapped_maze
    truth, _ = true_occupancy(maze_world, RES_M, origin_m=grid.origin_m, shape=grid.shape)
    free = grid.known_free_mask()
    assert np.count_nonzero(free) > 0.8 * np.count_nonzero(~truth & _inside(maze_world, grid))
    assert not np.any(free & truth)


def _inside(world: World, grid: OccupancyGrid) -> np.ndarray:
    xmin, ymin, xmax, ymax = world.bounds_m
    rows, cols = np.indices(grid.shape)
    xy = grid.to_world(rows.ravel(), cols.ravel())
    ok = (xy[:, 0] > xmin) & (xy[:, 0] < xmax) & (xy[:, 1] > ymin) & (xy[:, 1] < ymax)
    return ok.reshape(grid.shape)


def test_one_update_per_cell_per_scan_and_hits_win() -> None:
    grid = OccupancyGrid(resolution_m=0.1, margin_m=0.5)
    # beam 1 ends at (1.05, 0.05); beam 2 passes through that cell to (2.05, 0.05)
    grid.integrate(np.array([0.05, 0.05, 0.0]), np.array([[1.05, 0.05], [2.05, 0.05]]), np.array([True, True]))
    rows, cols = grid.to_cell(np.array([[1.05, 0.05], [0.55, 0.05], [2.05, 0.05], [0.05, 0.05]]))
    values = grid.log_odds[rows, cols]
    np.testing.assert_allclose(values, [grid.l_hit, grid.l_miss, grid.l_hit, grid.l_miss], rtol=1e-6)


def test_no_return_beams_clear_up_to_the_cap_and_mark_no_hit() -> None:
    grid = OccupancyGrid(resolution_m=0.05, max_free_range_m=2.0, margin_m=0.2)
    grid.integrate(np.zeros(3), np.array([[12.0, 0.01]]), np.array([False]))
    assert not grid.occupied_mask().any()
    xs = np.array([[0.5, 0.01], [1.9, 0.01], [2.3, 0.01]])
    rows, cols = grid.to_cell(xs)
    inside = (rows >= 0) & (rows < grid.shape[0]) & (cols >= 0) & (cols < grid.shape[1])
    assert inside[:2].all()
    np.testing.assert_allclose(grid.log_odds[rows[:2], cols[:2]], grid.l_miss)
    assert not inside[2] or grid.log_odds[rows[2], cols[2]] == 0.0


def test_three_state_thresholds_and_clamping() -> None:
    grid = OccupancyGrid(resolution_m=0.1, occupied_prob=0.65, free_prob=0.25, margin_m=0.3)
    sensor = np.array([0.05, 0.05, 0.0])
    wall = np.array([[0.55, 0.05]])
    grid.integrate(sensor, wall, np.array([True]))  # one hit: 0.85 > logit(0.65) = 0.62
    r, c = grid.to_cell(np.array([[0.55, 0.05], [0.25, 0.05]]))
    assert grid.three_state()[r[0], c[0]] == OCCUPIED
    assert grid.three_state()[r[1], c[1]] == UNKNOWN  # one miss: -0.4 > logit(0.25) = -1.10
    for _ in range(2):
        grid.integrate(sensor, wall, np.array([True]))
    assert grid.three_state()[r[1], c[1]] == FREE  # three misses: -1.2
    for _ in range(20):
        grid.integrate(sensor, wall, np.array([True]))
    assert grid.log_odds[r[0], c[0]] == pytest.approx(grid.l_max)
    assert grid.log_odds[r[1], c[1]] == pytest.approx(grid.l_min)
    assert grid.three_state().dtype == np.int8
    assert grid.probability()[r[0], c[0]] > 0.99


def test_growth_keeps_content_at_the_same_world_coordinates(maze_world: World, cast_scan) -> None:
    grid = OccupancyGrid(resolution_m=RES_M, margin_m=0.1)
    first = np.array([0.15, 0.15, 0.3])
    # hits within 0.6 m only: the two scans below touch disjoint areas
    angles, ranges = cast_scan(maze_world, first, max_range_m=0.6)
    grid.integrate(first, *_hits(angles, ranges, first))
    generation, shape, origin = grid.generation, grid.shape, grid.origin_m
    rows, cols = np.indices(shape)
    xy = grid.to_world(rows.ravel(), cols.ravel())
    before = grid.log_odds.ravel().copy()

    far = np.array([1.68, 1.68, -2.0])  # the opposite corner of the maze
    angles, ranges = cast_scan(maze_world, far, max_range_m=0.6)
    grid.integrate(far, *_hits(angles, ranges, far))
    assert grid.generation == generation + 1
    assert grid.shape[0] > shape[0] and grid.shape[1] > shape[1]
    assert origin[0] / RES_M == pytest.approx(round(origin[0] / RES_M))  # cell boundaries never move
    r, c = grid.to_cell(xy)
    np.testing.assert_array_equal(grid.log_odds[r, c], before)
    # integrating inside the current extent does not reallocate
    grid.integrate(far, *_hits(angles, ranges, far))
    assert grid.generation == generation + 1


def test_dirty_set_is_exactly_the_changed_cells(maze_world: World, cast_scan) -> None:
    grid = OccupancyGrid(resolution_m=RES_M, margin_m=0.05)
    rng = np.random.default_rng(2)
    shown = None  # what a client holds, updated only through deltas and full maps
    generation = -1
    for step in range(12):
        pose = np.array([rng.uniform(0.1, 1.7), rng.uniform(0.1, 1.7), rng.uniform(-3, 3)])
        angles, ranges = cast_scan(maze_world, pose, max_range_m=1.0)
        before = None if shown is None else grid.three_state().copy()
        grid.integrate(pose, *_beams(angles, ranges, pose))
        delta = grid.take_dirty()
        now = grid.three_state()
        if delta.generation != generation:  # reallocated: the client reloads the full map
            shown, generation = now.copy(), delta.generation
            continue
        assert before is not None
        changed = np.argwhere(now != before)
        assert sorted(map(tuple, changed)) == sorted(zip(delta.rows.tolist(), delta.cols.tolist(), strict=True))
        np.testing.assert_array_equal(delta.values, now[delta.rows, delta.cols])
        shown[delta.rows, delta.cols] = delta.values
        np.testing.assert_array_equal(shown, now)
        assert len(grid.take_dirty()) == 0, f"step {step}: a second call has nothing new"


def test_dirty_cells_follow_a_reallocation() -> None:
    grid = OccupancyGrid(resolution_m=0.1, margin_m=0.0)
    grid.integrate(np.array([0.05, 0.05]), np.array([[0.55, 0.05]]), np.array([True]))
    grid.integrate(np.array([0.05, 0.05]), np.array([[-0.45, 0.05]]), np.array([True]))  # grows west
    delta = grid.take_dirty()
    xy = grid.to_world(delta.rows, delta.cols)
    occupied = xy[delta.values == OCCUPIED]
    np.testing.assert_allclose(sorted(occupied[:, 0]), [-0.45, 0.55], atol=1e-9)


def test_rebuild_equals_integrating_from_scratch(maze_world: World, cast_scan) -> None:
    keyframes = []
    sequential = OccupancyGrid(resolution_m=RES_M)
    for pose in _tour(maze_world)[:8]:
        angles, ranges = cast_scan(maze_world, pose)
        ends_world, hit = _beams(angles, ranges, pose)
        sequential.integrate(pose, ends_world, hit)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        local = (ends_world - pose[:2]) @ np.array([[c, -s], [s, c]])
        keyframes.append((pose, local, hit))
    rebuilt = OccupancyGrid(resolution_m=RES_M)
    rebuilt.integrate(np.zeros(3), np.array([[5.0, 5.0]]), np.array([True]))  # stale content
    rebuilt.take_dirty()
    generation = rebuilt.generation
    rebuilt.rebuild(keyframes)
    assert rebuilt.generation == generation + 1
    assert len(rebuilt.take_dirty()) == 0  # clients reload the map; no stale deltas
    # same content at the same world coordinates
    rows, cols = np.nonzero(sequential.log_odds)
    r, c = rebuilt.to_cell(sequential.to_world(rows, cols))
    np.testing.assert_allclose(rebuilt.log_odds[r, c], sequential.log_odds[rows, cols], rtol=1e-6)
    assert np.count_nonzero(rebuilt.log_odds) == rows.size


def test_a_rebuild_in_chunks_moves_every_keyframe_as_transform_points_does(
    maze_world: World, cast_scan, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Keyframes moved into the world a chunk at a time give the grid of the same beams given in the world.

    Eight keyframes in chunks of three, some with their own beam origins and some starting
    at the pose: the log odds are equal to the bit to those of the keyframes moved one by one
    with :func:`mazebot.geometry.transform_points` and handed over at the identity pose.
    """
    monkeypatch.setattr(grid_module, "REBUILD_CHUNK_KEYFRAMES", 3)
    local_keyframes, world_keyframes = [], []
    for k, pose in enumerate(_tour(maze_world)[:8]):
        angles, ranges = cast_scan(maze_world, pose)
        ends_world, hit = _beams(angles, ranges, pose)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        local = (ends_world - pose[:2]) @ np.array([[c, -s], [s, c]])
        origins = np.broadcast_to(np.array([0.03, -0.01]) if k % 2 else np.zeros(2), local.shape)
        local_keyframes.append((pose, local, hit, origins) if k % 3 else (pose, local, hit))
        world_origins = transform_points(pose, origins) if k % 3 else np.broadcast_to(pose[:2], local.shape)
        world_keyframes.append((np.zeros(3), transform_points(pose, local), hit, world_origins))
    chunked, reference = OccupancyGrid(resolution_m=RES_M), OccupancyGrid(resolution_m=RES_M)
    chunked.rebuild(local_keyframes)
    reference.rebuild(world_keyframes)
    assert chunked.origin_cells == reference.origin_cells
    np.testing.assert_array_equal(chunked.log_odds, reference.log_odds)
    assert np.count_nonzero(chunked.log_odds) > 1000


def test_cells_and_world_coordinates_round_trip() -> None:
    grid = OccupancyGrid(resolution_m=0.05, margin_m=0.0)
    grid.integrate(np.array([-1.02, -0.51]), np.array([[2.03, 1.01]]), np.array([True]))
    rows, cols = np.indices(grid.shape)
    xy = grid.to_world(rows.ravel(), cols.ravel())
    r, c = grid.to_cell(xy)
    np.testing.assert_array_equal(r, rows.ravel())
    np.testing.assert_array_equal(c, cols.ravel())
    # row 0 is south, column 0 west
    assert grid.to_world(np.array([0]), np.array([0]))[0, 1] < grid.to_world(np.array([1]), np.array([0]))[0, 1]
    ox, oy = grid.origin_m
    assert ox <= -1.02 and oy <= -0.51


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="resolution"):
        OccupancyGrid(resolution_m=0.0)
    with pytest.raises(ValueError, match="free_prob"):
        OccupancyGrid(occupied_prob=0.4)
    grid = OccupancyGrid()
    with pytest.raises(ValueError, match="hit_mask"):
        grid.integrate(np.zeros(3), np.zeros((3, 2)), np.ones(2, bool))


def test_cells_shifted_by_a_rebuild_keep_every_point_in_its_cell() -> None:
    grid = OccupancyGrid(resolution_m=0.02)
    sensor = np.array([0.05, 0.05, 0.0])
    ends = np.array([[1.0, 0.05], [0.05, 1.0], [-0.7, -0.3]])
    grid.rebuild([(sensor, ends - sensor[:2], np.ones(3, dtype=bool))], cell_offset_m=(0.0234, -0.0047))
    assert grid.cell_offset_m == pytest.approx((0.0034, 0.0153))
    corner = np.asarray(grid.origin_m) - grid.cell_offset_m  # a whole number of cells
    assert np.round(corner / 0.02) * 0.02 == pytest.approx(corner, abs=1e-9)
    rows, cols = grid.to_cell(ends)
    assert np.abs(grid.to_world(rows, cols) - ends).max() <= 0.01 + 1e-9
    assert grid.occupied_mask()[rows, cols].all()  # the hits landed in the cells to_cell names


def test_a_thin_wall_on_a_cell_boundary_blackens_two_cells_and_one_once_the_cells_follow_the_lattice() -> None:
    """A 12 mm board along x = 0.16 m, seen from both sides: on cells whose boundary it lies on
    it is two cells thick; on cells centred on it (the offset the lattice gives), one."""
    ys = np.linspace(-0.2, 0.2, 41)
    west = [(np.array([0.0, 0.0, 0.0]), np.column_stack((np.full(ys.size, 0.154), ys)), np.ones(ys.size, bool))]
    east = [(np.array([0.32, 0.0, 0.0]), np.column_stack((np.full(ys.size, -0.154), ys)), np.ones(ys.size, bool))]
    fit = PitchFit(0.32, (0.16, 0.16), 1.0, (6, 6), True, True)
    for offset, thickness in ((None, 2), (cell_offset_on_lattice(fit, 0.0, 0.02), 1)):
        grid = OccupancyGrid(resolution_m=0.02)
        grid.rebuild(west + east, cell_offset_m=offset)
        rows, cols = np.nonzero(grid.occupied_mask())
        xs = np.unique(np.round(grid.to_world(rows, cols)[:, 0], 4))
        assert len(xs) == thickness
    assert cell_offset_on_lattice(fit, math.radians(1.0), 0.02) is None  # lines turned across the cells
    assert cell_offset_on_lattice(replace(fit, fits=False), 0.0, 0.02) is None


def test_lines_near_the_centres_of_the_cells_as_they_are_leave_the_cells_there() -> None:
    fit = PitchFit(0.3048, (0.1524, 0.1524), 1.0, (6, 6), True, True)  # a 1 ft maze from its start cell
    assert cell_offset_on_lattice(fit, 0.0, 0.02) is None
    assert cell_offset_on_lattice(replace(fit, phase_m=(0.1524, 0.161)), 0.0, 0.02) == pytest.approx((0.0, 0.011))


def _leg_scans(grid: OccupancyGrid, pose: np.ndarray, leg: np.ndarray, times: int, min_range_m: float = 0.15) -> None:
    """``times`` revolutions of 360 beams in a 2 m square room holding one leg (a disc); returns
    closer than ``min_range_m`` are dropped, as the driver drops the A1's invalid samples."""
    from mazebot.sim.raycast import cast_rays

    corners = np.array([(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)])
    segments = np.column_stack((corners, np.roll(corners, -1, axis=0)))
    rng = np.random.default_rng(1)
    for _ in range(times):
        angles = np.linspace(-np.pi, np.pi, 360, endpoint=False) + rng.uniform(0.0, np.radians(1.0))
        ranges = cast_rays(pose[:2], angles + pose[2], segments, leg[None], 12.0)
        keep = np.isfinite(ranges) & (ranges >= min_range_m)
        ends, hit = _beams(angles[keep], ranges[keep], pose)
        grid.integrate(pose, ends, hit)


@pytest.mark.parametrize("blind_range_m", [0.0, 0.15])
def test_a_thin_leg_seen_from_afar_stays_while_the_robot_stands_in_its_blind_zone(blind_range_m: float) -> None:
    leg = np.array([0.3, 0.2, 0.01])  # a 2 cm table leg
    grid = OccupancyGrid(resolution_m=RES_M, blind_range_m=blind_range_m)
    _leg_scans(grid, np.array([-0.4, 0.2, 0.0]), leg, 10)  # 0.7 m away: painted
    rows, cols = grid.to_cell(np.array([[0.29, 0.2]]))  # the face seen
    assert grid.occupied_mask()[max(rows[0] - 1, 0) : rows[0] + 2, cols[0] - 1 : cols[0] + 2].any()
    _leg_scans(grid, np.array([0.3, 0.09, 0.5]), leg, 20)  # 0.11 m from the leg's centre: no return from it
    around = grid.occupied_mask()[rows[0] - 1 : rows[0] + 2, cols[0] - 1 : cols[0] + 2]
    assert around.any() == (blind_range_m > 0)  # with no blind zone the beams beside it erased it
    # the robot's own place is free all the same: the blind zone makes free what held no wall
    r, c = grid.to_cell(np.array([[0.3, 0.09]]))
    assert grid.three_state()[r[0], c[0]] == FREE


def _wall_turned_to_the_cells(grid: OccupancyGrid, revolutions: int) -> None:
    """A wall's face 3 cm long above y = 1.5 cm, marked from 0.15 m below by beams straight at it."""
    xs = np.arange(2.0, 3.0, 0.005)
    for _ in range(revolutions):
        origins = np.column_stack((xs, np.full(xs.shape, -0.15)))
        grid.integrate(origins[0], np.column_stack((xs, np.full(xs.shape, 0.015))), np.ones(xs.shape, dtype=bool),
                       origins)


def test_far_beams_grazing_a_wall_clear_no_cell_of_it_near_beams_do() -> None:
    # the daemon's grid: a beam past [slam.map] map_max_range_m (where hits mark walls) lowers no wall cell
    grid = SlamParams().grid.new_grid()
    wall = np.column_stack((np.arange(2.01, 3.0, 0.02), np.full(50, 0.01)))  # the cells holding the face

    def states(xy: np.ndarray) -> np.ndarray:
        rows, cols = grid.to_cell(xy)
        return grid.three_state()[rows, cols]

    _wall_turned_to_the_cells(grid, 10)
    assert (states(wall) == OCCUPIED).all()
    # beams from 2-4 m down the corridor, rising 3 mm over 4 m: they pass under the face (y < 1.5 cm)
    # in the cells that hold it, and go on past the wall's end (no return: what a far hit becomes)
    origin = np.array([-0.5, 0.008])
    ends = np.column_stack((np.full(5, 3.5), np.linspace(0.008, 0.011, 5)))
    for _ in range(30):
        grid.integrate(origin, ends, np.zeros(5, dtype=bool), np.broadcast_to(origin, ends.shape))
    assert (states(wall) == OCCUPIED).all()  # the far beams cleared no cell of the wall
    assert (states(np.array([[3.3, 0.01], [0.5, 0.01]])) == FREE).all()  # past its end and near the lidar they clear
    # a near beam passes where the wall stood (taken away): it clears it as before
    near = np.array([2.5, -0.3])
    for _ in range(30):
        grid.integrate(near, np.array([[2.5, 0.5]]), np.zeros(1, dtype=bool), near[None])
    assert states(np.array([[2.5, 0.01]]))[0] == FREE
    assert grid.wall_range_m == SlamParams().map_max_range_m
