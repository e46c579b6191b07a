"""A scan match's uncertainty from the correlative likelihood surface about it (Olson, ICRA 2009).

ICP's information is its Hessian at the solution (:mod:`mazebot.slam.icp`): how sharp the fit
is at its minimum, not whether the minimum is the right one or how wide the plausible set is.
Olson ("Real-Time Correlative Scan Matching", ICRA 2009, section IV, "Computing the
covariance") evaluates the scan's likelihood over a grid of poses ``T_i`` about the match on
the smoothed lookup table and takes the moments of that distribution::

    s = Σ p(T_i),   u = Σ T_i p(T_i),   K = Σ T_i T_iᵀ p(T_i)
    mean = u / s,   Σ = K / s − u uᵀ / s²

wide where the data are ambiguous (a corridor along its length, two alignments side by side),
tight where they are not. The likelihood of a pose is the product over the scan's points of
the table's value under each (:class:`mazebot.slam.correlative.LikelihoodTable`: the Gaussian
of the distance to the nearest reference point), floored at the table's value at 3σ, as
Olson's rasterised cost is: a point farther than that from every surface is an outlier, not
evidence against the pose. ``point_share`` counts each point as that share of an independent
observation (1: Olson's product over independent points; smaller: the points' errors shared by
wall, as ICP's own information is known to be too sure on the laser logs).

The grid is ``±half_cells`` table cells in ``x`` and ``y`` and ``±half_headings`` of Olson's
heading step (the far points move about a cell per step), all about the match (vectorized:
one gather of ``poses × points``). A distribution that sits in one grid cell says nothing finer
than the grid: the covariance is then about zero and the cap below leaves ICP's information as
it is. Where the distribution's mode is not the match itself, the match sits on a shoulder of
the surface (``SurfaceCovariance.mode_off``).

**The cap** (:func:`capped_information`): the match's information becomes that of the sum of
the two covariances, ``(Ω⁻¹ + Σ_s)⁻¹``, written ``Ω − Ω (Ω + Σ_s⁻¹)⁻¹ Ω`` (Woodbury) so that a
singular ``Ω`` (a corridor's unobserved direction) stays defined: never more than either says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mazebot.slam.correlative import LikelihoodTable, heading_step_rad

#: a table value below the table's own at 3σ is an outlier's (Olson's floored cost)
OUTLIER_SIGMAS = 3.0


@dataclass(frozen=True)
class SurfaceCovariance:
    """Olson's moments of the likelihood over the grid about a match, in the table's frame.

    ``mean`` (3,) and ``covariance`` (3×3, m², m·rad, rad²) of the distribution; ``mode`` (3,)
    the grid's most likely pose and ``mode_off`` whether it is not the match's own;
    ``evaluations`` the table lookups made (poses × points).
    """

    mean: np.ndarray
    covariance: np.ndarray
    mode: np.ndarray
    mode_off: bool
    evaluations: int


def surface_covariance(
    table: LikelihoodTable,
    source_xy: np.ndarray,
    pose: np.ndarray,
    sigma_m: float,
    sensor_xy: np.ndarray | None = None,
    *,
    point_share: float = 1.0,
    half_cells: int = 3,
    half_headings: int = 3,
) -> SurfaceCovariance:
    """Olson's mean and covariance of ``source_xy`` (N, 2, robot frame) about ``pose`` (3,) on ``table``.

    ``sigma_m`` is the table's smoothing (its outlier floor is the value at 3σ). The grid's
    heading step is :func:`mazebot.slam.correlative.heading_step_rad` of the points.
    """
    src = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    centre = np.asarray(pose, dtype=np.float64).reshape(3)
    res_m = table.resolution_m
    step_rad = heading_step_rad(src, sensor_xy, res_m)
    shifts = np.arange(-half_cells, half_cells + 1, dtype=np.float64) * res_m
    turns = np.arange(-half_headings, half_headings + 1, dtype=np.float64) * step_rad
    if src.shape[0] == 0:
        return SurfaceCovariance(centre.copy(), np.zeros((3, 3)), centre.copy(), False, 0)
    log_p = _log_likelihoods(table, src, centre, shifts, turns, sigma_m) * point_share
    weights = np.exp(log_p - log_p.max())
    dx, dy, dth = np.meshgrid(shifts, shifts, turns, indexing="ij")
    offsets = np.stack([dx.ravel(), dy.ravel(), dth.ravel()], axis=1)
    w = weights.ravel()
    s = float(w.sum())
    u = offsets.T @ w
    k = (offsets * w[:, None]).T @ offsets
    cov = k / s - np.outer(u, u) / s**2
    # the mode: the match itself unless another pose of the grid is more likely (ties keep the match)
    middle = w.size // 2
    best = middle if w[middle] >= 1.0 - 1e-9 else int(np.argmax(w))
    return SurfaceCovariance(
        mean=centre + u / s,
        covariance=0.5 * (cov + cov.T),
        mode=centre + offsets[best],
        mode_off=best != middle,
        evaluations=int(w.size * src.shape[0]),
    )


def _log_likelihoods(
    table: LikelihoodTable,
    src: np.ndarray,
    centre: np.ndarray,
    shifts_m: np.ndarray,
    turns_rad: np.ndarray,
    sigma_m: float,
) -> np.ndarray:
    """Σ over points of log(table value, floored), at every (dx, dy, dθ) of the grid: shape (X, Y, Θ)."""
    floor = math.exp(-0.5 * OUTLIER_SIGMAS**2)
    theta = centre[2] + turns_rad
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    x = c * src[None, :, 0] - s * src[None, :, 1] + centre[0]  # (Θ, N)
    y = s * src[None, :, 0] + c * src[None, :, 1] + centre[1]
    gx = x[None, None, :, :] + shifts_m[:, None, None, None]  # (X, 1, Θ, N)
    gy = y[None, None, :, :] + shifts_m[None, :, None, None]  # (1, Y, Θ, N)
    gx, gy = np.broadcast_arrays(gx, gy)
    ix, iy = table._cells(gx, gy)
    values = np.maximum(table.tables[0][ix, iy], floor)
    return np.log(values).sum(axis=-1)


def capped_information(information: np.ndarray, covariance: np.ndarray, floor_m2: float = 1e-12) -> np.ndarray:
    """``(Ω⁻¹ + Σ)⁻¹`` for an information ``Ω`` that may be singular and a covariance ``Σ`` that may be zero.

    Woodbury: ``Ω − Ω (Ω + (Σ + εI)⁻¹)⁻¹ Ω``; ``floor_m2`` (ε) keeps ``Σ`` invertible, and a
    ``Σ`` of zero gives ``Ω`` back.
    """
    omega = np.asarray(information, dtype=np.float64)
    sigma = np.asarray(covariance, dtype=np.float64) + floor_m2 * np.eye(3)
    capped = omega - omega @ np.linalg.solve(omega + np.linalg.inv(sigma), omega)
    return 0.5 * (capped + capped.T)
