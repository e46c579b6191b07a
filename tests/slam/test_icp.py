"""Point-to-line ICP against ground truth: maze worlds, a degenerate corridor, outliers, a real log."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mazebot.geometry import compose, relative_pose
from mazebot.sim.world import World
from mazebot.slam.carmen import read_carmen
from mazebot.slam.icp import IcpParams, IcpResult, Target, estimate_normals, match_scan
from mazebot.slam.preprocess import voxel_downsample

CELL_M = 0.3048


def _points(angles: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    ok = np.isfinite(ranges) & (ranges > 0.15)
    return np.column_stack((ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])))


def _angle_error_deg(a: float, b: float) -> float:
    return abs(math.degrees(math.remainder(a - b, math.tau)))


def _random_poses(world: World, count: int, seed: int) -> list[np.ndarray]:
    """Poses near cell centres (within 4 cm), any heading."""
    assert world.maze is not None
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        x, y = world.maze.cell_center_m((int(rng.integers(world.maze.width)), int(rng.integers(world.maze.height))))
        out.append(np.array([x + rng.uniform(-0.04, 0.04), y + rng.uniform(-0.04, 0.04), rng.uniform(-np.pi, np.pi)]))
    return out


@pytest.fixture
def maze_target(maze_world: World, world_surface) -> Target:
    """The true wall faces, normals towards free space (viewpoints just in front of them)."""
    pts, normals = world_surface(maze_world, 0.01)
    return Target(pts, viewpoints_xy=pts + 0.05 * normals, normals=normals)


@pytest.mark.parametrize(
    ("offset", "seed"),
    [((0.05, 0.0, 3.0), 1), ((-0.035, 0.035, -3.0), 2), ((0.10, -0.02, 5.0), 3), ((-0.07, -0.07, -5.0), 4)],
)
def test_recovers_a_known_offset_in_a_maze(
    maze_world: World, maze_target: Target, cast_scan, offset: tuple[float, float, float], seed: int
) -> None:
    """From 5 cm / 3 degrees and from ~10 cm / 5 degrees off: within 5 mm and 0.2 degrees."""
    delta = np.array([offset[0], offset[1], math.radians(offset[2])])
    for i, truth in enumerate(_random_poses(maze_world, 8, seed)):
        angles, ranges = cast_scan(maze_world, truth, noise_rel=0.01, seed=100 * seed + i)
        result = match_scan(maze_target, _points(angles, ranges), truth + delta)
        assert result.converged
        assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.005
        assert _angle_error_deg(result.pose[2], truth[2]) < 0.2
        assert result.fitness > 0.9
        assert not result.degenerate
        assert result.rmse_m < 0.02


def test_matches_a_submap_built_from_scans_with_estimated_normals(maze_world: World, cast_scan) -> None:
    """The SLAM use: a submap of four noisy scans at known poses, normals estimated."""
    rng = np.random.default_rng(7)
    errors_deg = []
    for i, truth in enumerate(_random_poses(maze_world, 10, 8)):
        keyframes = []
        for j in range(4):
            pose = truth + np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(-0.5, 0.5)])
            angles, ranges = cast_scan(maze_world, pose, noise_rel=0.01, seed=1000 + 10 * i + j)
            keyframes.append((pose, _points(angles, ranges), np.zeros(2)))
        target = Target.from_scans(keyframes, voxel_size_m=0.02)
        angles, ranges = cast_scan(maze_world, truth, noise_rel=0.01, seed=i)
        result = match_scan(target, _points(angles, ranges), truth + np.array([0.05, -0.04, 0.05]))
        assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.005
        errors_deg.append(_angle_error_deg(result.pose[2], truth[2]))
    # the submap's own scans carry 1 % range noise at lever arms of a few decimetres
    assert np.median(errors_deg) < 0.15
    assert max(errors_deg) < 0.3


def test_tolerates_random_outliers(maze_world: World, maze_target: Target, cast_scan) -> None:
    rng = np.random.default_rng(11)
    xmin, ymin, xmax, ymax = maze_world.bounds_m
    for i, truth in enumerate(_random_poses(maze_world, 8, 12)):
        angles, ranges = cast_scan(maze_world, truth, noise_rel=0.01, seed=i)
        src = _points(angles, ranges)
        # a third as many junk points again, anywhere in the maze (people's legs, reflections)
        junk_world = np.column_stack(
            (rng.uniform(xmin, xmax, src.shape[0] // 3), rng.uniform(ymin, ymax, src.shape[0] // 3))
        )
        c, s = math.cos(truth[2]), math.sin(truth[2])
        junk = (junk_world - truth[:2]) @ np.array([[c, -s], [s, c]])
        result = match_scan(maze_target, np.vstack((src, junk)), truth + np.array([0.04, 0.03, math.radians(3)]))
        assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.005
        assert _angle_error_deg(result.pose[2], truth[2]) < 0.2
        assert result.fitness > 0.7


@pytest.mark.parametrize("range_noise_ratio", [0.0, 0.01])
def test_straight_corridor_is_degenerate_and_keeps_the_prior_along_it(
    corridor_world: World, world_surface, cast_scan, range_noise_ratio: float
) -> None:
    """Also with range noise weighting: far points weigh less, but observability is geometry."""
    pts, normals = world_surface(corridor_world, 0.01)
    target = Target(pts, viewpoints_xy=pts + 0.05 * normals, normals=normals)
    truth = np.array([0.3, 0.02, math.radians(10)])
    angles, ranges = cast_scan(corridor_world, truth, noise_rel=0.01)
    src = _points(angles, ranges)
    prior = truth + np.array([0.08, -0.03, math.radians(-3)])  # 8 cm too far along the corridor
    params = IcpParams(range_noise_ratio=range_noise_ratio)
    result = match_scan(target, src[voxel_downsample(src, 0.025)], prior, params, sensor_xy=np.zeros(2))
    assert result.degenerate
    assert result.weak_direction is not None
    assert abs(result.weak_direction[0]) > 0.99  # along the corridor (x)
    assert result.pose[0] == pytest.approx(prior[0], abs=1e-3)  # kept at the prior, not slid
    assert result.pose[1] == pytest.approx(truth[1], abs=0.005)  # across: corrected
    assert _angle_error_deg(result.pose[2], truth[2]) < 0.2
    # the scan tells nothing along the corridor: no information there for the pose graph
    along = np.array([1.0, 0.0, 0.0])
    assert along @ result.information @ along < 1e-6 * np.trace(result.information)
    assert np.all(np.linalg.eigvalsh(result.information) > -1e-6 * np.trace(result.information))


def test_weighting_by_range_noise_recovers_a_known_pose_more_accurately(maze_world: World, cast_scan) -> None:
    """1 % range noise: residuals weighted by their expected noise beat all points alike.

    The SLAM use (a submap of four noisy scans at known poses, normals estimated), 30
    poses, each matched once unweighted and once weighted from the same start. A wall
    3 m away is ten times noisier than one at 30 cm; weighting them alike lets the far
    points set the error. The weighted information must also say how large the errors
    are: ``eᵀΩe`` of the true error is χ²(3)-distributed, mean 3, when it is right.
    """
    rng = np.random.default_rng(5)
    errors: dict[float, list[tuple[float, float, float]]] = {0.0: [], 0.01: []}
    for i, truth in enumerate(_random_poses(maze_world, 30, 9)):
        keyframes = []
        for j in range(4):
            pose = truth + np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(-0.5, 0.5)])
            angles, ranges = cast_scan(maze_world, pose, noise_rel=0.01, seed=1000 + 10 * i + j)
            keyframes.append((pose, _points(angles, ranges), np.zeros(2)))
        target = Target.from_scans(keyframes, voxel_size_m=0.01)
        angles, ranges = cast_scan(maze_world, truth, noise_rel=0.01, seed=i)
        src = _points(angles, ranges)
        src = src[voxel_downsample(src, 0.025)]
        start = truth + np.array([0.02, -0.015, 0.02])
        for ratio, out in errors.items():
            result = match_scan(target, src, start, IcpParams(range_noise_ratio=ratio), sensor_xy=np.zeros(2))
            assert result.converged and not result.degenerate
            err = result.pose - truth
            err[2] = math.remainder(err[2], math.tau)
            out.append((math.hypot(err[0], err[1]), err[2], float(err @ result.information @ err)))
    plain, weighted = np.array(errors[0.0]), np.array(errors[0.01])

    def rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(a**2)))

    assert rms(weighted[:, 0]) < 0.002
    assert rms(weighted[:, 0]) < 0.9 * rms(plain[:, 0])  # about 1.8 -> 1.4 mm
    assert rms(weighted[:, 1]) < 0.8 * rms(plain[:, 1])  # about 0.11 -> 0.07 degrees
    assert 1.5 < float(np.mean(weighted[:, 2])) < 4.5


def test_range_noise_weighting_needs_a_noise_floor() -> None:
    with pytest.raises(ValueError, match="range_noise_ratio"):
        IcpParams(range_noise_ratio=-0.01)
    with pytest.raises(ValueError, match="noise_floor_m"):
        IcpParams(range_noise_ratio=0.01, noise_floor_m=0.0)


def test_information_grows_with_points_and_is_symmetric(maze_world: World, maze_target: Target, cast_scan) -> None:
    truth = _random_poses(maze_world, 1, 21)[0]
    angles, ranges = cast_scan(maze_world, truth, noise_rel=0.01)
    src = _points(angles, ranges)
    full = match_scan(maze_target, src, truth)
    half = match_scan(maze_target, src[::2], truth)
    np.testing.assert_allclose(full.information, full.information.T, atol=1e-9 * np.abs(full.information).max())
    assert np.all(np.linalg.eigvalsh(full.information) > 0)
    assert np.trace(full.information) > 1.5 * np.trace(half.information)


def _box_room(half_m: float = 2.0, step_m: float = 0.02) -> np.ndarray:
    t = np.arange(-half_m, half_m, step_m)
    side = np.full_like(t, half_m)
    return np.concatenate([np.c_[t, side], np.c_[t, -side], np.c_[side, t], np.c_[-side, t]])


def test_a_wall_off_as_a_whole_makes_the_clustered_information_honest_about_it() -> None:
    """A room whose north wall the scan sees 3 cm off (the submap's wall misplaced): the match is pulled
    1.6 cm north; the Hessian's std across the walls stays about a millimetre, the clustered one grows
    to half the error. With independent point noise alone both agree (within a factor 1.5)."""
    walls = _box_room()
    target = Target(walls, np.zeros(2))
    rng = np.random.default_rng(0)
    src = walls[::3] + rng.normal(0.0, 0.01, (walls[::3].shape[0], 2))
    moved = src.copy()
    moved[moved[:, 1] > 1.9, 1] += 0.03
    start = np.array([0.02, -0.01, 0.01])
    std = {}
    for name, scan in (("independent", src), ("wall off", moved)):
        for cluster_rad in (0.0, 0.35):
            result = match_scan(target, scan, start, IcpParams(information_cluster_rad=cluster_rad))
            std[name, cluster_rad] = np.sqrt(np.diag(np.linalg.inv(result.information)))
    error_y = abs(match_scan(target, moved, start).pose[1])
    assert error_y > 0.01
    assert std["wall off", 0.0][1] < 0.2 * error_y
    assert std["wall off", 0.35][1] > 0.4 * error_y
    ratio = std["independent", 0.35] / std["independent", 0.0]
    assert np.all((ratio >= 1.0) & (ratio < 1.5))


def test_the_clustered_information_is_the_hessians_shape_never_surer_and_symmetric(
    maze_world: World, maze_target: Target, cast_scan
) -> None:
    truth = _random_poses(maze_world, 1, 21)[0]
    angles, ranges = cast_scan(maze_world, truth, noise_rel=0.01)
    src = _points(angles, ranges)
    plain = match_scan(maze_target, src, truth)
    clustered = match_scan(maze_target, src, truth, IcpParams(information_cluster_rad=0.35))
    np.testing.assert_array_equal(plain.pose, clustered.pose)  # only the information differs
    info = clustered.information
    np.testing.assert_allclose(info, info.T, atol=1e-9 * np.abs(info).max())
    # never surer than the Hessian in any direction: H - I_clustered is positive semi-definite
    assert np.all(np.linalg.eigvalsh(plain.information - info) >= -1e-9 * np.abs(plain.information).max())
    assert np.all(np.linalg.eigvalsh(info) > 0)


def test_the_clustered_information_for_the_graph_only_leaves_the_filter_the_hessians(
    maze_world: World, maze_target: Target, cast_scan
) -> None:
    """``information_cluster_filter`` false: the filter's information is the Hessian's, the pose graph's
    edges take the clustered one (``edge_information``); the pose is the same either way."""
    truth = _random_poses(maze_world, 1, 22)[0]
    angles, ranges = cast_scan(maze_world, truth, noise_rel=0.01)
    src = _points(angles, ranges)
    plain = match_scan(maze_target, src, truth)
    both = match_scan(maze_target, src, truth, IcpParams(information_cluster_rad=0.35))
    graph = match_scan(maze_target, src, truth, IcpParams(information_cluster_rad=0.35,
                                                          information_cluster_filter=False))
    np.testing.assert_array_equal(graph.pose, plain.pose)
    np.testing.assert_array_equal(graph.information, plain.information)
    np.testing.assert_array_equal(graph.edge_information, both.information)
    assert plain.graph_information is None and both.graph_information is None
    np.testing.assert_array_equal(plain.edge_information, plain.information)
    np.testing.assert_array_equal(both.edge_information, both.information)


def test_without_overlap_it_gives_up_and_keeps_the_prior(maze_target: Target) -> None:
    far = np.array([[50.0, 50.0], [51.0, 50.0], [50.0, 51.0]])
    prior = np.array([1.0, 2.0, 0.3])
    result = match_scan(maze_target, far, prior)
    assert not result.converged
    np.testing.assert_array_equal(result.pose, prior)
    assert not result.information.any()


def test_estimated_normals_are_perpendicular_to_walls_and_corners_are_dropped() -> None:
    x = np.arange(0.0, 1.0, 0.02)
    wall = np.column_stack((x, 0.3 * x))  # a wall at atan(0.3)
    corner = np.vstack((np.column_stack((x, np.zeros_like(x))), np.column_stack((np.zeros_like(x[1:]), x[1:]))))
    normals, good = estimate_normals(wall, 8, 0.1, 0.2)
    assert good.all()
    direction = np.array([1.0, 0.3]) / math.hypot(1.0, 0.3)
    assert np.max(np.abs(normals @ direction)) < 1e-9
    _, good = estimate_normals(corner, 8, 0.1, 0.2)
    assert not good[0]  # the corner point itself has no single normal
    assert good[10:40].all()


def test_the_lidar_never_matches_the_back_of_a_thin_wall(cast_scan) -> None:
    """A 12 mm wall seen from both sides: each scan must lock onto its own face."""
    from mazebot.sim.world import World, rectangles_outline

    wall = World(
        "wall",
        rectangles_outline(np.array([[-1.0, -0.006, 1.0, 0.006]])),
        np.zeros((0, 3)),
        (0.0, 0.3, 0.0),
        (-1.0, -0.006, 1.0, 0.006),
    )
    # a post so the wall is not degenerate along x
    wall = World(
        "wall",
        np.vstack((wall.segments, rectangles_outline(np.array([[0.3, -0.3, 0.312, 0.3]])))),
        np.zeros((0, 3)),
        (0.0, 0.3, 0.0),
        (-1.0, -0.3, 1.0, 0.3),
    )
    keyframes = []
    for pose in (np.array([0.0, 0.25, 0.0]), np.array([0.0, -0.25, 0.0])):
        angles, ranges = cast_scan(wall, pose)
        keyframes.append((pose, _points(angles, ranges), np.zeros(2)))
    target = Target.from_scans(keyframes, voxel_size_m=0.01)
    for truth in (np.array([0.05, 0.2, 0.1]), np.array([0.05, -0.2, -0.1])):
        angles, ranges = cast_scan(wall, truth)
        result = match_scan(target, _points(angles, ranges), truth + np.array([0.0, 0.01, 0.0]))
        assert abs(result.pose[1] - truth[1]) < 0.002


# -- the Intel Research Lab log: real SICK scans, poses corrected by GMapping ------------------


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose of b in the frame of a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, math.remainder(b[2] - a[2], math.tau)])


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


INTEL_PARAMS = IcpParams(max_correspondence_m=0.5, min_correspondence_m=0.1)


def _intel_icp(lasers: list, i: int, j: int, initial: np.ndarray) -> np.ndarray:
    """Scan j matched against scan i alone (3 cm voxels), in scan i's frame."""
    scan = [(np.zeros(3), lasers[i].points_xy(30.0), np.zeros(2))]
    # 1 degree beams reach 10+ m here: neighbours for the normals are centimetres to decimetres apart
    target = Target.from_scans(scan, voxel_size_m=0.03, normal_neighbours=5, normal_radius_m=0.3)
    src = lasers[j].points_xy(30.0)
    return match_scan(target, src[voxel_downsample(src, 0.03)], initial, INTEL_PARAMS).pose


def test_intel_consecutive_scans_agree_with_gmapping(intel_log_path) -> None:
    """100 consecutive pairs (~1 m, ~5 degrees apart), started 3 cm / 1 degree off GMapping's relative pose.

    GMapping's corrected poses jitter by about 1.5 cm themselves (the best particle
    changes); the next test shows ICP's own precision is several times finer.
    """
    lasers = read_carmen(intel_log_path).lasers
    rng = np.random.default_rng(0)
    trans_err, rot_err = [], []
    for i in range(100):
        truth = _relative(lasers[i].pose, lasers[i + 1].pose)
        d = rng.normal(size=2)
        initial = truth + np.array([*(0.03 * d / np.linalg.norm(d)), math.radians(rng.choice([-1.0, 1.0]))])
        pose = _intel_icp(lasers, i, i + 1, initial)
        trans_err.append(float(np.hypot(*(pose[:2] - truth[:2]))))
        rot_err.append(_angle_error_deg(pose[2], truth[2]))
    assert np.median(trans_err) < 0.025
    assert np.median(rot_err) < 0.5
    assert np.percentile(trans_err, 90) < 0.06


def test_intel_icp_is_self_consistent_around_triangles(intel_log_path) -> None:
    """ICP(i, i+1) then ICP(i+1, i+2) must land where ICP(i, i+2) does: a check of precision
    that needs no ground truth."""
    lasers = read_carmen(intel_log_path).lasers
    closure_m, closure_deg = [], []
    for i in range(0, 100, 2):
        a = _intel_icp(lasers, i, i + 1, _relative(lasers[i].pose, lasers[i + 1].pose))
        b = _intel_icp(lasers, i + 1, i + 2, _relative(lasers[i + 1].pose, lasers[i + 2].pose))
        c = _intel_icp(lasers, i, i + 2, _relative(lasers[i].pose, lasers[i + 2].pose))
        chain = _compose(a, b)
        closure_m.append(float(np.hypot(*(chain[:2] - c[:2]))))
        closure_deg.append(_angle_error_deg(chain[2], c[2]))
    assert np.median(closure_m) < 0.01
    assert np.median(closure_deg) < 0.2


def _intel_match(lasers: list, i: int, j: int, params: IcpParams) -> IcpResult:
    target = Target.from_scans(
        [(np.zeros(3), lasers[i].points_xy(30.0), np.zeros(2))], voxel_size_m=0.03, normal_neighbours=5,
        normal_radius_m=0.3,
    )
    src = lasers[j].points_xy(30.0)
    return match_scan(target, src[voxel_downsample(src, 0.03)], _relative(lasers[i].pose, lasers[j].pose), params)


def _triangle_chi2(lasers: list, i: int, params: IcpParams) -> float:
    """chi² of ICP(i, i+1) ⊕ ICP(i+1, i+2) against ICP(i, i+2) under the three matches' own covariances."""
    a, b, c = (_intel_match(lasers, i, j, params) for i, j in ((i, i + 1), (i + 1, i + 2), (i, i + 2)))
    chain = compose(a.pose, b.pose)
    cos, sin = math.cos(a.pose[2]), math.sin(a.pose[2])
    rotation = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
    lever = np.eye(3)
    lever[:2, 2] = [-(chain[1] - a.pose[1]), chain[0] - a.pose[0]]  # a's heading moves b's position
    cov = (lever @ np.linalg.pinv(a.information) @ lever.T + rotation @ np.linalg.pinv(b.information) @ rotation.T
           + np.linalg.pinv(c.information))
    e = relative_pose(c.pose, chain)
    return float(e @ np.linalg.solve(cov, e))


@pytest.mark.slow
def test_intel_triangles_the_clustered_information_is_nearer_calibrated(intel_log_path) -> None:
    """Triangles of real scans (no reference needed): a calibrated information gives the loop's chi² the
    median of 3 degrees of freedom, 2.37. The Hessian's is surer than the three matches agree (median 7.5
    on scans 0-100); clustered by wall, 4.0."""
    lasers = read_carmen(intel_log_path).lasers
    medians = {}
    for cluster_rad in (0.0, 0.35):
        params = replace(INTEL_PARAMS, information_cluster_rad=cluster_rad)
        medians[cluster_rad] = float(np.median([_triangle_chi2(lasers, i, params) for i in range(0, 100, 2)]))
    assert medians[0.0] > 5.0
    assert 1.5 < medians[0.35] < 0.7 * medians[0.0]


#: a 1° laser, the laser logs' (SICK LMS in its 1° mode)
BEAM_STEP_RAD = math.radians(1.0)


def _wall_hits(bearings_rad: np.ndarray, normal: tuple[float, float], offset_m: float) -> np.ndarray:
    """Where beams from the origin at ``bearings_rad`` hit the line ``nᵀx = offset_m``."""
    n = np.asarray(normal, dtype=np.float64)
    beams = np.column_stack((np.cos(bearings_rad), np.sin(bearings_rad)))
    return beams * (offset_m / (beams @ n))[:, None]


def _room_with_a_far_wall(far_wall_m: float, bearing_shift_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """A scan from the origin at 1° steps: near walls 1–1.6 m away behind and to the right, a wall ``far_wall_m`` ahead
    (more than half the points); the walls' unit normals (towards the origin) with it.

    ``bearing_shift_rad`` turns the bearings of the far wall's beams: half a step gives a submap whose far points
    lie between the scan's, as one seen from another pose does.
    """
    near_behind = np.radians(np.arange(160.0, 201.0))  # x = −1.5, 41 beams
    near_right = np.radians(np.arange(-80.0, -59.0))  # y = −1, 21 beams
    far = np.radians(np.arange(-35.0, 36.0)) + bearing_shift_rad  # x = far_wall_m, 71 beams
    points = np.vstack((
        _wall_hits(near_behind, (-1.0, 0.0), 1.5), _wall_hits(near_right, (0.0, -1.0), 1.0),
        _wall_hits(far, (1.0, 0.0), far_wall_m),
    ))
    normals = np.vstack((
        np.tile((1.0, 0.0), (near_behind.size, 1)), np.tile((0.0, 1.0), (near_right.size, 1)),
        np.tile((-1.0, 0.0), (far.size, 1)),
    ))
    return points, normals


def _far_wall_match(fitness_beam_spacing: float, far_wall_m: float = 10.0) -> IcpResult:
    """The scan matched from the true pose (the origin) against a submap of the same walls whose far points lie
    half a beam step aside (8.7 cm at 10 m), near walls sampled densely, through a fixed gate of 5 cm."""
    target_points, target_normals = _room_with_a_far_wall(10.0, 0.5 * BEAM_STEP_RAD)
    dense_behind = np.column_stack((np.full(300, -1.5), np.linspace(-0.55, 0.55, 300)))
    dense_right = np.column_stack((np.linspace(0.17, 0.58, 100), np.full(100, -1.0)))
    far_only = target_points[np.isclose(target_points[:, 0], 10.0)]
    points = np.vstack((dense_behind, dense_right, far_only))
    normals = np.vstack((
        np.tile((1.0, 0.0), (300, 1)), np.tile((0.0, 1.0), (100, 1)), np.tile((-1.0, 0.0), (far_only.shape[0], 1)),
    ))
    assert target_normals.shape[1] == 2
    target = Target(points, viewpoints_xy=np.zeros(2), normals=normals)
    scan, _ = _room_with_a_far_wall(far_wall_m, 0.0)
    params = IcpParams(max_correspondence_m=0.05, min_correspondence_m=0.05, fitness_beam_spacing=fitness_beam_spacing)
    return match_scan(target, scan, np.zeros(3), params, beam_step_rad=BEAM_STEP_RAD)


def test_a_right_match_counts_a_far_walls_points_within_the_beams_spacing() -> None:
    """At 10 m a 1° laser's hits are 17 cm apart, the submap's nearest far point up to half that from a right
    scan point and beyond ICP's gate: the gate alone counts the match's inliers under a half; the beams' spacing
    counts them, and the pose is the same (the truth)."""
    gated = _far_wall_match(0.0)
    spaced = _far_wall_match(1.0)
    assert gated.fitness < 0.5
    assert spaced.fitness >= 0.9
    assert spaced.gated_fitness == pytest.approx(gated.fitness)
    np.testing.assert_array_equal(spaced.pose, gated.pose)
    assert float(np.hypot(*spaced.pose[:2])) < 1e-3 and abs(float(spaced.pose[2])) < math.radians(0.05)


def test_the_beams_spacing_does_not_count_a_wall_half_a_metre_off() -> None:
    """The scan's far wall 0.5 m beyond the submap's (another wall): its points stay outside the spacing (17 cm)."""
    spaced = _far_wall_match(1.0, far_wall_m=10.5)
    assert spaced.fitness < 0.5
