"""The map a robot keeps once its exploration is over follows the pose graph's last corrections."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mazebot.sim.raster import true_occupancy
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.slam import SlamParams
from tests.slam.test_lattice_fit import chain_job
from tests.slam.test_wall_lattice import keyframe_at, route_poses

#: keyframes painted this far off where the graph has them now (m): under the 1 cm rebuild threshold
STALE_M = 0.007


def walls_off_the_world(grid: OccupancyGrid, world) -> int:
    """The grid's occupied cells that no wall of ``world`` touches (the grid's frame is the world's).

    The truth raster is drawn on the grid's own cells, so a wall painted where it stands costs
    nothing whatever its phase against the cells; one painted a few millimetres over shows as the
    next cell blackened along the stretch where the wall's face lies near a cell boundary.
    """
    truth, _ = true_occupancy(world, grid.resolution_m, grid.origin_m, grid.shape)
    return int(np.sum(grid.occupied_mask() & ~truth))


def painted_at(keyframes, poses: np.ndarray) -> OccupancyGrid:
    """The grid of ``keyframes`` painted at ``poses`` (what the running map holds)."""
    grid = SlamParams().grid.new_grid()
    grid.rebuild(kf.rays(poses[k]) for k, kf in enumerate(keyframes))
    return grid


def test_once_explored_a_correction_under_the_thresholds_repaints_the_walls_where_they_are(maze_world, cast_scan):
    """Keyframes painted 7 mm off (under the 1 cm threshold) and now optimized onto the truth: while
    exploring the job keeps the map it has; once the exploration is over it rebuilds it, and its walls
    are blackened where the world's are (as many cells off them as a map painted at the true poses)."""
    truth = route_poses(maze_world)
    keyframes = [keyframe_at(maze_world, cast_scan, k, p, seed=k) for k, p in enumerate(truth)]
    painted = truth.copy()
    painted[1:, 1] += STALE_M
    # the chain as its matches saw it, no wall priors: the optimization keeps the true poses
    chain = chain_job(keyframes, truth, None)
    job = replace(chain, integrated_poses=painted, anchor_wall=None, wall_reference_rad=None)
    stale = painted_at(keyframes, painted)

    exploring = job.run()
    assert exploring.grid is None  # moved less than the thresholds: the stale map stays
    off = replace(job, exploration_over=True).run()
    assert off.grid is None  # [slam.graph] rebuild_after_exploration off (the default): as while exploring
    explored = replace(job, exploration_over=True, params=SlamParams(rebuild_after_exploration=True)).run()
    assert explored.grid is not None and explored.poses is not None
    np.testing.assert_allclose(explored.poses[:, :2], truth[:, :2], atol=0.002)

    before, after, at_truth = (
        walls_off_the_world(g, maze_world) for g in (stale, explored.grid, painted_at(keyframes, truth))
    )
    assert after == at_truth
    assert after < before / 2
