"""Continuing a saved run: the saved map in SLAM, and the robot found in it again.

``mazebot run --resume RUN`` loads the run's keyframes, pose graph and log-odds grid into
a fresh :class:`ResumedSlam`. The robot is put down again near the saved run's start (the
map frame's origin), but not exactly, so before its first update the SLAM re-localizes:
the first revolution (de-skewed like any other) is matched with ICP
(:func:`mazebot.slam.icp.match_scan`) against a submap of the saved keyframes around the
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

import logging
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from mazebot.errors import UsageError
from mazebot.geometry import compose, inverse, transform_points
from mazebot.io.scan import Scan
from mazebot.persist.snapshot import SavedRun, saved_grid
from mazebot.slam.icp import IcpResult, match_scan
from mazebot.slam.keyframes import build_target
from mazebot.slam.observed import ObservedSlam
from mazebot.slam.slam import OdometrySource, PaintDecision, SlamUpdate

log = logging.getLogger(__name__)

#: Variance used for a sequential edge the saved graph does not have (a resumed chain's seam).
SEAM_VARIANCE = 1.0


@dataclass(frozen=True)
class Relocalization:
    """Where the first scan was found: its map pose, and how well it matched."""

    pose: np.ndarray  # (3,) map pose at the end of the first revolution
    accepted: bool
    fitness: float
    rmse_m: float
    tried: int


class ResumedSlam(ObservedSlam):
    """A Slam that starts from a saved run and re-localizes on its first revolution.

    Example::

        slam = ResumedSlam(params, load_run(path), guess=(0, 0, 0), background=True)
        slam.update(scan, odometry)          # the first call re-localizes
        slam.relocalization.pose
    """

    def __init__(
        self,
        params: Any,
        saved: SavedRun,
        guess: tuple[float, float, float] = (0.0, 0.0, 0.0),
        *,
        search_xy_m: float = 0.1,
        search_theta_rad: float = 0.3,
        submap_radius_m: float = 1.0,
        **kwargs: Any,
    ) -> None:
        super().__init__(params, **kwargs)
        if abs(saved.resolution_m - self.grid.resolution_m) > 1e-12:
            raise UsageError(
                f"run {saved.path} has {saved.resolution_m} m cells but slam.grid.resolution_m asks for "
                f"{self.grid.resolution_m} m"
            )
        self.guess = np.asarray(guess, dtype=np.float64)
        self.search_xy_m = search_xy_m
        self.search_theta_rad = search_theta_rad
        self.submap_radius_m = submap_radius_m
        self.relocalization: Relocalization | None = None
        self._restore(saved)

    def _restore(self, saved: SavedRun) -> None:
        for kf in saved.keyframes:
            kf.normal_params = self.params.normals
        self.keyframes = list(saved.keyframes)
        self.graph = saved.graph
        self.grid = saved_grid(saved, self.grid)
        reference = saved.meta.get("wall_reference_rad")
        self.wall_reference_rad = None if reference is None else float(reference)
        ei, ej, _, omega = self.graph.edge_arrays
        sequential = {int(j): k for k, (i, j) in enumerate(zip(ei.tolist(), ej.tolist(), strict=True)) if j == i + 1}
        for j in range(1, len(self.keyframes)):
            k = sequential.get(j)
            if k is None:
                var_xy = var_theta = SEAM_VARIANCE
            else:
                cov = np.linalg.inv(omega[k])
                var_xy, var_theta = 0.5 * float(cov[0, 0] + cov[1, 1]), float(cov[2, 2])
            self._edge_var_xy.append(var_xy)
            self._edge_var_theta.append(var_theta)

    def update_steps(
        self, scan: Scan, odometry: OdometrySource, *, paint: bool | PaintDecision = True
    ) -> Generator[None, None, SlamUpdate]:
        if self.relocalization is None and self.keyframes:
            self.relocalization = self.relocalize(scan, odometry)
            yield
        return (yield from super().update_steps(scan, odometry, paint=paint))

    def relocalize(self, scan: Scan, odometry: OdometrySource) -> Relocalization:
        """Find the first revolution in the saved map; sets ``initial_pose`` and the submap."""
        p = self.params
        prepared, odom = self.prepare(scan, odometry)
        poses = self.keyframe_poses()
        dist = np.hypot(poses[:, 0] - self.guess[0], poses[:, 1] - self.guess[1])
        near = np.flatnonzero(dist <= self.submap_radius_m + self.search_xy_m)
        near = near[np.argsort(dist[near], kind="stable")[: max(p.submap_keyframes, 40)]]
        target = build_target([self.keyframes[k] for k in sorted(near.tolist())], p.submap_voxel_m)
        if target is None or prepared.points_match.shape[0] == 0:  # no keyframe near, or none with points
            log.warning("re-localization: no saved keyframe near the start; continuing from the guess")
            self.initial_pose = compose(self.guess, inverse(odom))
            return Relocalization(self.guess.copy(), False, 0.0, float("inf"), 0)
        steps_xy = (-self.search_xy_m, 0.0, self.search_xy_m)
        steps_th = np.linspace(-self.search_theta_rad, self.search_theta_rad, 7)
        # a corridor leaves ICP free along it: among the acceptable matches the one whose
        # hits (far walls included) fall on the saved map's walls wins
        walls = ndimage.binary_dilation(self.grid.log_odds > self.grid.occupied_logodds, iterations=1)
        hits = prepared.points_full

        def on_walls(pose: np.ndarray) -> float:
            rows, cols = self.grid.to_cell(transform_points(pose, hits))
            inside = (rows >= 0) & (rows < walls.shape[0]) & (cols >= 0) & (cols < walls.shape[1])
            return float(walls[rows[inside], cols[inside]].sum()) / max(1, hits.shape[0])

        best: IcpResult | None = None
        best_score = -1.0
        best_any: IcpResult | None = None
        tried = 0
        for dth in steps_th:
            for dx in steps_xy:
                for dy in steps_xy:
                    start = self.guess + np.array([dx, dy, dth])
                    match = match_scan(target, prepared.points_match, start, p.icp, sensor_xy=prepared.sensor_xy)
                    tried += 1
                    if best_any is None or match.fitness > best_any.fitness:
                        best_any = match
                    if self.acceptable(match):
                        score = on_walls(match.pose)
                        tie = abs(score - best_score) <= 1e-9
                        if score > best_score + 1e-9 or (tie and best is not None and match.rmse_m < best.rmse_m):
                            best, best_score = match, score
        chosen = best if best is not None else best_any
        assert chosen is not None
        pose = chosen.pose.copy() if best is not None else self.guess.copy()
        self.initial_pose = compose(pose, inverse(odom))
        self.target = target
        self._in_submap = set(near.tolist())
        self._target_position = pose[:2].copy()
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
