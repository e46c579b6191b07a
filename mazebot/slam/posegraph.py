"""2D pose graph and its sparse least-squares optimizer (Gauss–Newton / Levenberg–Marquardt).

Why one module of ~1050 lines: the graph, its initialisation (headings first, then positions)
and its sparse Gauss-Newton / Levenberg-Marquardt solver work on the same edge arrays and the
same assembled normal equations (:class:`_NormalEquations`), and they are checked together
against GTSAM on the M3500 and MITb graphs; the module reads as the tutorial's one algorithm
with its initialisation in front.

The method is that of Grisetti, Kümmerle, Stachniss & Burgard, "A Tutorial on
Graph-Based SLAM", IEEE Intelligent Transportation Systems Magazine 2(4), 2010; its
Algorithm 1 is reproduced in section III.B of Nayak et al., *2D Autonomous Mapping*, and the step
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

Initialization from a poor guess (``initialize_orientations``, or
``optimize(initialize="orientations")``): LM only finds the minimum of the basin it
starts in, and a wrong heading early in a trajectory bends everything after it, so from
a poor initial guess it can stall in a local minimum far above the optimum. Orientations
are the non-convex part of the problem; given them, positions are a linear
least-squares problem. So, as in the rotation initialization surveyed by Carlone, Tron,
Daniilidis & Dellaert, "Initialization techniques for 3D SLAM: a survey on rotation
estimation and its use in pose graph optimization", ICRA 2015, and in its planar
ancestor LAGO (Carlone, Aragues, Castellanos & Bona, "A fast and accurate approximation
for planar pose graph optimization", IJRR 33(7), 2014):

1. headings alone: every edge says ``θ_j - θ_i = z_θ + 2π k_ij`` for an unknown
   integer ``k_ij``. Headings composed along a spanning tree (breadth-first from the
   fixed vertices, only measured rotations) fix every ``k_ij``: tree edges get 0, every
   other edge the multiple of 2π that brings its residual along the tree nearest to 0.
   With the ``k_ij`` known the problem is linear, ``min Σ w_ij (θ_j - θ_i - z_θ - 2π k_ij)²``
   over unwrapped reals, a weighted graph Laplacian solved sparse; ``w_ij`` is the
   rotation's marginal information ``1 / Σ_θθ = Ω_θθ - Ω_θtᵀ Ω_tt⁺ Ω_tθ`` (``Ω_θθ`` for
   the usual block-diagonal ``Ω``);
2. positions given those headings: ``e_ij`` is then affine in the translations, so the
   ``chi2`` minimizer over all translations is one sparse linear solve (each edge adds
   ``K = R(θ_i + z_θ) Ω_tt R(θ_i + z_θ)ᵀ`` to a block Laplacian);
3. LM (or GN) from there corrects what the linear steps neglect (the coupling of heading
   and position errors).

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
from typing import Literal, cast

import numpy as np
import numpy.typing as npt
from scipy.sparse import csc_matrix, csgraph, csr_matrix
from scipy.sparse.linalg import splu

from mazebot.errors import UsageError
from mazebot.geometry import compose, inverse, relative_pose, wrap_angle

__all__ = [
    "Edge",
    "InitializeResult",
    "OptimizeResult",
    "PoseGraph",
    "PoseGraphError",
    "compose",
    "edge_jacobians",
    "edge_residuals",
    "estimate_headings",
    "invalid_information",
    "inverse",
    "relative_pose",
    "rotation_information",
    "wrap_angle",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

TWO_PI = 2.0 * np.pi


class PoseGraphError(UsageError):
    """The graph cannot be optimized as given (unanchored vertices, bad indices, singular system)."""


# --------------------------------------------------------------------------- edges


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
    initialize: str = "none"
    chi2_initialized: float | None = None  # chi2 after the initialization, before the first iteration
    initialize_seconds: float = 0.0  # part of ``seconds``


@dataclass(frozen=True)
class InitializeResult:
    """What one ``PoseGraph.initialize_orientations`` call did.

    ``wrapped_edges`` counts the edges whose heading constraint the spanning tree moved
    by a non-zero multiple of 2π.
    """

    chi2_before: float
    chi2_after: float
    seconds: float
    wrapped_edges: int


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
        measurements = np.reshape(np.asarray(measurement, dtype=np.float64), (1, -1))
        first = self.add_edges([i], [j], measurements, np.asarray(omega)[None])
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
        initialize: Literal["none", "orientations"] = "none",
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

        ``initialize="orientations"`` first replaces the initial guess by
        ``initialize_orientations`` (headings, then positions, by linear least squares;
        see the module docstring); use it when the initial guess may be poor. Its time
        is part of ``seconds``; ``chi2_before`` stays the cost of the poses as given and
        ``chi2_initialized`` is the cost after the initialization.

        Raises ``PoseGraphError`` for bad arguments or a part of the graph that no fixed
        vertex anchors (its poses would be undetermined).
        """
        if method not in ("lm", "gn"):
            raise PoseGraphError(f"method must be 'lm' or 'gn', got {method!r}")
        if initialize not in ("none", "orientations"):
            raise PoseGraphError(f"initialize must be 'none' or 'orientations', got {initialize!r}")
        if max_iterations < 0:
            raise PoseGraphError(f"max_iterations must be >= 0, got {max_iterations}")
        if not (relative_tolerance >= 0.0 and step_tolerance >= 0.0 and initial_damping > 0.0):
            raise PoseGraphError("tolerances must be >= 0 and initial_damping > 0")
        start_s = time.perf_counter()
        anchors = self._anchors(fixed)
        system = _NormalEquations(self, anchors)
        x = self.vertices.copy()
        chi2_before = system.chi2(x)
        chi2_start = chi2_before
        chi2_initialized = None
        initialize_s = 0.0
        if initialize == "orientations" and system.variable_count and chi2_before > 0.0:
            init_start_s = time.perf_counter()
            x, _ = _initial_guess(x, system, anchors)
            chi2_start = chi2_initialized = system.chi2(x)
            initialize_s = time.perf_counter() - init_start_s
        if system.variable_count == 0 or max_iterations == 0 or chi2_start == 0.0:
            self.vertices = x
            seconds = time.perf_counter() - start_s
            return OptimizeResult(
                0, chi2_before, chi2_start, True, seconds, 0, method, initialize, chi2_initialized, initialize_s
            )
        settings = _Settings(max_iterations, relative_tolerance, step_tolerance, initial_damping)
        if method == "gn":
            outcome = system.gauss_newton(x, chi2_start, settings)
        else:
            outcome = system.levenberg_marquardt(x, chi2_start, settings)
        self.vertices = outcome.vertices
        return OptimizeResult(
            iterations=outcome.iterations,
            chi2_before=chi2_before,
            chi2_after=outcome.chi2,
            converged=outcome.converged,
            seconds=time.perf_counter() - start_s,
            linear_solves=outcome.linear_solves,
            method=method,
            initialize=initialize,
            chi2_initialized=chi2_initialized,
            initialize_seconds=initialize_s,
        )

    def initialize_orientations(self, fixed: Sequence[int] | None = None) -> InitializeResult:
        """Replace the poses by a fresh initial guess built from the measurements alone.

        Headings first (linear least squares over the angles, unwrapped along a
        breadth-first spanning tree from the fixed vertices), then positions given those
        headings (linear least squares); the method is in the module docstring. Only
        the fixed vertices' poses are read from the current guess; they do not move.
        ``fixed`` as in ``optimize``. Follow with ``optimize()`` to reach the optimum.

        Raises ``PoseGraphError`` for a part of the graph that no fixed vertex anchors,
        or if the translations are not determined by the edges' information.
        """
        start_s = time.perf_counter()
        anchors = self._anchors(fixed)
        system = _NormalEquations(self, anchors)  # checks the anchors and the connectivity
        x = self.vertices.copy()
        chi2_before = system.chi2(x)
        if system.variable_count == 0 or len(system.edge_i) == 0:
            return InitializeResult(chi2_before, chi2_before, time.perf_counter() - start_s, 0)
        x, turns = _initial_guess(x, system, anchors)
        self.vertices = x
        seconds = time.perf_counter() - start_s
        return InitializeResult(chi2_before, system.chi2(x), seconds, int(np.count_nonzero(turns)))

    def _anchors(self, fixed: Sequence[int] | None) -> list[int]:
        """The vertices held in place: ``fixed``, else the graph's ``fixed`` set, else vertex 0."""
        anchors = sorted(self.fixed) if fixed is None else sorted({int(v) for v in fixed})
        if not anchors and len(self):
            anchors = [0]
        return anchors


# --------------------------------------------------------------------------- initialization


def rotation_information(information: FloatArray) -> FloatArray:
    """Information of each edge's rotation alone, shape (M,): ``1 / Σ_θθ = Ω_θθ - Ω_θtᵀ Ω_tt⁺ Ω_tθ``.

    The Schur complement of the translation block: what the edge says about the heading
    once its translation is left free. It is ``Ω_θθ`` when ``Ω`` is block diagonal (the
    usual case); 0 for an edge that measures no rotation.
    """
    weight = information[:, 2, 2].copy()
    cross = information[:, :2, 2]
    coupled = np.flatnonzero(np.any(cross != 0.0, axis=1))
    if len(coupled):
        pinv = np.linalg.pinv(information[coupled][:, :2, :2])
        weight[coupled] -= np.einsum("mi,mij,mj->m", cross[coupled], pinv, cross[coupled])
    scale = np.max(np.abs(information), axis=(1, 2)) if len(information) else np.zeros(0)
    weight[weight <= 1e-12 * scale] = 0.0  # round-off of an edge without rotation information
    return weight


def _roots(vertex_count: int, edge_i: IntArray, edge_j: IntArray, anchors: Sequence[int]) -> IntArray:
    """The anchors plus the first vertex of every connected part (of these edges) without one, sorted."""
    adjacency = csr_matrix((np.ones(len(edge_i)), (edge_i, edge_j)), shape=(vertex_count, vertex_count))
    _, labels = csgraph.connected_components(adjacency, directed=False)
    anchored = np.zeros(labels.max() + 1, dtype=bool)
    anchored[labels[list(anchors)]] = True
    _, first = np.unique(labels, return_index=True)
    return np.union1d(np.asarray(anchors, dtype=np.intp), first[~anchored]).astype(np.intp)


def _in_order(vertices: IntArray, order: IntArray | None) -> IntArray:
    """``vertices`` sorted by their position in the elimination ``order`` (those not in it last); as given if None."""
    if order is None:
        return vertices
    rank = np.full(int(max(vertices.max(initial=-1), order.max(initial=-1))) + 1, len(order), dtype=np.intp)
    rank[order] = np.arange(len(order))
    return vertices[np.argsort(rank[vertices], kind="stable")]


def _solve_spd(matrix: csr_matrix, rhs: FloatArray, ordered: bool) -> FloatArray | None:
    """Solve a sparse symmetric positive definite system with diagonal pivots; None if singular.

    ``ordered``: the rows are already in a fill-reducing order; otherwise SuperLU's
    minimum degree orders them.
    """
    try:
        factor = splu(
            csc_matrix(matrix),
            permc_spec="NATURAL" if ordered else "MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:  # "Factor is exactly singular"
        return None
    solution = factor.solve(rhs)
    return solution if np.all(np.isfinite(solution)) else None


def estimate_headings(
    vertex_count: int,
    edge_i: IntArray,
    edge_j: IntArray,
    rotations: FloatArray,
    weights: FloatArray,
    anchors: Sequence[int],
    poses: FloatArray,
    order: IntArray | None = None,
) -> tuple[FloatArray, IntArray]:
    """Headings from the relative rotations alone: ``(θ (N,) unwrapped, k (M,) turns per edge)``.

    Step 1 of the initialization (module docstring). ``rotations`` are the edges'
    measured ``z_θ`` (rad), ``weights`` their rotation information (1/rad², 0 = edge
    ignored, see ``rotation_information``). The anchors keep their heading from
    ``poses``; so does the first vertex of any part of the graph that the weighted
    edges do not join to an anchor (it is the gauge of that part). Every other pose's
    heading is the weighted least-squares solution of ``θ_j - θ_i = z_θ + 2π k_ij``,
    where ``k_ij`` makes the edge agree, to within π, with the headings composed
    along a breadth-first spanning tree from the anchors; the tree edges get ``k = 0``.
    ``order`` is a fill-reducing elimination order of the vertices for the sparse
    solve (default: minimum degree, computed here).
    """
    used = weights > 0.0
    ui, uj, uz, uw = edge_i[used], edge_j[used], rotations[used], weights[used]
    roots = _roots(vertex_count, ui, uj, anchors)

    # breadth-first tree from a virtual vertex S joined to every root, so a forest of several anchors is one tree
    s = vertex_count
    rows = np.concatenate((ui, np.full(len(roots), s)))
    cols = np.concatenate((uj, roots))
    adjacency = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(s + 1, s + 1))
    _, parent = csgraph.breadth_first_order(adjacency, s, directed=False, return_predecessors=True)
    parent[s] = s
    # the edge behind each tree link (parent, child): of parallel edges, the one with the most rotation information
    key = np.minimum(ui, uj).astype(np.int64) * vertex_count + np.maximum(ui, uj)
    by_key = np.lexsort((-uw, key))
    child = np.flatnonzero(parent[:s] != s)
    link = np.minimum(parent[child], child).astype(np.int64) * vertex_count + np.maximum(parent[child], child)
    edge = by_key[np.searchsorted(key[by_key], link)]
    # climb[v]: heading of v minus heading of up[v]; pointer jumping sums the tree path in log2(depth) passes
    climb = np.zeros(s + 1)
    climb[child] = np.where(ui[edge] == parent[child], uz[edge], -uz[edge])
    climb[roots] = poses[roots, 2]
    up = parent
    while np.any(up != s):
        climb = climb + climb[up]
        up = up[up]
    tree = climb[:s]

    turns = np.zeros(len(edge_i), dtype=np.intp)
    turns_used = np.round((tree[uj] - tree[ui] - uz) / TWO_PI).astype(np.intp)
    turns[used] = turns_used
    target = uz + TWO_PI * turns_used
    free = np.ones(vertex_count, dtype=bool)
    free[roots] = False
    free_index = _in_order(np.flatnonzero(free), order)
    headings = tree.copy()
    if len(free_index) == 0:
        return headings, turns
    # weighted graph Laplacian Σ w (e_j - e_i)(e_j - e_i)ᵀ and right side Σ w target (e_j - e_i)
    laplacian = csr_matrix(
        (np.concatenate((uw, uw, -uw, -uw)), (np.concatenate((ui, uj, ui, uj)), np.concatenate((ui, uj, uj, ui)))),
        shape=(vertex_count, vertex_count),
    )
    rhs = np.bincount(uj, uw * target, vertex_count) - np.bincount(ui, uw * target, vertex_count)
    free_rows = laplacian[free_index]
    solution = _solve_spd(
        free_rows[:, free_index], rhs[free_index] - free_rows[:, roots] @ tree[roots], order is not None
    )
    if solution is None:  # cannot happen: every part holds a fixed root, so the reduced Laplacian is definite
        raise PoseGraphError("the heading system is singular")
    headings[free_index] = solution
    return headings, turns


def _positions_given_headings(
    poses: FloatArray,
    headings: FloatArray,
    edge_i: IntArray,
    edge_j: IntArray,
    measurements: FloatArray,
    information: FloatArray,
    anchors: Sequence[int],
    order: IntArray | None = None,
) -> FloatArray:
    """Step 2 of the initialization: the translations minimizing ``chi2`` for fixed headings; returns new poses.

    With ``θ`` fixed, ``e_t = G (t_j - t_i) - g`` with ``G = R(θ_i + z_θ)ᵀ`` and
    ``g = R(z_θ)ᵀ z_t``, and ``e_θ = c`` is a constant, so an edge's cost
    ``e_tᵀ Ω_tt e_t + 2 c e_tᵀ Ω_tθ + const`` has the normal equations
    ``K (t_j - t_i) = Gᵀ (Ω_tt g - c Ω_tθ)`` with ``K = Gᵀ Ω_tt G``, assembled into a
    2N x 2N block Laplacian. The anchors (and the first vertex of any part that the
    translation-measuring edges leave unanchored) keep their positions.
    """
    vertex_count = len(poses)
    used = np.any(information[:, :2, :2] != 0.0, axis=(1, 2))
    ei, ej, z, omega = edge_i[used], edge_j[used], measurements[used], information[used]
    omega_tt = omega[:, :2, :2]
    omega_tq = omega[:, :2, 2]
    roots = _roots(vertex_count, ei, ej, anchors)
    phi = headings[ei] + z[:, 2]
    rot = np.empty((len(ei), 2, 2))  # Gᵀ = R(θ_i + z_θ)
    rot[:, 0, 0] = rot[:, 1, 1] = np.cos(phi)
    rot[:, 1, 0] = np.sin(phi)
    rot[:, 0, 1] = -rot[:, 1, 0]
    block = rot @ omega_tt @ rot.transpose(0, 2, 1)
    cos_z = np.cos(z[:, 2])
    sin_z = np.sin(z[:, 2])
    g = np.column_stack((cos_z * z[:, 0] + sin_z * z[:, 1], -sin_z * z[:, 0] + cos_z * z[:, 1]))
    angle_error = wrap_angle(headings[ej] - headings[ei] - z[:, 2])
    pull = np.einsum("mij,mj->mi", rot, np.einsum("mij,mj->mi", omega_tt, g) - angle_error[:, None] * omega_tq)

    two = np.arange(2)
    first = np.stack((ei, ej, ei, ej))[:, :, None, None]
    second = np.stack((ei, ej, ej, ei))[:, :, None, None]
    rows = np.broadcast_to(2 * first + two[:, None], (4, len(ei), 2, 2))
    cols = np.broadcast_to(2 * second + two, (4, len(ei), 2, 2))
    values = np.array([1.0, 1.0, -1.0, -1.0])[:, None, None, None] * block
    size = 2 * vertex_count
    matrix = csr_matrix((values.reshape(-1), (rows.reshape(-1), cols.reshape(-1))), shape=(size, size))
    rhs = np.bincount((2 * ej[:, None] + two).reshape(-1), pull.reshape(-1), size) - np.bincount(
        (2 * ei[:, None] + two).reshape(-1), pull.reshape(-1), size
    )
    fixed_vars = (2 * roots[:, None] + two).reshape(-1)
    free = np.ones(vertex_count, dtype=bool)
    free[roots] = False
    free_vars = (2 * _in_order(np.flatnonzero(free), order)[:, None] + two).reshape(-1)
    translations = poses[:, :2].reshape(-1).copy()
    if len(free_vars):
        free_rows = matrix[free_vars]
        reduced_rhs = rhs[free_vars] - free_rows[:, fixed_vars] @ translations[fixed_vars]
        solution = _solve_spd(free_rows[:, free_vars], reduced_rhs, order is not None)
        if solution is None:
            raise PoseGraphError(
                "the edges' translation information does not determine every position; cannot initialize"
            )
        translations[free_vars] = solution
    out = np.column_stack((translations.reshape(vertex_count, 2), wrap_angle(headings)))
    out[list(anchors)] = poses[list(anchors)]
    return out


def _initial_guess(poses: FloatArray, system: _NormalEquations, anchors: Sequence[int]) -> tuple[FloatArray, IntArray]:
    """Headings, then positions, from the measurements (module docstring): ``(new poses (N, 3), turns k (M,))``.

    Both sparse solves reuse the optimizer's fill-reducing order of the free poses.
    """
    edge_i, edge_j, z, omega = system.edge_i, system.edge_j, system.measurements, system.information
    weights = rotation_information(omega)
    order = system.permuted_free
    headings, turns = estimate_headings(len(poses), edge_i, edge_j, z[:, 2], weights, anchors, poses, order)
    return _positions_given_headings(poses, headings, edge_i, edge_j, z, omega, anchors, order), turns


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
        # np.bincount with float weights gives floats (its stubs say integers)
        return cast(FloatArray, h_data), cast(FloatArray, gradient[: self.variable_count]), chi2

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
