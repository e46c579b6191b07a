"""Continuing a saved run: the saved map in SLAM, and the robot found in it again.

``mazebot run --resume RUN`` loads the run's keyframes, pose graph and log-odds grid into
a fresh :class:`~mazebot.slam.slam.Slam` (:func:`resume_slam`, through its public
``continue_map``). The robot is put down again near the saved run's start (the map
frame's origin), but not exactly, so before its first update the SLAM re-localizes
(:func:`relocalize`, the Slam's ``locate_first``): the first revolution (de-skewed like
any other) is matched with ICP (:func:`mazebot.slam.icp.match_scan`) against a submap of the saved keyframes around the
guess, from every start of a small pose grid (±``search_xy_m`` in x and y,
±``search_theta_rad`` in heading). Among the acceptable matches (SLAM's own fitness and
residual limits) the one that puts most of the revolution's hits on the saved map's
walls wins (ICP alone slides along a corridor; the far walls decide), and its pose becomes the map
pose of the odometry frame's origin, so everything that follows is in the saved map's
frame. If no start gives an acceptable match the guess stands and a warning says so.

The new keyframes continue the saved graph (the first one is linked to the last saved
keyframe by a weak odometry edge), and loop closure ties them to the saved ones nearby.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from mazebot.errors import UsageError
from mazebot.geometry import compose, inverse, transform_points
from mazebot.io.scan import Scan
from mazebot.persist.snapshot import SavedRun, saved_grid
from mazebot.slam.icp import IcpResult, match_scan
from mazebot.slam.keyframes import build_target
from mazebot.slam.posegraph import PoseGraph
from mazebot.slam.slam import OdometrySource, Relocalization, Slam, SlamParams

log = logging.getLogger(__name__)

#: Variance used for a sequential edge the saved graph does not have (a resumed chain's seam).
SEAM_VARIANCE = 1.0

__all__ = ["SEAM_VARIANCE", "Relocalization", "chain_variances", "relocalize", "resume_slam"]


def resume_slam(
    params: SlamParams,
    saved: SavedRun,
    guess: tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    search_xy_m: float = 0.1,
    search_theta_rad: float = 0.3,
    submap_radius_m: float = 1.0,
    background: bool = False,
    record_trajectory: bool = True,
    before_update: Callable[[Scan], None] | None = None,
) -> Slam:
    """A Slam that continues ``saved`` and re-localizes on its first revolution near ``guess``.

    ``search_*`` and ``submap_radius_m`` are :func:`relocalize`'s; the other options are
    :class:`~mazebot.slam.slam.Slam`'s. The first update fills ``slam.relocalization``.

    Example::

        slam = resume_slam(params, load_run(path), guess=(0, 0, 0), background=True)
        slam.update(scan, odometry)          # the first call re-localizes
        slam.relocalization.pose
    """
    locate = functools.partial(
        relocalize,
        guess=np.asarray(guess, dtype=np.float64),
        search_xy_m=search_xy_m,
        search_theta_rad=search_theta_rad,
        submap_radius_m=submap_radius_m,
    )
    slam = Slam(params, background=background, record_trajectory=record_trajectory, before_update=before_update,
                locate_first=locate)
    if abs(saved.resolution_m - slam.grid.resolution_m) > 1e-12:
        raise UsageError(
            f"run {saved.path} has {saved.resolution_m} m cells but slam.grid.resolution_m asks for "
            f"{slam.grid.resolution_m} m"
        )
    reference = saved.meta.get("wall_reference_rad")
    slam.continue_map(
        saved.keyframes,
        saved.graph,
        saved_grid(saved, slam.grid),
        wall_reference_rad=None if reference is None else float(reference),
        chain_variances=chain_variances(saved.graph, len(saved.keyframes)),
    )
    return slam


def chain_variances(graph: PoseGraph, keyframes: int) -> list[tuple[float, float]]:
    """(xy, heading) variances of the sequential edges 0→1 … of a saved graph (its seams: :data:`SEAM_VARIANCE`).

    The xy variance is the mean of the edge covariance's x and y terms, as SLAM keeps it for
    its own edges (:meth:`mazebot.slam.slam.Slam.continue_map`).
    """
    ei, ej, _, omega = graph.edge_arrays
    sequential = {int(j): k for k, (i, j) in enumerate(zip(ei.tolist(), ej.tolist(), strict=True)) if j == i + 1}
    out: list[tuple[float, float]] = []
    for j in range(1, keyframes):
        k = sequential.get(j)
        if k is None:
            out.append((SEAM_VARIANCE, SEAM_VARIANCE))
        else:
            cov = np.linalg.inv(omega[k])
            out.append((0.5 * float(cov[0, 0] + cov[1, 1]), float(cov[2, 2])))
    return out


def relocalize(
    slam: Slam,
    scan: Scan,
    odometry: OdometrySource,
    guess: np.ndarray,
    *,
    search_xy_m: float = 0.1,
    search_theta_rad: float = 0.3,
    submap_radius_m: float = 1.0,
) -> Relocalization:
    """Find the first revolution in ``slam``'s map near ``guess``, and start the Slam there.

    Reads the Slam's public state (keyframes, grid, parameters, :meth:`~Slam.prepare`) and
    places it with :meth:`~Slam.start_in_map`: the odometry frame's map pose, and the submap
    of the saved keyframes around the found pose for the first match.
    """
    p = slam.params
    guess = np.asarray(guess, dtype=np.float64)
    prepared, odom = slam.prepare(scan, odometry)
    poses = slam.keyframe_poses()
    dist = np.hypot(poses[:, 0] - guess[0], poses[:, 1] - guess[1])
    near = np.flatnonzero(dist <= submap_radius_m + search_xy_m)
    near = near[np.argsort(dist[near], kind="stable")[: max(p.submap_keyframes, 40)]]
    target = build_target([slam.keyframes[k] for k in sorted(near.tolist())], p.submap_voxel_m)
    if target is None or prepared.points_match.shape[0] == 0:  # no keyframe near, or none with points
        log.warning("re-localization: no saved keyframe near the start; continuing from the guess")
        slam.start_in_map(compose(guess, inverse(odom)))
        return Relocalization(guess.copy(), False, 0.0, float("inf"), 0)
    steps_xy = (-search_xy_m, 0.0, search_xy_m)
    steps_th = np.linspace(-search_theta_rad, search_theta_rad, 7)
    # a corridor leaves ICP free along it: among the acceptable matches the one whose
    # hits (far walls included) fall on the saved map's walls wins
    grid = slam.grid
    walls = ndimage.binary_dilation(grid.log_odds > grid.occupied_logodds, iterations=1)
    hits = prepared.points_full

    def on_walls(pose: np.ndarray) -> float:
        rows, cols = grid.to_cell(transform_points(pose, hits))
        inside = (rows >= 0) & (rows < walls.shape[0]) & (cols >= 0) & (cols < walls.shape[1])
        return float(walls[rows[inside], cols[inside]].sum()) / max(1, hits.shape[0])

    best: IcpResult | None = None
    best_score = -1.0
    best_any: IcpResult | None = None
    tried = 0
    for dth in steps_th:
        for dx in steps_xy:
            for dy in steps_xy:
                start = guess + np.array([dx, dy, dth])
                match = match_scan(target, prepared.points_match, start, p.icp, sensor_xy=prepared.sensor_xy)
                tried += 1
                if best_any is None or match.fitness > best_any.fitness:
                    best_any = match
                if slam.acceptable(match):
                    score = on_walls(match.pose)
                    tie = abs(score - best_score) <= 1e-9
                    if score > best_score + 1e-9 or (tie and best is not None and match.rmse_m < best.rmse_m):
                        best, best_score = match, score
    chosen = best if best is not None else best_any
    assert chosen is not None
    pose = chosen.pose.copy() if best is not None else guess.copy()
    slam.start_in_map(compose(pose, inverse(odom)), target, submap_xy=pose[:2])
    if best is None:
        log.warning(
            "re-localization failed (best fitness %.2f, rmse %.3f m); continuing from the guess",
            chosen.fitness,
            chosen.rmse_m,
        )
    else:
        log.info(
            "re-localized in the saved map at (%.3f m, %.3f m, %.3f rad), fitness %.2f, rmse %.4f m",
            *pose,
            chosen.fitness,
            chosen.rmse_m,
        )
    return Relocalization(pose, best is not None, float(chosen.fitness), float(chosen.rmse_m), tried)
