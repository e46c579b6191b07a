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
priors keep their full weight by default: they are not the edges that can be wrong by a metre).

A sequential edge can be wrong too: ICP that stops near a prediction a decimetre off along
a corridor claims millimetres all the same (Olson & Agarwal, "Inference on networks of
mixtures for robust robot mapping", RSS 2012, treat such odometry failures as a mixture
component of the chain's edges). Where the loops make the chain redundant, an edge that
contradicts them by many σ is as likely wrong as a closure that does, so
:func:`robust_edges` can make those edges robust too, with a Φ of their own
(``[slam.loop] dcs_sequential_phi``). Only an edge that an accepted closure spans lies on a
cycle: anywhere else (a corridor with no loop around it, the stretch after the last
closure) the edge is the only tie between its two poses, and scaling it down would let
the chain come apart.

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


#: an edge whose weight fell below this is counted as switched off (``s² < 0.1``: χ² beyond about 5.3 Φ)
DOWNWEIGHTED = 0.1


def dcs_weights(chi2: np.ndarray, phi: float | np.ndarray) -> np.ndarray:
    """The information scale ``s²`` of edges with squared Mahalanobis residuals ``chi2`` (Agarwal et al. 2013)."""
    chi2 = np.maximum(np.asarray(chi2, dtype=np.float64), 0.0)
    s = np.minimum(1.0, 2.0 * phi / (phi + chi2))
    return s * s


def spanned_by_closures(edge_i: np.ndarray, edge_j: np.ndarray, closure: np.ndarray, count: int) -> np.ndarray:
    """(count - 1,) how many of the ``closure`` edges span each sequential edge ``k → k + 1`` of ``count`` poses.

    A closure ``a → b`` (``a < b``) and the chain between its ends make a cycle through every
    sequential edge from ``a`` to ``b``; an edge with a count of 0 lies on no cycle. Edges to
    vertices beyond ``count`` (the wall grid's) are not closures of the chain and are ignored.
    """
    ci = np.asarray(edge_i, dtype=np.intp)[closure]
    cj = np.asarray(edge_j, dtype=np.intp)[closure]
    inside = (ci < count) & (cj < count)
    lo, hi = np.minimum(ci, cj)[inside], np.maximum(ci, cj)[inside]
    steps = np.zeros(max(count, 1), dtype=np.int64)
    np.add.at(steps, lo, 1)
    np.add.at(steps, hi, -1)
    return np.cumsum(steps)[: max(count - 1, 0)]


def robust_edges(
    edge_i: np.ndarray, edge_j: np.ndarray, count: int, closure_phi: float, sequential_phi: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which edges :func:`optimize_dcs` makes robust, each one's Φ, and which of them are sequential.

    The loop closures (edges between keyframes more than one apart, among the first ``count``
    vertices) with ``closure_phi``; with ``sequential_phi`` > 0 also the sequential edges
    ``k → k + 1`` that a closure spans (:func:`spanned_by_closures`), with ``sequential_phi``.
    Returns ``(robust, phi, sequential)``: a mask over the edges, Φ per robust edge (in the
    edges' order) and a mask over the robust edges telling the sequential ones.
    """
    ei, ej = np.asarray(edge_i, dtype=np.intp), np.asarray(edge_j, dtype=np.intp)
    inside = (ei < count) & (ej < count)
    closure = (ej - ei > 1) & inside  # the chain's edges join k - 1 and k
    sequential = np.zeros_like(closure)
    if sequential_phi > 0 and count > 1:
        chain = (ej - ei == 1) & inside
        spanned = spanned_by_closures(ei, ej, closure, count)
        sequential = chain & (spanned[np.clip(ei, 0, count - 2)] > 0)
    robust = closure | sequential
    phi = np.where(sequential[robust], sequential_phi, closure_phi)
    return robust, phi, sequential[robust]


def optimize_dcs(
    vertices: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    closure: np.ndarray,
    phi: float | np.ndarray,
    max_rounds: int = 4,
    max_iterations: int = 30,
    settled: float = 0.02,
) -> RobustResult:
    """Optimize the graph ``vertices`` + ``edges`` (``(i, j, z, Ω)``) with the edges where ``closure`` is True robust.

    ``phi`` (χ² units) is DCS's Φ, one for all or one per robust edge (:func:`robust_edges`); an edge
    whose Φ is <= 0 keeps its full weight; every Φ <= 0 or no robust edges: one plain optimization.
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
        if np.all(np.asarray(phi) <= 0) or not closure.any() or rounds >= max_rounds:
            break
        e = edge_residuals(x, ei[closure], ej[closure], z[closure])
        chi2 = np.einsum("mi,mij,mj->m", e, omega[closure], e)
        new = dcs_weights(chi2, phi) if np.ndim(phi) == 0 else _weights_per_edge(chi2, np.asarray(phi))
        change = float(np.max(np.abs(new - weights)))
        weights = new
        if change <= settled:
            break
    return RobustResult(x, optimization, weights, rounds)


def _weights_per_edge(chi2: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """:func:`dcs_weights` with a Φ per edge; an edge whose Φ is <= 0 keeps its full weight."""
    weights = np.ones(chi2.shape)
    on = phi > 0
    weights[on] = dcs_weights(chi2[on], phi[on])
    return weights
