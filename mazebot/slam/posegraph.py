"""2D pose graph and its sparse least-squares optimizer (Gauss–Newton / Levenberg–Marquardt).

The method is that of Grisetti, Kümmerle, Stachniss & Burgard, "A Tutorial on
Graph-Based SLAM", IEEE Intelligent Transportation Systems Magazine 2(4), 2010; its
Algorithm 1 is reproduced in section III.B of the design seed (``000_…``), and the step
numbers below are that algorithm's. Every vertex is a pose ``x_i = (x, y, θ)`` (metres,
metres, radians) of the robot in the world frame; every edge ``<i, j>`` carries a
measured relative pose ``z_ij`` (``x_j`` seen from ``x_i``) and its 3x3 information
matrix ``Ω_ij`` (inverse covariance, in the order ``x, y, θ``).

Error of one edge, with poses as homogeneous matrices ``X = v2t(x)`` and ``t2v`` the
inverse map (the tutorial's pose-pose error)::

    e_ij = t2v(Z_ij⁻¹ (X_i⁻¹ X_j)),        angle wrapped to [-π, π)

and the cost is ``F(x) = Σ e_ijᵀ Ω_ij e_ij``, reported as ``chi2`` (no ½).

Each iteration linearizes ``e_ij`` around the current poses (Algorithm 1, step 2) with
Jacobians ``A_ij = ∂e_ij/∂Δx_i`` and ``B_ij = ∂e_ij/∂Δx_j``, accumulates
``H = Σ Jᵀ Ω J`` and ``b = Σ Jᵀ Ω e`` into the 3x3 blocks ii, ij, ji, jj and the
segments i, j (steps 3–4), keeps the anchored poses fixed (step 5), solves
``H Δx = -b`` with a sparse direct factorization (step 6) and applies the increment
(step 7).

The increment is applied on the manifold (the tutorial's ``x ⊞ Δx``, "least squares on
a manifold"): ``X_i ← X_i · v2t(Δx_i)``, i.e. ``Δx_i`` is a small motion in the robot
frame of pose ``i``. This is the local chart of GTSAM's ``Pose2::retract``, so iteration
counts compare with GTSAM's. With that chart the Jacobians are, writing
``p = R_iᵀ (t_j - t_i)`` for the translation of ``X_i⁻¹ X_j``, ``R_z`` for the rotation
of ``Z_ij``, ``θ_e`` for the angle of ``e_ij`` and ``S = [[0, -1], [1, 0]]``::

    A_ij = [[-R_zᵀ, -R_zᵀ S p],      B_ij = [[R(θ_e), 0],
            [  0,       -1   ]]              [  0,    1]]

(derivation: perturbing ``X_j`` by ``δ`` moves ``p`` by ``R(φ) δ_t`` with ``φ = θ_j - θ_i``,
and ``R_zᵀ R(φ) = R(θ_e)``; perturbing ``X_i`` moves ``p`` by ``-δ_t - δ_θ S p``).

Levenberg–Marquardt damps the normal equations to ``(H + λ I) Δx = -b``, accepts a step
only if it lowers ``chi2`` and updates ``λ`` with Nielsen's rule from the gain ratio
(Madsen, Nielsen & Tingleff, "Methods for Non-Linear Least Squares Problems", 2nd ed.
2004, section 3.2, Algorithm 3.16).

All per-edge work is vectorized over the edges with numpy. The sparsity pattern of
``H``, a fill-reducing ordering and the scatter map from 3x3 blocks into the CSC arrays
are computed once per ``optimize`` call, so an iteration is: residuals and Jacobians
(batched 3x3 products), one ``np.bincount`` scatter, one SuperLU factorization.

Example::

    graph = PoseGraph()
    a = graph.add_vertex((0.0, 0.0, 0.0))
    b = graph.add_vertex((1.1, 0.1, 0.0))
    graph.add_edge(a, b, (1.0, 0.0, 0.0), np.eye(3))
    result = graph.optimize()
    graph.vertices[b]        # ≈ (1.0, 0.0, 0.0)
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.sparse import csc_matrix, csgraph
from scipy.sparse.linalg import splu

from mazebot.errors import UsageError

__all__ = [
    "Edge",
    "OptimizeResult",
    "PoseGraph",
    "PoseGraphError",
    "compose",
    "edge_jacobians",
    "edge_residuals",
    "invalid_information",
    "inverse",
    "relative_pose",
    "wrap_angle",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

TWO_PI = 2.0 * np.pi


class PoseGraphError(UsageError):
    """The graph cannot be optimized as given (unanchored vertices, bad indices, singular system)."""


# --------------------------------------------------------------------------- SE(2) helpers


def wrap_angle(angle_rad: npt.ArrayLike) -> FloatArray:
    """Wrap angles to [-π, π) radians, element-wise.

    Residual angles must be wrapped, or a heading error of +179° vs -179° would look like
    358° instead of 2°.
    """
    return np.remainder(np.asarray(angle_rad, dtype=np.float64) + np.pi, TWO_PI) - np.pi


def compose(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Pose composition ``a ⊕ b`` on (..., 3) arrays of (x_m, y_m, theta_rad); broadcasts.

    ``b`` is expressed in the frame of ``a``; the result is in ``a``'s parent frame:
    ``v2t(a) · v2t(b)`` in homogeneous matrices.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cos_a = np.cos(a[..., 2])
    sin_a = np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = a[..., 0] + cos_a * b[..., 0] - sin_a * b[..., 1]
    out[..., 1] = a[..., 1] + sin_a * b[..., 0] + cos_a * b[..., 1]
    out[..., 2] = wrap_angle(a[..., 2] + b[..., 2])
    return out


def inverse(a: npt.ArrayLike) -> FloatArray:
    """Pose inverse ``a⁻¹`` on (..., 3) arrays, so that ``compose(a, inverse(a)) == 0``."""
    a = np.asarray(a, dtype=np.float64)
    cos_a = np.cos(a[..., 2])
    sin_a = np.sin(a[..., 2])
    out = np.empty_like(a)
    out[..., 0] = -cos_a * a[..., 0] - sin_a * a[..., 1]
    out[..., 1] = sin_a * a[..., 0] - cos_a * a[..., 1]
    out[..., 2] = wrap_angle(-a[..., 2])
    return out


def relative_pose(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Pose of ``b`` seen from ``a``: ``a⁻¹ ⊕ b`` on (..., 3) arrays; broadcasts.

    This is the measurement model of an edge: ``ẑ_ij = relative_pose(x_i, x_j)``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cos_a = np.cos(a[..., 2])
    sin_a = np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = cos_a * dx + sin_a * dy
    out[..., 1] = -sin_a * dx + cos_a * dy
    out[..., 2] = wrap_angle(b[..., 2] - a[..., 2])
    return out


def edge_residuals(vertices: FloatArray, edge_i: IntArray, edge_j: IntArray, measurements: FloatArray) -> FloatArray:
    """Residuals ``e_ij = t2v(Z_ij⁻¹ (X_i⁻¹ X_j))`` of all edges, shape (M, 3), angle wrapped."""
    return relative_pose(measurements, relative_pose(vertices[edge_i], vertices[edge_j]))


def edge_jacobians(
    vertices: FloatArray, edge_i: IntArray, edge_j: IntArray, measurements: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residuals and Jacobians of all edges at once: ``(e (M,3), A (M,3,3), B (M,3,3))``.

    ``A = ∂e/∂Δx_i`` and ``B = ∂e/∂Δx_j`` for the increment ``X ← X · v2t(Δx)`` (see the
    module docstring); this is Algorithm 1, step 2, for every edge in one pass.
    """
    xi = vertices[edge_i]
    xj = vertices[edge_j]
    cos_i = np.cos(xi[:, 2])
    sin_i = np.sin(xi[:, 2])
    dx = xj[:, 0] - xi[:, 0]
    dy = xj[:, 1] - xi[:, 1]
    # p = R_iᵀ (t_j - t_i): translation of X_i⁻¹ X_j
    px = cos_i * dx + sin_i * dy
    py = -sin_i * dx + cos_i * dy
    phi = xj[:, 2] - xi[:, 2]

    cos_z = np.cos(measurements[:, 2])
    sin_z = np.sin(measurements[:, 2])
    ux = px - measurements[:, 0]
    uy = py - measurements[:, 1]
    theta_e = wrap_angle(phi - measurements[:, 2])
    count = len(edge_i)
    e = np.empty((count, 3))
    e[:, 0] = cos_z * ux + sin_z * uy
    e[:, 1] = -sin_z * ux + cos_z * uy
    e[:, 2] = theta_e

    # A_ij = [[-R_zᵀ, -R_zᵀ S p], [0, 0, -1]] with S p = (-p_y, p_x)
    a = np.zeros((count, 3, 3))
    a[:, 0, 0] = -cos_z
    a[:, 0, 1] = -sin_z
    a[:, 1, 0] = sin_z
    a[:, 1, 1] = -cos_z
    a[:, 0, 2] = cos_z * py - sin_z * px
    a[:, 1, 2] = -sin_z * py - cos_z * px
    a[:, 2, 2] = -1.0
    # B_ij = [[R(θ_e), 0], [0, 1]]: R_zᵀ R(φ) = R(φ - θ_z)
    cos_e = np.cos(theta_e)
    sin_e = np.sin(theta_e)
    b = np.zeros((count, 3, 3))
    b[:, 0, 0] = cos_e
    b[:, 0, 1] = -sin_e
    b[:, 1, 0] = sin_e
    b[:, 1, 1] = cos_e
    b[:, 2, 2] = 1.0
    return e, a, b


def _chi2_terms(residuals: FloatArray, information: FloatArray) -> FloatArray:
    """Per-edge squared Mahalanobis norms ``e_ijᵀ Ω_ij e_ij``, shape (M,)."""
    return np.einsum("mi,mij,mj->m", residuals, information, residuals)


def invalid_information(information: FloatArray) -> npt.NDArray[np.bool_]:
    """Which of the (M, 3, 3) information matrices are unusable: not finite, not symmetric or
    with a negative eigenvalue (beyond round-off). A singular one is allowed: it constrains
    fewer directions, and the graph as a whole still has to determine every pose."""
    finite = np.all(np.isfinite(information), axis=(1, 2))
    safe = np.where(finite[:, None, None], information, 0.0)
    scale = np.maximum(np.max(np.abs(safe), axis=(1, 2)), 1e-300)
    symmetric = np.all(np.abs(safe - safe.transpose(0, 2, 1)) <= 1e-9 * scale[:, None, None], axis=(1, 2))
    eigen_min = np.linalg.eigvalsh(0.5 * (safe + safe.transpose(0, 2, 1)))[:, 0] if len(safe) else np.zeros(0)
    return ~(finite & symmetric & (eigen_min >= -1e-12 * scale))


# --------------------------------------------------------------------------- the graph


@dataclass(frozen=True)
class Edge:
    """One constraint: pose ``j`` measured from pose ``i`` (vertex indices, not g2o ids)."""

    i: int
    j: int
    measurement: FloatArray  # (3,): dx_m, dy_m, dtheta_rad in the frame of pose i
    information: FloatArray  # (3, 3): symmetric positive definite, units 1/m², 1/(m·rad), 1/rad²


@dataclass(frozen=True)
class OptimizeResult:
    """What one ``PoseGraph.optimize`` call did.

    ``iterations`` counts linearizations (outer iterations, as GTSAM and g2o count them);
    ``linear_solves`` also counts the extra factorizations of rejected LM steps.
    """

    iterations: int
    chi2_before: float
    chi2_after: float
    converged: bool
    seconds: float
    linear_solves: int = 0
    method: str = "lm"


class PoseGraph:
    """Poses (``vertices``, shape (N, 3)) joined by relative-pose constraints (``edges``).

    Vertices are addressed by their index in ``vertices``; ``vertex_ids`` keeps the
    external ids (g2o's) so a graph written back keeps its numbering. ``fixed`` holds the
    indices of vertices anchored in the input (g2o ``FIX``); when it is empty the first
    vertex is held fixed, which removes the gauge freedom of the problem (Algorithm 1,
    step 5).

    Example::

        graph = PoseGraph()
        for pose in [(0, 0, 0), (1, 0, 0), (1, 1, np.pi / 2)]:
            graph.add_vertex(pose)
        graph.add_edge(0, 1, (1, 0, 0), np.eye(3))
        graph.chi2()
    """

    def __init__(self) -> None:
        self._pose_buffer: FloatArray = np.zeros((16, 3))  # grows by doubling; rows [0, len) are live
        self.vertex_ids: list[int] = []
        self._index_of_id: dict[int, int] = {}
        self.fixed: set[int] = set()
        # edges arrive in chunks (one per add_edge/add_edges call); edge_arrays joins them lazily
        self._edge_chunks: list[tuple[IntArray, IntArray, FloatArray, FloatArray]] = []
        self._edge_count = 0

    # ------------------------------------------------------------------ building

    def add_vertex(self, pose: npt.ArrayLike, vertex_id: int | None = None) -> int:
        """Append a pose (x_m, y_m, theta_rad); returns its index.

        ``vertex_id`` is the external id (default: the index); it must be unique.
        """
        return int(self.add_vertices(np.reshape(np.asarray(pose, dtype=np.float64), (1, -1)), [vertex_id])[0])

    def add_vertices(self, poses: npt.ArrayLike, vertex_ids: Sequence[int | None] | None = None) -> IntArray:
        """Append K poses at once (shape (K, 3)); returns their indices.

        ``vertex_ids`` are the external ids (default: the indices); they must be unique.
        """
        pose_array = np.asarray(poses, dtype=np.float64)
        if pose_array.ndim != 2 or pose_array.shape[1] != 3 or not np.all(np.isfinite(pose_array)):
            raise PoseGraphError(f"vertex poses must be rows of 3 finite numbers (x_m, y_m, theta_rad), got {poses!r}")
        first = len(self.vertex_ids)
        indices = np.arange(first, first + len(pose_array), dtype=np.intp)
        ids = [None] * len(pose_array) if vertex_ids is None else list(vertex_ids)
        if len(ids) != len(pose_array):
            raise PoseGraphError(f"got {len(pose_array)} poses but {len(ids)} vertex ids")
        new_ids = [int(index) if vid is None else int(vid) for index, vid in zip(indices, ids, strict=True)]
        index_of_id = dict(zip(new_ids, indices.tolist(), strict=True))
        if len(index_of_id) != len(new_ids) or not self._index_of_id.keys().isdisjoint(index_of_id):
            seen: set[int] = set(self._index_of_id)
            for duplicate in new_ids:
                if duplicate in seen:
                    break
                seen.add(duplicate)
            raise PoseGraphError(f"vertex id {duplicate} is already in the graph; ids must be unique")
        needed = first + len(pose_array)
        if needed > len(self._pose_buffer):
            grown = np.zeros((max(needed, 2 * len(self._pose_buffer)), 3))
            grown[:first] = self._pose_buffer[:first]
            self._pose_buffer = grown
        self._pose_buffer[first:needed] = pose_array
        self.vertex_ids.extend(new_ids)
        self._index_of_id.update(index_of_id)
        return indices

    def add_edge(self, i: int, j: int, measurement: npt.ArrayLike, information: npt.ArrayLike | None = None) -> int:
        """Add the constraint "pose ``j`` is at ``measurement`` in the frame of pose ``i``".

        ``i`` and ``j`` are vertex indices; ``measurement`` is (dx_m, dy_m, dtheta_rad) in
        the frame of pose ``i``; ``information`` is its 3x3 inverse covariance (default
        identity), symmetric positive semi-definite. Returns the edge index.
        """
        omega = np.eye(3) if information is None else information
        first = self.add_edges([i], [j], np.reshape(np.asarray(measurement, dtype=np.float64), (1, -1)), [omega])
        return int(first)

    def add_edges(
        self,
        edge_i: npt.ArrayLike,
        edge_j: npt.ArrayLike,
        measurements: npt.ArrayLike,
        information: npt.ArrayLike,
    ) -> int:
        """Add M edges at once: indices (M,), (M,), measurements (M, 3), information (M, 3, 3).

        All edges are checked before any is added. Returns the index of the first new edge.
        """
        i = np.asarray(edge_i, dtype=np.intp).reshape(-1)
        j = np.asarray(edge_j, dtype=np.intp).reshape(-1)
        z = np.asarray(measurements, dtype=np.float64)
        omega = np.asarray(information, dtype=np.float64)
        count = len(i)
        if len(j) != count or z.shape != (count, 3) or omega.shape != (count, 3, 3):
            raise PoseGraphError(
                f"add_edges needs i (M,), j (M,), measurements (M, 3), information (M, 3, 3); got "
                f"{len(i)}, {len(j)}, {z.shape}, {omega.shape}"
            )
        vertex_count = len(self.vertex_ids)
        bad = (i < 0) | (i >= vertex_count) | (j < 0) | (j >= vertex_count)
        if bad.any():
            k = int(np.argmax(bad))
            raise PoseGraphError(f"edge {i[k]}->{j[k]} names a vertex index outside 0..{vertex_count - 1}")
        if (i == j).any():
            k = int(np.argmax(i == j))
            raise PoseGraphError(f"edge {i[k]}->{j[k]} joins a vertex to itself")
        if not np.all(np.isfinite(z)):
            k = int(np.argmax(~np.all(np.isfinite(z), axis=1)))
            raise PoseGraphError(f"edge {i[k]}->{j[k]}: measurement must be 3 finite numbers, got {z[k].tolist()}")
        bad_information = invalid_information(omega)
        if bad_information.any():
            k = int(np.argmax(bad_information))
            raise PoseGraphError(
                f"edge {i[k]}->{j[k]}: information must be a finite, symmetric, positive semi-definite 3x3 "
                f"matrix, got {omega[k].tolist()}"
            )
        first = self._edge_count
        self._edge_chunks.append((i.copy(), j.copy(), z.copy(), omega.copy()))
        self._edge_count += count
        return first

    def index_of(self, vertex_id: int) -> int:
        """Index of the vertex with external id ``vertex_id``."""
        try:
            return self._index_of_id[vertex_id]
        except KeyError:
            raise PoseGraphError(f"no vertex with id {vertex_id} in the graph") from None

    # ------------------------------------------------------------------ views

    @property
    def vertices(self) -> FloatArray:
        """All poses as an (N, 3) float64 array (x_m, y_m, theta_rad).

        A view: edits write through, until the next ``add_vertex`` may reallocate.
        """
        return self._pose_buffer[: len(self.vertex_ids)]

    @vertices.setter
    def vertices(self, value: npt.ArrayLike) -> None:
        array = np.asarray(value, dtype=np.float64)
        if array.shape != (len(self.vertex_ids), 3):
            raise PoseGraphError(f"expected poses of shape ({len(self.vertex_ids)}, 3), got {array.shape}")
        self._pose_buffer[: len(array)] = array

    @property
    def edge_arrays(self) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
        """Edges as arrays ``(i (M,), j (M,), measurements (M, 3), information (M, 3, 3))``; do not modify."""
        if len(self._edge_chunks) != 1:
            if not self._edge_chunks:
                return (np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros((0, 3)), np.zeros((0, 3, 3)))
            joined = tuple(np.concatenate(parts) for parts in zip(*self._edge_chunks, strict=True))
            self._edge_chunks = [joined]  # type: ignore[list-item]
        return self._edge_chunks[0]

    @property
    def edges(self) -> list[Edge]:
        """The edges as ``Edge`` records (copies; use ``add_edge`` to change the graph)."""
        edge_i, edge_j, z, omega = self.edge_arrays
        ends = zip(edge_i.tolist(), edge_j.tolist(), strict=True)
        return [Edge(a, b, z[k].copy(), omega[k].copy()) for k, (a, b) in enumerate(ends)]

    def __len__(self) -> int:
        return len(self.vertex_ids)

    @property
    def edge_count(self) -> int:
        return self._edge_count

    def __repr__(self) -> str:
        return f"PoseGraph({len(self)} vertices, {self.edge_count} edges, fixed={sorted(self.fixed)})"

    # ------------------------------------------------------------------ cost

    def residuals(self) -> FloatArray:
        """Residuals ``e_ij`` of every edge at the current poses, shape (M, 3)."""
        edge_i, edge_j, z, _ = self.edge_arrays
        return edge_residuals(self.vertices, edge_i, edge_j, z)

    def chi2(self) -> float:
        """``F(x) = Σ e_ijᵀ Ω_ij e_ij``: the sum of squared Mahalanobis residuals, the cost Algorithm 1 minimizes."""
        if self.edge_count == 0:
            return 0.0
        return float(np.sum(_chi2_terms(self.residuals(), self.edge_arrays[3])))

    # ------------------------------------------------------------------ optimization

    def optimize(
        self,
        max_iterations: int = 50,
        method: Literal["lm", "gn"] = "lm",
        fixed: Sequence[int] | None = None,
        relative_tolerance: float = 1e-6,
        step_tolerance: float = 1e-10,
        initial_damping: float = 1e-5,
    ) -> OptimizeResult:
        """Move the poses to a (local) minimum of ``chi2``; updates ``vertices`` in place.

        ``method`` is ``"lm"`` (Levenberg–Marquardt: takes a step only if it lowers
        ``chi2``) or ``"gn"`` (plain Gauss–Newton as in Algorithm 1: one factorization per
        iteration, but may diverge from a poor initial guess). ``fixed`` lists vertex
        indices held in place; default: the graph's ``fixed`` set, or vertex 0 if that is
        empty. The run stops when a step changes ``chi2`` by less than
        ``relative_tolerance`` (relative), when every component of a step is below
        ``step_tolerance`` (m, rad), or after ``max_iterations`` linearizations.
        ``initial_damping`` is LM's first ``λ`` (units of ``H``).

        Raises ``PoseGraphError`` for bad arguments or a part of the graph that no fixed
        vertex anchors (its poses would be undetermined).
        """
        if method not in ("lm", "gn"):
            raise PoseGraphError(f"method must be 'lm' or 'gn', got {method!r}")
        if max_iterations < 0:
            raise PoseGraphError(f"max_iterations must be >= 0, got {max_iterations}")
        if not (relative_tolerance >= 0.0 and step_tolerance >= 0.0 and initial_damping > 0.0):
            raise PoseGraphError("tolerances must be >= 0 and initial_damping > 0")
        start_s = time.perf_counter()
        anchors = sorted(self.fixed) if fixed is None else sorted({int(v) for v in fixed})
        if not anchors and len(self):
            anchors = [0]
        system = _NormalEquations(self, anchors)
        x = self.vertices.copy()
        chi2_before = system.chi2(x)
        if system.variable_count == 0 or max_iterations == 0 or chi2_before == 0.0:
            return OptimizeResult(0, chi2_before, chi2_before, True, time.perf_counter() - start_s, 0, method)
        settings = _Settings(max_iterations, relative_tolerance, step_tolerance, initial_damping)
        if method == "gn":
            outcome = system.gauss_newton(x, chi2_before, settings)
        else:
            outcome = system.levenberg_marquardt(x, chi2_before, settings)
        self.vertices = outcome.vertices
        return OptimizeResult(
            iterations=outcome.iterations,
            chi2_before=chi2_before,
            chi2_after=outcome.chi2,
            converged=outcome.converged,
            seconds=time.perf_counter() - start_s,
            linear_solves=outcome.linear_solves,
            method=method,
        )


# --------------------------------------------------------------------------- linear system


class _NormalEquations:
    """``H Δx = -b`` for one graph structure: pattern, ordering and scatter map built once.

    Construction (once per ``optimize``):

    1. number the free vertices; anchored ones get no variables (Algorithm 1, step 5,
       done by removing their rows and columns instead of adding a prior);
    2. list every scalar entry the edge blocks ``H_ii, H_ij, H_ji, H_jj`` add to
       (Algorithm 1, step 3: each edge touches 4 blocks);
    3. compute a fill-reducing ordering of the pose adjacency graph (minimum degree on
       the N_free x N_free block pattern, expanded to 3x3 blocks), so the sparse LU
       keeps the factor sparse and can use the natural order every iteration;
    4. map every entry, in permuted coordinates, to its slot of the CSC ``data`` array.

    Each iteration then only computes values and scatters them with ``np.bincount``.
    """

    def __init__(self, graph: PoseGraph, anchors: Sequence[int]) -> None:
        vertex_count = len(graph)
        for v in anchors:
            if not 0 <= v < vertex_count:
                raise PoseGraphError(f"fixed vertex index {v} is outside 0..{vertex_count - 1}")
        self.edge_i, self.edge_j, self.measurements, self.information = graph.edge_arrays
        free = np.ones(vertex_count, dtype=bool)
        free[list(anchors)] = False
        self.free_vertices = np.flatnonzero(free)
        block_of_vertex = np.full(vertex_count, -1, dtype=np.intp)
        block_of_vertex[self.free_vertices] = np.arange(len(self.free_vertices))
        self.block_i = block_of_vertex[self.edge_i]
        self.block_j = block_of_vertex[self.edge_j]
        self.variable_count = 3 * len(self.free_vertices)
        if self.variable_count == 0:
            return
        self._check_anchored(graph, anchors)

        blocks = len(self.free_vertices)
        order = self._block_ordering(blocks)
        # position of each free pose in the factorization order
        block_position = np.empty(blocks, dtype=np.intp)
        block_position[order] = np.arange(blocks)
        pos_i = np.where(self.block_i >= 0, block_position[np.maximum(self.block_i, 0)], -1)
        pos_j = np.where(self.block_j >= 0, block_position[np.maximum(self.block_j, 0)], -1)

        # block pattern: the 3x3 blocks ii, ij, ji, jj of every edge, plus every diagonal block
        edge_count = len(self.edge_i)
        block_rows = np.concatenate((pos_i, pos_i, pos_j, pos_j))
        block_cols = np.concatenate((pos_i, pos_j, pos_i, pos_j))
        valid = (block_rows >= 0) & (block_cols >= 0)  # blocks touching a fixed pose do not exist
        diagonal = np.arange(blocks)
        keys = np.concatenate((block_cols[valid] * blocks + block_rows[valid], diagonal * (blocks + 1)))
        unique_keys, block_slot = np.unique(keys, return_inverse=True)  # sorted by column, then row
        slot_col = unique_keys // blocks
        slot_row = unique_keys % blocks
        column_start = np.searchsorted(slot_col, np.arange(blocks + 1))  # block CSC indptr
        column_count = np.diff(column_start)

        # expand to scalars: scalar column 3c+k lists rows 3r+a of every block (r, c) in order, so
        # entry (a, k) of the q-th block of block column c sits at 9·start_c + 3k·count_c + 3q + a
        q = np.arange(len(unique_keys)) - column_start[slot_col]
        count = column_count[slot_col]
        three = np.arange(3)
        a_index = three[None, :, None]
        k_index = three[None, None, :]
        position = (9 * column_start[slot_col] + 3 * q)[:, None, None] + 3 * k_index * count[:, None, None] + a_index
        self.nnz = 9 * len(unique_keys)
        self.indices = np.empty(self.nnz, dtype=np.int32)
        self.indices[position.reshape(-1)] = np.broadcast_to(
            3 * slot_row[:, None, None] + a_index, position.shape
        ).reshape(-1)
        self.indptr = np.empty(self.variable_count + 1, dtype=np.int32)
        self.indptr[:-1] = (9 * column_start[:-1, None] + 3 * three * column_count[:, None]).reshape(-1)
        self.indptr[-1] = self.nnz
        self.diagonal_slots = position[block_slot[valid.sum() :]][:, three, three].reshape(-1)
        # where each entry of the (4, M, 3, 3) stack [H_ii, H_ij, H_ji, H_jj] lands in the CSC data
        # array; entries of blocks that touch a fixed pose go to one extra slot, dropped after the sum
        slot = np.full((4 * edge_count, 3, 3), self.nnz, dtype=np.intp)
        slot[valid] = position[block_slot[: valid.sum()]]
        self.slot = slot.reshape(-1)

        # b scatter: the variable of each entry of the (2, M, 3) stack [b_i, b_j]; fixed ones to slot n
        grad_index = 3 * np.concatenate((pos_i, pos_j))[:, None] + three
        grad_index[np.concatenate((pos_i, pos_j)) < 0] = self.variable_count
        self.grad_index = grad_index.reshape(-1)
        self.permuted_free = self.free_vertices[order]

    def _check_anchored(self, graph: PoseGraph, anchors: Sequence[int]) -> None:
        """Refuse graphs with a connected component that holds no fixed vertex (singular H)."""
        vertex_count = len(graph)
        adjacency = csc_matrix(
            (np.ones(len(self.edge_i)), (self.edge_i, self.edge_j)), shape=(vertex_count, vertex_count)
        )
        _, labels = csgraph.connected_components(adjacency, directed=False)
        anchored = np.zeros(labels.max() + 1, dtype=bool)
        anchored[labels[list(anchors)]] = True
        loose = np.flatnonzero(~anchored[labels])
        if len(loose):
            raise PoseGraphError(
                f"{len(loose)} vertices (e.g. id {graph.vertex_ids[loose[0]]}) are not connected to a fixed vertex; "
                "add edges or fix one vertex of each part"
            )

    def _block_ordering(self, blocks: int) -> IntArray:
        """Fill-reducing order of the free poses: SuperLU's minimum degree on ``AᵀA`` of the pose graph.

        Ordering 3x3 blocks instead of scalars keeps each pose's variables together (a
        smaller ordering problem and denser supernodes). The values are a diagonally
        dominant stand-in: only the pattern matters for the ordering.
        """
        ok = (self.block_i >= 0) & (self.block_j >= 0)
        rows = np.concatenate([self.block_i[ok], self.block_j[ok], np.arange(blocks)])
        cols = np.concatenate([self.block_j[ok], self.block_i[ok], np.arange(blocks)])
        degree = np.bincount(rows, minlength=blocks).astype(np.float64)
        values = np.concatenate([-np.ones(2 * ok.sum()), degree + 1.0])
        pattern = csc_matrix((values, (rows, cols)), shape=(blocks, blocks))
        pattern.sum_duplicates()
        lu = splu(
            pattern,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            relax=1,
            panel_size=8,
            options={"SymmetricMode": True},
        )
        # Pr A Pc = LU with Pc[k, perm_c[k]] = 1: old column k goes to position perm_c[k]
        order = np.empty(blocks, dtype=np.intp)
        order[lu.perm_c] = np.arange(blocks)
        return order

    # ------------------------------------------------------------------ per iteration

    def chi2(self, x: FloatArray) -> float:
        if len(self.edge_i) == 0:
            return 0.0
        e = edge_residuals(x, self.edge_i, self.edge_j, self.measurements)
        return float(np.sum(_chi2_terms(e, self.information)))

    def linearize(self, x: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        """CSC data of ``H``, the vector ``b`` (both permuted) and ``chi2`` at ``x``.

        Algorithm 1, steps 2–4, vectorized: ``H_ii += AᵀΩA``, ``H_ij += AᵀΩB``,
        ``H_ji += BᵀΩA``, ``H_jj += BᵀΩB``, ``b_i += AᵀΩe``, ``b_j += BᵀΩe``.
        """
        e, a, b = edge_jacobians(x, self.edge_i, self.edge_j, self.measurements)
        omega = self.information
        edge_count = len(e)
        a_t = a.transpose(0, 2, 1)
        b_t = b.transpose(0, 2, 1)
        omega_b = omega @ b
        blocks = np.empty((4, edge_count, 3, 3))
        np.matmul(a_t, omega @ a, out=blocks[0])
        np.matmul(a_t, omega_b, out=blocks[1])
        blocks[2] = blocks[1].transpose(0, 2, 1)  # H_ji = H_ijᵀ
        np.matmul(b_t, omega_b, out=blocks[3])
        h_data = np.bincount(self.slot, weights=blocks.reshape(-1), minlength=self.nnz + 1)[: self.nnz]

        omega_e = np.einsum("mij,mj->mi", omega, e)
        grads = np.empty((2, edge_count, 3))
        np.einsum("mji,mj->mi", a, omega_e, out=grads[0])
        np.einsum("mji,mj->mi", b, omega_e, out=grads[1])
        gradient = np.bincount(self.grad_index, weights=grads.reshape(-1), minlength=self.variable_count + 1)
        chi2 = float(np.einsum("mi,mi->", e, omega_e))
        return h_data, gradient[: self.variable_count], chi2

    def solve(self, h_data: FloatArray, gradient: FloatArray) -> FloatArray | None:
        """Solve ``H Δ = -b`` (permuted coordinates) with SuperLU; None if ``H`` is singular.

        The matrix is already in fill-reducing order, so SuperLU runs with the natural
        column order and diagonal pivots (``SymmetricMode``), which keeps the symmetric
        structure: effectively a sparse LDLᵀ without CHOLMOD. ``relax=3`` (supernodes of
        one pose) and ``panel_size=8`` were measured about 1.5x faster than SuperLU's
        defaults on both benchmark graphs.
        """
        n = self.variable_count
        matrix = csc_matrix((h_data, self.indices, self.indptr), shape=(n, n))
        try:
            factor = splu(
                matrix,
                permc_spec="NATURAL",
                diag_pivot_thresh=0.0,
                relax=3,
                panel_size=8,
                options={"SymmetricMode": True},
            )
        except RuntimeError:  # "Factor is exactly singular"
            return None
        step = factor.solve(-gradient)
        if not np.all(np.isfinite(step)):
            return None
        return step

    def apply(self, x: FloatArray, step: FloatArray) -> FloatArray:
        """``x ⊞ Δx``: right-compose each free pose with its increment (Algorithm 1, step 7, on the manifold)."""
        out = x.copy()
        out[self.permuted_free] = compose(x[self.permuted_free], step.reshape(-1, 3))
        return out

    # ------------------------------------------------------------------ solvers

    def gauss_newton(self, x: FloatArray, chi2: float, settings: _Settings) -> _Outcome:
        """Algorithm 1 as written: every step is taken, whatever it does to ``chi2``."""
        for iteration in range(1, settings.max_iterations + 1):
            h_data, gradient, chi2 = self.linearize(x)
            step = self.solve(h_data, gradient)
            if step is None:
                raise PoseGraphError("the linear system is singular; Gauss-Newton cannot continue (try method 'lm')")
            candidate = self.apply(x, step)
            new_chi2 = self.chi2(candidate)
            if not np.isfinite(new_chi2):  # diverged: keep the last finite poses
                return _Outcome(x, chi2, iteration, iteration, False)
            x = candidate
            if abs(chi2 - new_chi2) <= settings.relative_tolerance * chi2 or _tiny(step, settings):
                return _Outcome(x, new_chi2, iteration, iteration, True)
            chi2 = new_chi2
        return _Outcome(x, chi2, settings.max_iterations, settings.max_iterations, False)

    def levenberg_marquardt(self, x: FloatArray, chi2: float, settings: _Settings) -> _Outcome:
        """Damped Gauss–Newton with Nielsen's update of ``λ`` (Madsen et al. 2004, Algorithm 3.16).

        Solves ``(H + λ I) Δx = -b``. The gain ratio ``ρ`` compares the actual decrease of
        ``chi2`` with the decrease of the damped quadratic model,
        ``L(0) - L(Δx) = -bᵀΔx + λ ΔxᵀΔx`` (``chi2`` is twice Madsen's ``F``, hence no ½).
        An accepted step (``ρ > 0``) scales ``λ`` by ``max(1/3, 1 - (2ρ - 1)³)`` and resets
        ``ν = 2``; a rejected one multiplies ``λ`` by ``ν`` and doubles ``ν``.

        ``λ₀`` is absolute (``settings.initial_damping``, 1e-5 as GTSAM's default) rather
        than Madsen's ``τ · max(diag H)``: loop-closure terms make ``max(diag H)`` grow with
        the square of the initial position errors (2e9 for MITb from odometry), and any
        ``λ`` that large drowns the long, soft modes of a trajectory, so LM would crawl.
        """
        lam = settings.initial_damping
        nu = 2.0
        solves = 0
        for iteration in range(1, settings.max_iterations + 1):
            h_data, gradient, chi2 = self.linearize(x)
            while True:
                damped = h_data.copy()
                damped[self.diagonal_slots] += lam
                step = self.solve(damped, gradient)
                solves += 1
                if step is not None:
                    if _tiny(step, settings):
                        return _Outcome(x, chi2, iteration, solves, True)
                    candidate = self.apply(x, step)
                    new_chi2 = self.chi2(candidate)
                    predicted = _dot(step, lam * step - gradient)
                    if np.isfinite(new_chi2) and new_chi2 < chi2 and predicted > 0.0:
                        rho = (chi2 - new_chi2) / predicted
                        lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), _MIN_DAMPING)
                        nu = 2.0
                        if chi2 - new_chi2 <= settings.relative_tolerance * chi2:
                            return _Outcome(candidate, new_chi2, iteration, solves, True)
                        x = candidate
                        break
                    if predicted <= settings.relative_tolerance * chi2:
                        # the model itself promises no useful decrease: this is a minimum
                        return _Outcome(x, chi2, iteration, solves, True)
                lam *= nu
                nu *= 2.0
                if lam > _MAX_DAMPING:
                    return _Outcome(x, chi2, iteration, solves, False)
        return _Outcome(x, self.chi2(x), settings.max_iterations, solves, False)


_MIN_DAMPING = 1e-12  # keeps λ·ν able to grow after many good steps
_MAX_DAMPING = 1e32  # beyond this the step is zero in float64: give up


@dataclass(frozen=True)
class _Settings:
    max_iterations: int
    relative_tolerance: float
    step_tolerance: float
    initial_damping: float


@dataclass(frozen=True)
class _Outcome:
    vertices: FloatArray
    chi2: float
    iterations: int
    linear_solves: int
    converged: bool


def _dot(a: FloatArray, b: FloatArray) -> float:
    """Dot product without BLAS: OpenBLAS threads ``ddot`` above 10k elements, which costs more than it saves here."""
    return float(np.einsum("i,i->", a, b))


def _tiny(step: FloatArray, settings: _Settings) -> bool:
    """A step whose largest component (m or rad) is below the step tolerance changes nothing."""
    return bool(np.max(np.abs(step)) < settings.step_tolerance)
