"""A heading bias shared by every sequential match, estimated from a finished pose graph's loops.

A scan matcher can turn every match a little the same way in the robot's frame: on the
Seattle laser log each sequential edge turns about a hundredth of a degree more than the
finished map does, going west along its first corridor and coming back east alike. Along
one corridor the chain then bends, and the bend is in the chain's own edges, so nothing
the chain measures shows it. Loop closures do: a turn of the same sense bends the pass
out one way in the map and the pass back the other way, and the closures between the
passes meet them where their counts balance (two passes west and one east keep a third of
the westward bend). What is left of the bend turns the whole map about its start.

The bias is estimated as one more unknown of the graph's headings, the way the planar
pose graph's orientations are estimated apart from its positions (Carlone et al., "A fast
and accurate approximation for planar pose graph optimization", IJRR 2014): linearized
about the optimized poses, every edge says ``θ_j − θ_i = z_θ − β s`` (``s`` 1 for a
sequential edge, 0 for a closure), weighted by the edge's rotation information. Its
standard error is the normal matrix's, scaled by the fit's variance factor where that
exceeds 1 (Förstner's a-posteriori variance of unit weight): the edges' own claims when
the graph fits within them, wider when it does not. A bias is a systematic error of the
matcher, so estimating it with the poses is self-calibration, as a camera's own parameters
are estimated in bundle adjustment (Triggs et al., "Bundle adjustment — a modern synthesis",
2000).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csc_matrix
from scipy.sparse.linalg import splu

from mazebot.geometry import wrap_angle
from mazebot.slam.posegraph import rotation_information


@dataclass(frozen=True)
class HeadingBias:
    """The sequential edges' shared heading bias ``bias_rad`` (their measured turn minus the map's), its
    standard error ``std_rad`` and the heading fit's variance factor (chi² over redundancy)."""

    bias_rad: float
    std_rad: float
    variance_factor: float

    def significant(self, sigmas: float) -> bool:
        """Whether the bias exceeds ``sigmas`` standard errors (``sigmas`` 0: never, the option is off)."""
        return sigmas > 0 and abs(self.bias_rad) > sigmas * self.std_rad


def sequential_heading_bias(
    vertices: np.ndarray,
    edge_i: np.ndarray,
    edge_j: np.ndarray,
    measurements: np.ndarray,
    information: np.ndarray,
    sequential: np.ndarray,
) -> HeadingBias | None:
    """The heading bias shared by the ``sequential`` edges, jointly with the headings, vertex 0 held.

    ``vertices`` (N, 3) the optimized poses, the edges ``(i, j, z, Ω)`` as the pose graph holds them.
    None when the heading fit has no redundancy beyond the bias (no loop to measure it by) or the
    bias is not observable (no sequential edge, or every loop made of sequential edges alone).
    """
    poses = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    ei, ej = np.asarray(edge_i, dtype=np.intp), np.asarray(edge_j, dtype=np.intp)
    z = np.asarray(measurements, dtype=np.float64).reshape(-1, 3)
    weight = rotation_information(np.asarray(information, dtype=np.float64).reshape(-1, 3, 3))
    seq = np.asarray(sequential, dtype=bool)
    used = weight > 0
    ei, ej, z, weight, seq = ei[used], ej[used], z[used], weight[used], seq[used]
    count = poses.shape[0]
    redundancy = len(ei) - (count - 1) - 1
    if redundancy <= 0 or not np.any(seq):
        return None
    residual = wrap_angle(z[:, 2] - (poses[ej, 2] - poses[ei, 2]))
    # unknowns: the heading corrections of vertices 1..N-1 (columns 0..N-2) and the bias (column N-1)
    rows = np.arange(len(ei))
    entries = [(rows[ej > 0], ej[ej > 0] - 1, np.ones(int(np.count_nonzero(ej > 0)))),
               (rows[ei > 0], ei[ei > 0] - 1, -np.ones(int(np.count_nonzero(ei > 0)))),
               (rows[seq], np.full(int(np.count_nonzero(seq)), count - 1), np.ones(int(np.count_nonzero(seq))))]
    r = np.concatenate([e[0] for e in entries])
    c = np.concatenate([e[1] for e in entries])
    v = np.concatenate([e[2] for e in entries])
    design = csc_matrix((v, (r, c)), shape=(len(ei), count))
    normal = (design.T @ design.multiply(weight[:, None])).tocsc()
    try:
        factor = splu(normal)
    except RuntimeError:  # singular: the bias is not observable apart from the headings
        return None
    solution = factor.solve(design.T @ (weight * residual))
    unit = np.zeros(count)
    unit[-1] = 1.0
    variance = float(factor.solve(unit)[-1])
    if not math.isfinite(variance) or variance <= 0:
        return None
    misfit = residual - design @ solution
    variance_factor = float(np.sum(weight * misfit**2)) / redundancy
    return HeadingBias(float(solution[-1]), math.sqrt(variance * max(1.0, variance_factor)), variance_factor)
