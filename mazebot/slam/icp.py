"""Point-to-line ICP (2D point-to-plane) of a scan against a local submap.

The method is the one of Nayak, Chiang and Kanupriyaa, *2D Autonomous Mapping* (CMU 18-500
report), section III.B: a kd-tree over the reference (target) points, point-to-plane error,
outlier rejection, and a convergence test of at most 150 iterations or a step below 1 cm /
0.01 rad. Each iteration:

1. **Transform** the source points by the current pose estimate ``(x, y, θ)``.
2. **Associate** each with its nearest target point (scipy ``cKDTree``), among the
   ``candidates`` nearest keeping the first whose surface faces the lidar (a lidar never
   sees the back of a wall: with 12 mm maze walls both faces lie within one grid cell,
   and matching the wrong face biases the pose by the wall's thickness).
3. **Reject outliers**: a distance gate that starts at ``max_correspondence_m`` and
   shrinks to the mean + 3 std of the accepted distances (Zhang, IJCV 1994; the seed's
   "mean distance plus a margin" rule, made adaptive), never below
   ``min_correspondence_m``.
4. **Weight** the point-to-line residuals ``r_i = n_iᵀ(R p_i + t − q_i)`` (Chen &
   Medioni 1992; Censi, "An ICP variant using a point-to-line metric", ICRA 2008) with
   the Cauchy kernel ``w = 1 / (1 + (r/c)²)``, ``c`` from the residuals' median
   absolute deviation. With ``range_noise_ratio`` ρ > 0 each residual is first divided
   by its expected noise (weighted least squares, below) and the kernel acts on the
   normalized residual ``e_i = r_i / σ_i``.
5. **Solve** the linearized least squares ``(JᵀWJ) δ = −JᵀWr`` (3×3) in the eigenbasis
   of ``JᵀWJ``: directions whose eigenvalue is below ``degeneracy_ratio`` times the
   largest are not observable (a straight corridor does not say where along it the
   robot is), so the pose keeps its prior (odometry) value along them instead of
   sliding (Zhang, Kaess & Singh, "On degeneracy of optimization-based state estimation
   problems", ICRA 2016: solution remapping).
6. **Stop** when the step is below ``stop_translation_m`` / ``stop_rotation_rad``; the
   result counts as converged when the last step met the seed's criteria.

The rotation column of the Jacobian is scaled by the points' RMS lever arm ``L`` so the
Hessian has one unit (m⁻²) and its eigenvalues can be compared.

**Range-proportional noise.** A lidar like the A1M8 measures the bearing precisely and
the range with a noise proportional to the range (about 1 %). Projected on the wall's
normal, a point's noise is ``ρ·|nᵀb|`` with ``b`` the beam (lidar to point; ``|nᵀb| =
range·|cos|`` of the incidence angle), and the target point ``q`` carries its own, from
the lidar position it was seen from. So ``σ_i² = ρ²((nᵀb_i)² + (nᵀ(q_i − v_i))²) +
σ_floor²`` (``σ_floor``: what does not scale with range: quantization, the submap's own
pose errors). In a corridor the only points that fix the position along it are on a
far wall ahead; with all points weighted alike their noise, ten times that of the side
walls, sets the along-track error. Weighting by ``1/σ_i²`` is the maximum-likelihood
estimate (the weighted point-to-line metric of Censi, ICRA 2008, with a per-point
covariance; Segal, Haehnel & Thrun, "Generalized-ICP", RSS 2009, for the general
form). Observability (step 5) is still judged on the kernel-weighted Hessian without
the ``1/σ_i²`` factor: a far wall is a weak measurement, not a missing one. The
information matrix is then ``JᵀWJ / s²`` with ``W`` the same weights and ``s²`` the
weighted variance of the normalized residuals (1 when the noise model is right), at
least ``min_variance_factor``. ``ρ = 0`` is the unweighted estimate (every point alike).

Target normals come from a PCA of each target point's ``normal_neighbours`` nearest
neighbours (Hoppe et al., SIGGRAPH 1992); points whose neighbourhood is not a line
(corners, isolated returns) are dropped from the target.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Iterable
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from mazebot.geometry import transform_points
from mazebot.slam_config import IcpParams as IcpParams  # the [slam.icp] section is ICP's parameters
from mazebot.steps import all_at_once

#: ICP iterations between two stages of :func:`match_scan_steps` (about a millisecond here, four on a Pi 4).
ITERATIONS_PER_STAGE = 4


@dataclass(frozen=True)
class IcpResult:
    """Outcome of :func:`match_scan`.

    ``pose`` (3,) is the source frame's pose in the target frame. ``fitness`` is the
    share of source points with an accepted correspondence, ``rmse_m`` their unweighted
    point-to-line RMS (in metres, whatever the weighting). ``information`` (3×3, for the
    pose graph) is ``JᵀWJ / σ²`` with ``σ²`` the weighted residual variance (with range
    noise weighting: ``W`` includes ``1/σ_i²`` and ``σ²`` is the normalized residuals'
    variance factor), with unobservable directions removed (there
    the pose is the prior, so the scan adds no information). ``degenerate`` says some
    direction was unobservable; ``weak_direction`` (3,) is the weakest one as a unit
    pose step ``(dx, dy, dθ)``, or None. ``graph_information`` is the information the
    pose graph's edges take when it differs from the filter's (ICP's clustered by wall
    for the graph only, ``information_cluster_filter`` false), else None:
    :attr:`edge_information` is the one to put on an edge.
    """

    pose: np.ndarray
    converged: bool
    iterations: int
    fitness: float
    rmse_m: float
    information: np.ndarray
    degenerate: bool
    weak_direction: np.ndarray | None
    correspondences: int
    graph_information: np.ndarray | None = None

    @property
    def edge_information(self) -> np.ndarray:
        """The information of a pose-graph edge made from this match (a sequential edge or a loop closure)."""
        return self.information if self.graph_information is None else self.graph_information


class Target:
    """A submap prepared for matching: kd-tree and surface normals, built once.

    ``points_xy`` (M, 2) in the target (world) frame. ``viewpoints_xy`` (2,) or (M, 2)
    are the lidar positions the points were seen from; with them the normals point
    towards free space and ICP only matches surfaces that face the scanning lidar.
    ``normals`` (M, 2) may be given instead of estimated (e.g. from a known world).
    Estimated normals use the ``normal_neighbours`` nearest points within
    ``normal_radius_m``; points whose neighbourhood spreads more than ``max_line_spread``
    (eigenvalue ratio) across the line are dropped (see :func:`estimate_normals`).

    Example::

        target = Target(submap_points, viewpoints)
        result = match_scan(target, scan.points_match, initial_pose=odometry_guess)
    """

    def __init__(
        self,
        points_xy: np.ndarray,
        viewpoints_xy: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        normal_neighbours: int = 10,
        normal_radius_m: float = 0.1,
        max_line_spread: float = 0.2,
    ) -> None:
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        view = (
            None if viewpoints_xy is None else np.broadcast_to(np.asarray(viewpoints_xy, dtype=np.float64), pts.shape)
        )
        if normals is None:
            normals, good = estimate_normals(pts, normal_neighbours, normal_radius_m, max_line_spread, view)
        else:
            normals = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
            if normals.shape != pts.shape:
                raise ValueError(f"normals must have the shape of points {pts.shape}, got {normals.shape}")
            good = np.ones(pts.shape[0], dtype=bool)
        self.oriented = viewpoints_xy is not None
        if view is not None:
            flip = np.einsum("ij,ij->i", normals, view - pts) < 0
            normals = np.where(flip[:, None], -normals, normals)
        self.points = pts[good]
        self.normals = normals[good]
        # |nᵀ(v − q)|: the range from the viewpoint projected on the normal, what the point's
        # own range noise moves it by along the normal (0 without viewpoints: exact points)
        self.normal_range_m = (
            np.zeros(self.points.shape[0])
            if view is None
            else np.abs(np.einsum("ij,ij->i", self.normals, view[good] - self.points))
        )
        # one extra row: cKDTree reports a missing neighbour as index M
        self._normals_pad = np.vstack((self.normals, np.zeros((1, 2))))
        self.tree = cKDTree(self.points)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @classmethod
    def from_scans(
        cls,
        scans: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
        voxel_size_m: float = 0.02,
        normal_neighbours: int = 10,
        normal_radius_m: float = 0.1,
        max_line_spread: float = 0.2,
    ) -> Target:
        """A target from several scans ``(pose (3,), points_robot (N, 2), sensor_robot (2,))``.

        The points are moved into the world frame, viewpoints kept, and the union thinned
        to one point per ``voxel_size_m`` square (the first, so no point is invented).
        ``sensor_robot`` is the lidar centre in the robot frame (``PreparedScan.sensor_xy``).
        """
        all_pts, all_view = [], []
        for pose, pts, sensor in scans:
            pose = np.asarray(pose, dtype=np.float64)
            world = transform_points(pose, np.asarray(pts, dtype=np.float64))
            view = transform_points(pose, np.asarray(sensor, dtype=np.float64).reshape(1, 2))
            all_pts.append(world)
            all_view.append(np.broadcast_to(view, world.shape))
        if not all_pts:
            raise ValueError("a target needs at least one scan")
        pts = np.concatenate(all_pts)
        view = np.concatenate(all_view)
        cells = np.floor(pts / voxel_size_m).astype(np.int64)
        _, first = np.unique((cells[:, 0] << 32) ^ (cells[:, 1] & 0xFFFFFFFF), return_index=True)
        first.sort()
        return cls(pts[first], view[first], None, normal_neighbours, normal_radius_m, max_line_spread)


def estimate_normals(
    points_xy: np.ndarray,
    neighbours: int,
    radius_m: float,
    max_line_spread: float,
    viewpoints_xy: np.ndarray | None = None,
    queries: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (M, 2) by PCA of each point's neighbourhood, and a mask of usable ones.

    The 2×2 covariance of the neighbours within ``radius_m`` has the closed-form
    principal angle ``φ = ½ atan2(2 c_xy, c_xx − c_yy)``; the normal is perpendicular.
    A normal is usable with at least 3 neighbours and ``λ_min / λ_max <= max_line_spread``.
    With ``viewpoints_xy`` (M, 2) only neighbours seen from the same side count, so the
    two faces of a 12 mm wall, seen from opposite sides, do not blur into one thick line.
    ``queries`` (indices): only those points' normals are estimated (M is their count), their
    neighbours still taken among all the points.
    """
    n = points_xy.shape[0]
    m = n if queries is None else int(queries.shape[0])
    if m == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    k = min(neighbours, n)
    asked = points_xy if queries is None else points_xy[queries]
    dist, idx = cKDTree(points_xy).query(asked, k=k, distance_upper_bound=radius_m)
    dist, idx = dist.reshape(m, k), idx.reshape(m, k)
    ok = np.isfinite(dist)
    if viewpoints_xy is not None:
        look_all = viewpoints_xy - points_xy
        look = look_all if queries is None else look_all[queries]
        look_pad = np.vstack((look_all, np.zeros((1, 2))))
        ok &= np.einsum("md,mkd->mk", look, look_pad[idx]) > 0
    count = ok.sum(axis=1)
    pad = np.vstack((points_xy, np.zeros((1, 2))))
    nb = pad[idx]  # (M, k, 2), missing neighbours at (0, 0) and masked below
    w = ok.astype(np.float64)
    mean = np.einsum("mk,mkd->md", w, nb) / np.maximum(count, 1)[:, None]
    d = (nb - mean[:, None, :]) * w[:, :, None]
    cxx = np.einsum("mk,mk->m", d[..., 0], d[..., 0])
    cyy = np.einsum("mk,mk->m", d[..., 1], d[..., 1])
    cxy = np.einsum("mk,mk->m", d[..., 0], d[..., 1])
    phi = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    normals = np.column_stack((-np.sin(phi), np.cos(phi)))
    half_tr = 0.5 * (cxx + cyy)
    root = np.sqrt((0.5 * (cxx - cyy)) ** 2 + cxy**2)
    lam_max, lam_min = half_tr + root, half_tr - root
    good = (count >= 3) & (lam_min <= max_line_spread * np.maximum(lam_max, 1e-18))
    return normals, good


def match_scan_steps(
    target: Target,
    source_xy: np.ndarray,
    initial_pose: np.ndarray,
    params: IcpParams | None = None,
    sensor_xy: np.ndarray | None = None,
    prior_pose: np.ndarray | None = None,
) -> Generator[None, None, IcpResult]:
    """:func:`match_scan` in stages (:mod:`mazebot.steps`): it yields every ``ITERATIONS_PER_STAGE`` iterations.

    Most scans converge in a few iterations; a poor start can take up to
    ``max_iterations`` (150), tens of milliseconds on the event loop in one piece. The
    numbered steps are those of the module docstring.
    """
    p = params or IcpParams()
    src = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    pose = np.array(initial_pose, dtype=np.float64).reshape(3)
    prior = pose.copy() if prior_pose is None else np.array(prior_pose, dtype=np.float64).reshape(3)
    sensor = np.zeros(2) if sensor_xy is None else np.asarray(sensor_xy, dtype=np.float64).reshape(2)
    gate_m = p.max_correspondence_m
    k = max(1, p.candidates if target.oriented else 1)
    converged = False
    last: _Iteration | None = None
    iterations = 0
    if len(target) == 0 or src.shape[0] == 0:
        return _give_up(prior, 0)

    for iterations in range(1, p.max_iterations + 1):
        if iterations % ITERATIONS_PER_STAGE == 0:
            yield
        # 1. transform the source by the current estimate
        c, sn = math.cos(pose[2]), math.sin(pose[2])
        rot = np.array([[c, -sn], [sn, c]])
        rp = src @ rot.T  # R p: the lever arms about the robot's position
        moved = rp + pose[:2]

        # 2. associate with the nearest target point whose surface faces the lidar
        rows, j, d = _associate(target, moved, rot @ sensor + pose[:2], gate_m, k)
        m = rows.size
        if m < p.min_correspondences:
            return _give_up(prior, iterations, m / src.shape[0])

        # 3. outlier gate for the next iteration: mean + 3 std of the accepted distances
        mean_d = float(d.sum()) / m
        std_d = math.sqrt(max(0.0, float(d @ d) / m - mean_d * mean_d))
        gate_m = min(gate_m, max(p.min_correspondence_m, mean_d + 3.0 * std_d))

        # 4. point-to-line residuals r = nᵀ(R p + t − q) to the matched target points q, Cauchy weights
        n = target.normals[j]
        r = np.einsum("ij,ij->i", n, moved[rows] - target.points[j])
        e, w, var = _robust_weights(p, r, n, (src[rows] - sensor) @ rot.T, target.normal_range_m[j])

        # 5. linearized least squares, unobservable directions kept at the prior
        last = _solve_step(p, rp[rows], n, r, e, w, var)
        if p.information_cluster_rad > 0.0:
            last = replace(last, wall=_wall_clusters(n, target.points[j], p))
        step = last.step_from(pose, prior)
        pose += step

        # 6. convergence: the seed's criteria, then finer steps until they stop mattering
        step_t, step_r = math.hypot(step[0], step[1]), abs(float(step[2]))
        converged = step_t < p.converged_translation_m and step_r < p.converged_rotation_rad
        if step_t < p.stop_translation_m and step_r < p.stop_rotation_rad:
            break

    assert last is not None  # at least one iteration ran: max_iterations >= 1
    pose[2] = math.remainder(pose[2], math.tau)
    return last.result(p, pose, converged, iterations, src.shape[0])


@dataclass(frozen=True)
class _Iteration:
    """One linearized solve (step 5) and what the result is made of when it is the last.

    ``residual_m`` are the point-to-line residuals ``r``, ``normalized`` the residuals the
    kernel acted on (``r / σ`` when weighted, else ``r``), ``weights`` the Cauchy weights;
    ``strong`` marks the observable eigen-directions of the lever-arm-scaled Hessian
    (``eigval``, ``eigvec``), ``lever_m`` the scale of its rotation column, ``hess_obs`` the
    information of the observable directions in that scaling (None until :meth:`result`
    makes it, unweighted), ``step_scaled`` the solved step in the same scaling.
    """

    residual_m: np.ndarray
    normalized: np.ndarray
    weights: np.ndarray
    weighted: bool
    strong: np.ndarray
    eigval: np.ndarray
    eigvec: np.ndarray
    lever_m: float
    hess_obs: np.ndarray | None
    step_scaled: np.ndarray
    jac: np.ndarray  # (m, 3) the residuals' Jacobian, rotation column scaled by ``lever_m``
    system: np.ndarray  # (3, 3) the matrix the step solved with (weighted by the noise when ``weighted``)
    score_weight: np.ndarray  # (m,) each residual's factor in the gradient: w r (or w r / σ² when weighted)
    wall: np.ndarray | None = None  # (m,) which wall (line of the submap) each residual lies on, for clustering

    def step_from(self, pose: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """The step in (x, y, θ): the solved one, with its weak directions taking the pose back to ``prior``."""
        unit = np.array([1.0, 1.0, self.lever_m])
        offset = pose - prior
        offset[2] = math.remainder(offset[2], math.tau)
        weak = self.eigvec[:, ~self.strong]
        step_s = self.step_scaled - weak @ (weak.T @ (offset * unit))
        return step_s / unit

    def result(self, p: IcpParams, pose: np.ndarray, converged: bool, iterations: int, sources: int) -> IcpResult:
        """The match's result, its information matrix from this (the last) iteration."""
        w, r, e = self.weights, self.residual_m, self.normalized
        if self.weighted:
            # the normalized residuals' variance factor: 1 when the noise model is right
            sigma2 = max(p.min_variance_factor, float(np.sum(w * e**2) / np.sum(w)))
            hess_obs = self.hess_obs
            assert hess_obs is not None  # the weighted solve makes it
        else:
            sigma2 = max(p.sigma_min_m**2, float(np.sum(w * r**2) / np.sum(w)))
            # information of the observable directions only, back in (x, y, θ) units
            kept = self.eigvec[:, self.strong]
            hess_obs = (kept * self.eigval[self.strong]) @ kept.T
        unscale = np.array([1.0, 1.0, self.lever_m])
        information = hess_obs * np.outer(unscale, unscale) / sigma2
        graph_information = None
        if self.wall is not None:
            clustered = self._clustered(hess_obs, sigma2) * np.outer(unscale, unscale)
            # the filter keeps the Hessian's unless it is to take the clustered one too: a less sure
            # match makes the filter's prediction less sure and its correlative window wider
            information, graph_information = (
                (clustered, None) if p.information_cluster_filter else (information, clustered)
            )
        weak_direction = None
        if not self.strong.all():
            v = self.eigvec[:, int(np.argmin(self.eigval))] / unscale
            weak_direction = v / np.linalg.norm(v)
        return IcpResult(
            pose=pose,
            converged=converged,
            iterations=iterations,
            fitness=r.size / sources,
            rmse_m=float(np.sqrt(np.mean(r**2))),
            information=information,
            degenerate=not bool(self.strong.all()),
            weak_direction=weak_direction,
            correspondences=int(r.size),
            graph_information=graph_information,
        )


    def _clustered(self, hess_obs: np.ndarray, sigma2: float) -> np.ndarray:
        """The information (scaled units) of residuals that err together by wall: a cluster-robust covariance.

        ICP's Hessian ``H/σ²`` takes every point's residual as independent; a wall that the
        submap holds a centimetre off moves all its points together, and a scan of 150
        points then claims the certainty of 150 independent ones (on triangles of the Intel
        log's scans, which need no reference, the loops' chi² median is 7.5 where a
        calibrated information gives 2.37). The sandwich estimator with clusters (Liang &
        Zeger, Biometrika 1986; White, Econometrica 1980 for the independent case) takes the
        spread of each cluster's share of the gradient instead:
        ``Cov = H⁻¹ (C/(C−1) Σ_c g_c g_cᵀ) H⁻¹``, with ``g_c`` the gradient summed over the
        points of cluster ``c`` (the residuals on one wall of the submap:
        :func:`_wall_clusters`) and ``H`` the matrix the step solved with. Its shape is the
        match's own: a corridor's walls say little along it, a doorway's few walls little
        where they are few. The result is the inverse of that covariance plus the Hessian's
        ``σ² H⁻¹`` (for independent residuals the clustered part is about the Hessian's, so
        the information is about half of it, the share the filter took of ICP's by hand),
        in the observable directions only.
        """
        kept = self.eigvec[:, self.strong]
        if kept.shape[1] == 0:
            return hess_obs
        assert self.wall is not None
        _, cluster = np.unique(self.wall, return_inverse=True)
        count = int(cluster.max()) + 1 if cluster.size else 0
        if count < 2:
            return hess_obs
        scores = self.jac * self.score_weight[:, None]
        g = np.stack([np.bincount(cluster, weights=scores[:, k], minlength=count) for k in range(3)], axis=1)
        meat = (count / (count - 1)) * (g.T @ g)
        h_r = kept.T @ self.system @ kept
        h_inv = np.linalg.inv(h_r)
        cov_r = h_inv @ (kept.T @ meat @ kept) @ h_inv + sigma2 * np.linalg.inv(kept.T @ hess_obs @ kept)
        info_r = np.linalg.inv(0.5 * (cov_r + cov_r.T))
        return kept @ info_r @ kept.T


def _wall_clusters(normals: np.ndarray, target_xy: np.ndarray, p: IcpParams) -> np.ndarray:
    """A label per correspondence: the wall of the submap it lies on (its line's direction and offset, binned).

    Two matched target points lie on one wall when their normals point the same way
    (within ``information_cluster_rad``) and their lines' distances from the origin
    (``nᵀq``) agree within ``information_cluster_m``. Such residuals share the error of
    that wall's place in the submap (the pose of the keyframe that saw it).
    """
    angle = np.floor((np.arctan2(normals[:, 1], normals[:, 0]) + math.pi) / p.information_cluster_rad)
    offset = np.floor(np.einsum("ij,ij->i", normals, target_xy) / p.information_cluster_m)
    return (angle.astype(np.int64) << 32) + offset.astype(np.int64)


def _robust_weights(
    p: IcpParams, r: np.ndarray, n: np.ndarray, beam: np.ndarray, target_normal_range_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Step 4's Cauchy weights: ``(normalized residuals, weights, expected variance or None)``.

    With ``range_noise_ratio`` > 0 each residual is divided by its expected noise (both
    points' range noise along the normal, ``beam`` being lidar to point, and a floor) and
    the kernel acts on that; else on the residuals in metres. The kernel's scale is the
    median absolute deviation (× 1.4826), at least the configured minimum.
    """
    m = r.size
    if p.range_noise_ratio > 0.0:
        var = (p.range_noise_ratio**2) * (
            np.einsum("ij,ij->i", n, beam) ** 2 + target_normal_range_m**2
        ) + p.noise_floor_m**2
        e = r / np.sqrt(var)
        scale = max(p.robust_scale_min_sigma, 1.4826 * float(np.partition(np.abs(e), m // 2)[m // 2]))
        return e, 1.0 / (1.0 + (e / scale) ** 2), var
    scale = max(p.robust_scale_min_m, 1.4826 * float(np.partition(np.abs(r), m // 2)[m // 2]))  # MAD
    return r, 1.0 / (1.0 + (r / scale) ** 2), None


def _solve_step(
    p: IcpParams, arm: np.ndarray, n: np.ndarray, r: np.ndarray, e: np.ndarray, w: np.ndarray,
    var: np.ndarray | None,
) -> _Iteration:
    """Step 5: the linearized least squares, the rotation column scaled by the RMS lever arm to metres.

    Weighted (``var`` given): observability from the kernel-weighted geometry, the step
    from the noise-weighted system (module docstring).
    """
    m = r.size
    lever_m = max(0.1, math.sqrt(float(np.einsum("ij,ij->", arm, arm)) / m))
    jac = np.empty((m, 3))
    jac[:, :2] = n
    jac[:, 2] = (arm[:, 0] * n[:, 1] - arm[:, 1] * n[:, 0]) / lever_m
    jw = jac * w[:, None]
    hess = jw.T @ jac
    hess_obs: np.ndarray | None
    if var is not None:
        jwn = jw / var[:, None]
        system = jwn.T @ jac
        step_s, strong, eigval, eigvec, hess_obs = _solve_weighted(system, jwn.T @ r, hess, p.degeneracy_ratio)
        score_weight = w * r / var
    else:
        system = hess
        step_s, strong, eigval, eigvec = _solve_observable(hess, jw.T @ r, p.degeneracy_ratio)
        hess_obs = None
        score_weight = w * r
    return _Iteration(
        r, e, w, var is not None, strong, eigval, eigvec, lever_m, hess_obs, step_s, jac, system, score_weight
    )


match_scan = all_at_once(
    match_scan_steps,
    """Align ``source_xy`` (N, 2, robot frame) to ``target``, starting at ``initial_pose``.

    ``sensor_xy`` (2,) is the lidar centre in the robot frame (for the facing test);
    ``prior_pose`` (default ``initial_pose``) is what unobservable directions keep.
    """,
)


def _associate(
    target: Target, moved: np.ndarray, lidar_xy: np.ndarray, gate_m: float, candidates: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correspondences of the transformed source points ``moved`` (N, 2): (rows, target index, distance).

    The nearest target point within ``gate_m``; on an oriented target, where that point's
    surface faces away from the lidar (the far face of a thin wall), the nearest of
    ``candidates`` neighbours that faces it, or none.
    """
    dist, j = target.tree.query(moved, k=1)  # gating afterwards is faster than distance_upper_bound
    ok = dist <= gate_m
    if target.oriented:
        toward = lidar_xy - moved
        away = ok & (np.einsum("ij,ij->i", target._normals_pad[j], toward) <= 0)
        if candidates > 1 and away.any():
            again = np.flatnonzero(away)
            d2, j2 = target.tree.query(moved[again], k=min(candidates, len(target)), distance_upper_bound=gate_m)
            d2, j2 = d2.reshape(again.size, -1), j2.reshape(again.size, -1)
            facing = (d2 <= gate_m) & (np.einsum("nkd,nd->nk", target._normals_pad[j2], toward[again]) > 0)
            pick = np.argmax(facing, axis=1)
            pos = np.arange(again.size)
            found = facing[pos, pick]
            dist[again] = d2[pos, pick]
            j[again] = j2[pos, pick]
            away[again[found]] = False
        ok &= ~away
    rows = np.flatnonzero(ok)
    return rows, j[rows], dist[rows]


def _solve_observable(
    hess: np.ndarray, grad: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton step ``−H⁻¹g`` restricted to the well-constrained eigen-directions of ``H``.

    Returns the step, the mask of strong directions, eigenvalues and eigenvectors.
    """
    eigval, eigvec = np.linalg.eigh(hess)
    strong = eigval > ratio * max(float(eigval[-1]), 1e-12)
    proj = eigvec.T @ grad
    coef = np.where(strong, -proj / np.where(strong, eigval, 1.0), 0.0)
    return eigvec @ coef, strong, eigval, eigvec


def _solve_weighted(
    hess: np.ndarray, grad: np.ndarray, hess_geometry: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton step of the noise-weighted system ``(hess, grad)`` within the observable directions.

    Which directions are observable is read from ``hess_geometry`` (the same Jacobian with
    the kernel's weights only), as in :func:`_solve_observable`: weighting far points down
    must not turn a weak direction into a missing one. The step solves the weighted system
    restricted to the span of the strong eigenvectors ``V``: ``δ = −V (VᵀHV)⁻¹ Vᵀg``.
    Returns the step, the strong mask, the geometry's eigenvalues and eigenvectors, and
    ``V VᵀHV Vᵀ`` (the weighted Hessian of the observable directions, for the information).
    """
    eigval, eigvec = np.linalg.eigh(hess_geometry)
    strong = eigval > ratio * max(float(eigval[-1]), 1e-12)
    kept = eigvec[:, strong]
    if not strong.any():
        return np.zeros(3), strong, eigval, eigvec, np.zeros((3, 3))
    reduced = kept.T @ hess @ kept
    step = -kept @ np.linalg.solve(reduced, kept.T @ grad)
    return step, strong, eigval, eigvec, kept @ reduced @ kept.T


def _give_up(prior: np.ndarray, iterations: int, fitness: float = 0.0) -> IcpResult:
    """Too little overlap to say anything: the prior, no information."""
    return IcpResult(
        pose=prior.copy(),
        converged=False,
        iterations=iterations,
        fitness=float(fitness),
        rmse_m=float("nan"),
        information=np.zeros((3, 3)),
        degenerate=True,
        weak_direction=None,
        correspondences=0,
    )
