"""The lattice's pitch and direction measured from keyframes' walls; a room turns the lattice priors off."""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np
import pytest

from mazebot.geometry import relative_pose
from mazebot.sim.hand_maze import HandBuild, hand_built_world
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.room import make_room
from mazebot.slam.lattice_fit import fit_pitch
from mazebot.slam.slam import LoopClosureJob, Slam, SlamParams
from mazebot.slam.wall_lattice import LatticeParams
from mazebot.slam.wall_priors import LATTICE_REFIT_GROWTH
from tests.slam.test_wall_lattice import keyframe_at, route_poses

CONFIGURED = LatticeParams(pitch_m=0.3048, pitch_search=0.08)


def chain_job(keyframes, poses, lattice: LatticeParams | None) -> LoopClosureJob:
    """An optimization of the chain of ``poses`` as its scan matches saw it, the wall direction from keyframe 0."""
    count = len(poses)
    ei, ej = np.arange(count - 1), np.arange(1, count)
    info = np.tile(np.diag([1 / 0.005**2, 1 / 0.005**2, 1 / 0.01**2]), (count - 1, 1, 1))
    direction, _, _ = keyframes[0].wall_direction()  # measured, not told
    return LoopClosureJob(
        candidates=[],
        keyframes=keyframes,
        poses=poses.copy(),
        integrated_poses=poses.copy(),
        edges=(ei, ej, relative_pose(poses[ei], poses[ej]), info),
        params=SlamParams(lattice=lattice),
        wall_reference_rad=math.remainder(direction + float(poses[0, 2]), math.pi / 2),
        optimize_anyway=True,
        anchor_wall=(direction, 0.01),  # as loose as any keyframe: the direction from all the walls
    )


@pytest.mark.parametrize("pitch_m", [0.29, 0.32])
def test_keyframes_measure_a_pitch_and_angle_they_were_not_told(cast_scan, pitch_m: float) -> None:
    layout = generate_maze(6, 6, seed=3, kind="braided", cell_size_m=pitch_m)
    world = hand_built_world(layout, HandBuild(pitch_error_max=0.0, maze_angle_rad=math.radians(17.0)), 3)
    truth = route_poses(world)
    keyframes = [keyframe_at(world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    for kf, pose in zip(keyframes, truth, strict=True):
        kf.pose = pose.copy()
    result = chain_job(keyframes, truth, CONFIGURED).run()
    fit = result.lattice_fit
    assert fit is not None and fit.fits
    assert fit.pitch_m == pytest.approx(world.maze.cell_size_m, abs=0.002)
    assert abs(math.degrees(math.remainder(result.wall_reference_rad - math.radians(17.0), math.pi / 2))) < 0.3
    assert fit.line_rms_m > 0.002  # boards off their lines: the priors trust the lattice that much less


def test_on_a_perfect_lattice_the_lines_lie_on_it(maze_world, cast_scan) -> None:
    truth = route_poses(maze_world)
    keyframes = [keyframe_at(maze_world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    fit = chain_job(keyframes, truth, CONFIGURED).run().lattice_fit
    assert fit is not None and fit.fits
    assert fit.pitch_m == pytest.approx(0.3048, abs=0.0005)
    assert fit.line_rms_m < 0.002  # below the configured trust (5 mm): the exact maze's priors are today's


def test_a_room_turns_the_lattice_priors_off(cast_scan) -> None:
    room = make_room(2.0, 1.2, cylinders=4, seed=0, footprint_radius_m=0.09)
    rng = np.random.default_rng(1)
    poses = np.column_stack((rng.uniform(0.2, 1.8, 12), rng.uniform(0.2, 1.0, 12), rng.uniform(-3, 3, 12)))
    keyframes = [keyframe_at(room, cast_scan, k, p, seed=k) for k, p in enumerate(poses)]
    result = chain_job(keyframes, poses, CONFIGURED).run()
    assert result.lattice_fit is not None and not result.lattice_fit.measured and not result.lattice_fit.fits
    # and without the lattice's edges the job is the one without a lattice at all
    plain = chain_job(keyframes, poses, None).run()
    assert np.allclose(result.poses, plain.poses, atol=1e-9)


def test_two_lines_fit_any_pitch_so_they_measure_none() -> None:
    u = np.repeat([0.0, 2.0], 200)
    v = np.repeat([0.0, 1.2], 200)
    fit = fit_pitch([(u, np.ones(u.size), 0), (v, np.ones(v.size), 1)], 0.3048, search=0.08)
    assert fit.lines == (1, 1) or max(fit.lines) <= 2
    assert not fit.measured and not fit.fits


def test_a_maze_whose_walls_miss_the_lattice_turns_the_priors_off_and_says_so_once(cast_scan, caplog) -> None:
    """A maze of 0.40 m cells configured as 1 ft: its walls lie on no lattice within the pitch
    search, so the job adds no lattice edge (its poses are the plain job's) and SLAM logs the
    switch once, however many jobs report it."""
    layout = generate_maze(6, 6, seed=3, kind="braided", cell_size_m=0.40)
    world = hand_built_world(layout, HandBuild(pitch_error_max=0.0, maze_angle_rad=0.0, clutter=0), 3)
    truth = route_poses(world)
    rng = np.random.default_rng(2)
    drifted = truth + np.column_stack((np.cumsum(rng.normal(0, 0.004, (len(truth), 2)), axis=0),
                                       np.zeros(len(truth))))
    keyframes = [keyframe_at(world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    result = chain_job(keyframes, drifted, CONFIGURED).run()
    fit = result.lattice_fit
    assert fit is not None and not fit.fits
    plain = chain_job(keyframes, drifted, None).run()
    assert np.allclose(result.poses, plain.poses, atol=1e-9)
    slam = Slam(SlamParams(lattice=CONFIGURED))
    with caplog.at_level(logging.INFO, logger="mazebot.slam.slam"):
        for k in range(4):  # with three lines on an axis or without: no lattice either way
            slam._note_lattice(replace(fit, measured=bool(k % 2)), 0)
    off = [r for r in caplog.records if "lattice priors off" in r.getMessage()]
    assert len(off) == 1


def test_the_lines_lie_between_the_faces_seen_from_both_sides_however_unequally_seen() -> None:
    """Boards 12 mm thick on lines at 0.10 + 0.30 k m: ten times more points on their +u faces
    than on their -u faces, and the axis's lines are still the boards' centre lines."""
    k = np.arange(6) * 0.30
    plus_u = np.repeat(0.106 + k, 1000)
    minus_u = np.repeat(0.094 + k, 100)
    v = np.repeat(0.05 + k, 300)
    fit = fit_pitch([(plus_u, np.ones(plus_u.size), 0), (minus_u, np.ones(minus_u.size), 0),
                     (v + 0.006, np.ones(v.size), 1), (v - 0.006, np.ones(v.size), 1)], 0.30, search=0.0)
    assert math.remainder(fit.phase_m[0] - 0.10, 0.30) == pytest.approx(0.0, abs=0.0015)
    assert math.remainder(fit.phase_m[1] - 0.05, 0.30) == pytest.approx(0.0, abs=0.0015)


@pytest.mark.parametrize("count, spread_m", [(18_000, 3.0), (200, 60.0), (5_000, 500.0), (1, 1.0)])
def test_the_histogram_counts_every_bin_as_sorting_the_bins_did(count: int, spread_m: float) -> None:
    """A maze's positions go into a dense count, a building's far-flung ones are sorted: the same bins either way,
    each bin's weights summed in the same order (the same floats), the same as the sorted form always gave."""
    from mazebot.slam.lattice_fit import _histogram

    rng = np.random.default_rng(count)
    x = rng.uniform(-spread_m, spread_m, count)
    w = rng.uniform(0.0, 2.0, count)
    w[::7] = 0.0  # a bin holding only weightless positions is no bin
    index = np.floor(x / 0.002).astype(np.int64)
    keys, inverse = np.unique(index, return_inverse=True)
    weight = np.bincount(inverse, weights=w, minlength=keys.size)
    centres, weights = _histogram(x, w, 0.002)
    assert np.array_equal(centres, (keys[weight > 0] + 0.5) * 0.002)
    assert np.array_equal(weights, weight[weight > 0])


def test_within_range_is_hypots_answer_on_the_circle_beside_it_and_for_nan_and_inf() -> None:
    from mazebot.slam.wall_priors import within_radius

    rng = np.random.default_rng(3)
    for radius in rng.uniform(0.1, 2.0, 10):
        dx, dy = rng.uniform(-2.0, 2.0, 20_000), rng.uniform(-2.0, 2.0, 20_000)
        angle = rng.uniform(0.0, math.tau, 2_000)
        dx[:2_000], dy[:2_000] = radius * np.cos(angle), radius * np.sin(angle)  # on the circle, to rounding
        dx[2_000:4_000], dy[2_000:4_000] = np.nextafter(dx[:2_000], 10.0), dy[:2_000]  # an ulp beside it
        dx[4_000:4_010], dx[4_010:4_020] = np.nan, np.inf
        assert np.array_equal(within_radius(dx, dy, float(radius)), np.hypot(dx, dy) <= radius)


def test_a_job_takes_the_last_fit_again_until_the_keyframes_grew_by_a_quarter(maze_world, cast_scan) -> None:
    """The lattice is the maze's: a job a few keyframes after the last gives the same priors without
    fitting it again; a quarter more keyframes, or the final rebuild, fit it afresh."""
    truth = route_poses(maze_world)
    keyframes = [keyframe_at(maze_world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    count = len(keyframes)
    fresh = chain_job(keyframes, truth, CONFIGURED).run()
    assert fresh.lattice_fit is not None and fresh.lattice_fit.fits and fresh.lattice_fit_keyframes == count
    # a fit known from fewer keyframes, which no refit would give (a pitch 1 mm off): taken as it is
    known = replace(fresh.lattice_fit, pitch_m=fresh.lattice_fit.pitch_m + 0.001)
    earlier = math.ceil(count / LATTICE_REFIT_GROWTH) + 1  # grew by less than a quarter since
    reused = replace(chain_job(keyframes, truth, CONFIGURED), known_fit=(known, earlier)).run()
    assert reused.lattice_fit == known and reused.lattice_fit_keyframes == earlier
    # the same fit as a fresh one: the same priors, the same poses
    same = replace(chain_job(keyframes, truth, CONFIGURED), known_fit=(fresh.lattice_fit, earlier)).run()
    assert same.poses is not None and fresh.poses is not None
    np.testing.assert_array_equal(same.poses, fresh.poses)
    # grown by a quarter, a fit that did not fit, or the final rebuild: fitted again
    for job in (
        replace(chain_job(keyframes, truth, CONFIGURED), known_fit=(known, math.floor(count / LATTICE_REFIT_GROWTH))),
        replace(chain_job(keyframes, truth, CONFIGURED), known_fit=(replace(known, fits=False), earlier)),
        replace(chain_job(keyframes, truth, CONFIGURED), known_fit=(known, earlier), rebuild_anyway=True),
    ):
        result = job.run()
        assert result.lattice_fit == fresh.lattice_fit and result.lattice_fit_keyframes == count
