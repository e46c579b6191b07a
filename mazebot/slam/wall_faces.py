"""Each wall face's own direction, and how far the faces seen from one place turn apart.

The map's anchor (:mod:`mazebot.slam.wall_priors`) ties the wall grid's direction to the
walls keyframe 0 sees at the start. That holds where every wall lies on one grid (a maze
cut by machine): the faces seen from the start then run in one direction, to the
lidar's noise. In a maze built by hand each board is set at its own small angle (a few
tenths of a degree), and the mean direction of the two to four faces seen from the start
is off the maze's mean grid by about as much: tied to it, the whole map turns about the
start by that error (0.6° on a 6×6 maze measured: 2 cm at its far side, a one-cell band
of cells beside every wall painted occupied).

So the faces seen at rest are measured one by one: surface points split by the grid
axis their normal faces, then into faces by gaps across and along; each long enough face
gets its own direction by least squares (the line's slope against the grid axis), kept
only if its standard error is small, so that the lidar's noise over a short stretch does
not pose as a turned board. The spread of those directions about their mean says whether
the faces lie on one grid (:func:`face_spread`).
"""

from __future__ import annotations

import math

import numpy as np

#: A point belongs to a grid axis's faces if its normal lies within this of the axis
#: (the smoothed normals of a face scatter by a few degrees; a post's round side does not
#: stay within it for long).
AXIS_TOLERANCE_RAD = math.radians(15.0)

#: Points of one axis more than this apart across the face (after sorting) lie on different
#: faces: two parallel boards are at least a wall's thickness (6 mm) apart, one board's face
#: spreads by the A1's range noise (~1 % of 0.1-0.5 m, smoothed onto local lines).
FACE_GAP_ACROSS_M = 0.004

#: ... and points of one face more than this apart along it are two faces (a gap at a post,
#: a shadow): each is its own board.
FACE_GAP_ALONG_M = 0.05

#: A face needs this many points ...
FACE_MIN_POINTS = 20

#: ... over at least this length: a near wall that the lidar's 0.15 m minimum range splits
#: into two short halves shows each half turned by up to ±0.5° from the ends' smoothing.
FACE_MIN_LENGTH_M = 0.12

#: A face's direction counts only if its least-squares standard error is within this
#: (0.1°): below the boards' turns of a hand-built maze, above the A1's noise over a
#: well-seen face.
FACE_MAX_STDERR_RAD = math.radians(0.1)


def face_turns(points: np.ndarray, normals: np.ndarray, grid_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Each face's turn from the grid direction ``grid_rad`` (radians, counter-clockwise) and its point count.

    ``points`` (N, 2) and ``normals`` (N, 2) are surface points of one place (a keyframe's
    frame); ``grid_rad`` the wall grid's direction in that frame (modulo 90°). Returns
    ``(turns_rad (F,), points (F,))`` for the faces that pass the module's tests.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
    c, s = math.cos(grid_rad), math.sin(grid_rad)
    u = c * pts[:, 0] + s * pts[:, 1]
    v = -s * pts[:, 0] + c * pts[:, 1]
    nu = c * nrm[:, 0] + s * nrm[:, 1]
    nv = -s * nrm[:, 0] + c * nrm[:, 1]
    cos_tol = math.cos(AXIS_TOLERANCE_RAD)
    turns: list[float] = []
    counts: list[int] = []
    # faces across u (normal along ±u: the line runs along v) and across v (the line runs along u);
    # a line u = a + b v is the v axis turned by -atan(b), a line v = a + b u the u axis turned by +atan(b)
    for across, along, normal, sign in ((u, v, nu, -1.0), (v, u, nv, 1.0)):
        for side in (1.0, -1.0):
            keep = side * normal >= cos_tol
            for a, b in _faces(across[keep], along[keep]):
                fitted = _slope(a, b)
                if fitted is not None:
                    turns.append(sign * math.atan(fitted))
                    counts.append(a.size)
    return np.array(turns), np.array(counts, dtype=np.intp)


def face_spread(turns_rad: np.ndarray, counts: np.ndarray) -> float | None:
    """The faces' turns' RMS about their mean, weighted by points (radians); None below two faces."""
    turns = np.asarray(turns_rad, dtype=np.float64)
    if turns.size < 2:
        return None
    weights = np.asarray(counts, dtype=np.float64)
    mean = float(np.average(turns, weights=weights))
    return math.sqrt(float(np.average((turns - mean) ** 2, weights=weights)))


def _faces(across: np.ndarray, along: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The points of one axis and side split into faces: by gaps across, then by gaps along."""
    faces = []
    order = np.argsort(across)
    across, along = across[order], along[order]
    for part in np.split(np.arange(across.size), np.flatnonzero(np.diff(across) > FACE_GAP_ACROSS_M) + 1):
        a, b = across[part], along[part]
        by_along = np.argsort(b)
        a, b = a[by_along], b[by_along]
        for piece in np.split(np.arange(b.size), np.flatnonzero(np.diff(b) > FACE_GAP_ALONG_M) + 1):
            if piece.size >= FACE_MIN_POINTS and b[piece[-1]] - b[piece[0]] >= FACE_MIN_LENGTH_M:
                faces.append((a[piece], b[piece]))
    return faces


def _slope(across: np.ndarray, along: np.ndarray) -> float | None:
    """The slope of ``across`` against ``along`` by least squares, or None if its standard error is too large."""
    centred = along - along.mean()
    spread = float(centred @ centred)
    slope = float(centred @ (across - across.mean())) / spread
    residual = across - across.mean() - slope * centred
    stderr = math.sqrt(float(residual @ residual) / max(1, across.size - 2) / spread)
    if math.atan(stderr) > FACE_MAX_STDERR_RAD:
        return None
    return slope
