"""Dynamic covariance scaling of loop closures: a wrong closure that slipped through cannot bend the map.

Loop-closure verification (:mod:`mazebot.slam.loop_closure`) is strict, but on a
building's scans it can still accept a closure that fits locally and is wrong by a
door's spacing (two corridors alike, a doorway one metre over). Least squares gives
that one edge the same pull as the right ones, so the whole map bends towards it.

Dynamic covariance scaling (Agarwal, Tipaldi, Spinello, Stachniss & Burgard, "Robust
map optimization using dynamic covariance scaling", ICRA 2013) scales the information
of each loop-closure edge by ``s²`` with

    s = min(1, 2Φ / (Φ + χ²)),

``χ²`` the edge's squared Mahalanobis residual at the current estimate: an edge that
agrees with the rest of the graph (``χ² ≤ Φ``) keeps its full weight, one that
disagrees loses weight as ``(2Φ/χ²)²``. It is the closed-form optimum of switchable
constraints (Sünderhauf & Protzel, IROS 2012) with the switch's prior ``Φ``, so no
switch variables are added. Here it runs as iteratively reweighted least squares: the
graph is optimized, the closures' weights are set from their residuals, and it is
optimized again from there, until the weights settle (the sequential chain and the
priors keep their full weight: they are not the edges that can be wrong by a metre).

A map whose closures all agree is optimized once, as before: every weight is 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mazebot.slam.posegraph import OptimizeResult, PoseGraph, edge_residuals


@dataclass(frozen=True)
class RobustResult:
    """The optimized poses of the graph (all its vertices), the last optimization, and each closure's weight."""

    vertices: np.ndarray
    optimization: OptimizeResult
    weights: np.ndarray  # (C,) the s² of each loop-closure edge, in the order given (1: full weight)
    rounds: int  # optimizations run


def dcs_weights(chi2: np.ndarray, phi: float) -> np.ndarray:
    """The information scale ``s²`` of edges with squared Mahalanobis residuals ``chi2`` (Agarwal et al. 2013)."""
    chi2 = np.maximum(np.asarray(chi2, dtype=np.float64), 0.0)
    s = np.minimum(1.0, 2.0 * phi / (phi + chi2))
    return s * s


def optimize_dcs(
    vertices: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    closure: np.ndarray,
    phi: float,
    max_rounds: int = 4,
    max_iterations: int = 30,
    settled: float = 0.02,
) -> RobustResult:
    """Optimize the graph ``vertices`` + ``edges`` (``(i, j, z, Ω)``) with the edges where ``closure`` is True robust.

    ``phi`` (χ² units) is DCS's Φ; ``phi <= 0`` or no closure edges: one plain optimization.
    Rounds stop when no weight changed by more than ``settled`` or after ``max_rounds``.
    Vertex 0 is held fixed.
    """
    ei, ej, z, omega = (np.asarray(a) for a in edges)
    closure = np.asarray(closure, dtype=bool)
    weights = np.ones(int(closure.sum()))
    x = np.asarray(vertices, dtype=np.float64).copy()
    rounds = 0
    optimization = None
    while True:
        graph = PoseGraph()
        graph.add_vertices(x)
        scaled = omega.copy()
        scaled[closure] *= weights[:, None, None]
        if len(ei):
            graph.add_edges(ei, ej, z, scaled)
        optimization = graph.optimize(max_iterations=max_iterations, method="lm")
        rounds += 1
        x = graph.vertices.copy()
        if phi <= 0 or not closure.any() or rounds >= max_rounds:
            break
        e = edge_residuals(x, ei[closure], ej[closure], z[closure])
        chi2 = np.einsum("mi,mij,mj->m", e, omega[closure], e)
        new = dcs_weights(chi2, phi)
        change = float(np.max(np.abs(new - weights)))
        weights = new
        if change <= settled:
            break
    return RobustResult(x, optimization, weights, rounds)
